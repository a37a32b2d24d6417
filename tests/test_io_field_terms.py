"""The camera's off-axis terms fitted to a capture's light profiles, and the sensor
response written as a window, widened PSFs and a weighted scene (diffcam.io.field_terms:
fit_field_terms, acceptance_split)."""

import numpy as np
import pytest

from diffcam.core.errors import DiffcamError
from diffcam.io import acceptance_split, fit_field_terms

NY, NX, M = 30, 32, 20
PITCH, Z2 = 30e-6, 1e-3                 # 0.03 rad per pixel
Z1 = np.array([2e-3, 2.5e-3, 3e-3])     # magnifications 1.5, 1.4, 1.33
AXIS = (M - 1) / 2                      # the PSFs' centroid: the stack's optical axis


def _stack():
    """Three disc footprints about the PSF centre (radius 8 px), random textures
    symmetric about it (so their centroid is the axis)."""
    rng = np.random.default_rng(1)
    r = np.hypot(*np.meshgrid(np.arange(M) - AXIS, np.arange(M) - AXIS, indexing="ij"))
    texture = rng.uniform(0.2, 1.0, (len(Z1), M, M))
    return (r < 8) * (texture + texture[:, ::-1, ::-1])


def _sources(seed=2, n=30):
    """(plane, top-left row, top-left column, brightness) of point sources whose chief
    rays lie within ±10 px of the axis."""
    rng = np.random.default_rng(seed)
    centre = (NY // 2 - M // 2, NX // 2 - M // 2)       # the PSF placed on the axis
    return [(rng.integers(len(Z1)), centre[0] + rng.integers(-10, 11),
             centre[1] + rng.integers(-10, 11), rng.uniform(1, 3)) for _ in range(n)]


def _capture(psfs, p, sources, cos_power=True):
    """Each source's PSF placed on the sensor, times the response ratio of every pixel:
    ``A(θ)/A(θ0)`` with ``tan θ`` the ray from the source (``cos^p``, or its Gaussian
    form ``exp(-p tan²θ / 2)``), summed point by point."""
    q = PITCH / Z2
    axis = np.array([AXIS + NY // 2 - M // 2, AXIS + NX // 2 - M // 2])
    image = np.zeros((NY, NX))
    y, x = np.meshgrid(np.arange(NY), np.arange(NX), indexing="ij")
    for z, top, left, s in sources:
        mag = 1 + Z2 / Z1[z]
        c = np.array([top, left]) + AXIS - axis             # chief ray, pixels from the axis
        placed = np.zeros((NY + 2 * M, NX + 2 * M))
        placed[M + top:2 * M + top, M + left:2 * M + left] = psfs[z]
        h = placed[M:M + NY, M:M + NX]
        yy, xx = y - axis[0], x - axis[1]
        t2 = q ** 2 * ((yy * (mag - 1) + c[0]) ** 2 + (xx * (mag - 1) + c[1]) ** 2) / mag ** 2
        t02 = q ** 2 * (mag - 1) ** 2 * ((yy - c[0]) ** 2 + (xx - c[1]) ** 2) / mag ** 2
        ratio = ((1 + t02) / (1 + t2)) ** (p / 2) if cos_power else np.exp(-p / 2 * (t2 - t02))
        image += s * h * ratio
    return image


def test_fit_recovers_a_known_sensor_response():
    """A capture made point by point with a pixel response cos^100 θ (angles up to
    about 0.3 rad): the fitted exponent within 20 % of 100 (89: the fit's Gaussian form
    and its L1 term bias it low), and the term explains the profiles better than none."""
    psfs, sources = _stack(), _sources()
    image = _capture(psfs, 100.0, sources)
    fitted = fit_field_terms(image, psfs, Z1, Z2, PITCH, free=("acceptance_exponent",),
                             light_weight=1e-3)
    without = fit_field_terms(image, psfs, Z1, Z2, PITCH, free=(), light_weight=1e-3)
    assert abs(fitted.acceptance_exponent / 100.0 - 1) < 0.2, fitted
    assert fitted.aperture_distance == 0 and fitted.vignetting_exponent == 0
    assert sum(fitted.misfit) < 0.4 * sum(without.misfit), (fitted, without)


@pytest.mark.slow
def test_all_three_terms_free_on_a_response_only_capture():
    """Every term free, on the capture made with the response alone: the response is
    found (within 30 % of 100), vignetting stays near 0 (the scene absorbs it)."""
    psfs = _stack()
    fitted = fit_field_terms(_capture(psfs, 100.0, _sources()), psfs, Z1, Z2, PITCH,
                             light_weight=1e-3)
    assert abs(fitted.acceptance_exponent / 100.0 - 1) < 0.3, fitted
    assert fitted.vignetting_exponent < 1.0, fitted


def test_split_is_the_point_by_point_model():
    """The window, the widened planes and the weighted scene give the capture that the
    Gaussian response makes point by point (one plane: the window's β is that plane's)."""
    psfs = _stack()[:1]
    sources = [s for s in _sources(3, 25)]
    sources = [(0,) + s[1:] for s in sources]
    truth = _capture(psfs, 30.0, sources, cos_power=False)
    split = acceptance_split(psfs, (NY, NX), 30.0, Z1[:1], Z2, PITCH)
    model = np.zeros((NY, NX))
    for _, top, left, s in sources:
        c = np.array([top, left]) + AXIS - np.array(split.axis)
        placed = np.zeros((NY + 2 * M, NX + 2 * M))
        placed[M + top:2 * M + top, M + left:2 * M + left] = split.psfs[0]
        model += s * np.exp(-split.scene_scale[0] * (c @ c)) * placed[M:M + NY, M:M + NX]
    np.testing.assert_allclose(split.window * model, truth, rtol=1e-4, atol=1e-6 * truth.max())


@pytest.mark.parametrize("change, message", [
    ({"z1": Z1[:2]}, "one positive distance"),
    ({"z1": -Z1}, "one positive distance"),
    ({"pixel_pitch": -1e-6}, "pixel_pitch"),
    ({"free": ("focus",)}, "free must name"),
    ({"free": "focus"}, r"got \('focus',\)"),      # one name as a string
    ({"light_weight": 2.0}, "light_weight"),
])
def test_bad_input_is_refused(change, message):
    psfs = _stack()
    kwargs = {"z1": Z1, "z2": Z2, "pixel_pitch": PITCH} | change
    with pytest.raises(DiffcamError, match=message):
        fit_field_terms(np.ones((NY, NX)), psfs, **kwargs)


def test_split_refuses_an_exponent_out_of_range():
    with pytest.raises(DiffcamError, match="acceptance_exponent"):
        acceptance_split(_stack(), (NY, NX), -1.0, Z1, Z2, PITCH)
