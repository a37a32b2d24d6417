"""The camera's off-axis terms (`diffcam.model.off_axis`) fitted to a capture's light
profiles through a PSF stack measured on axis, and the sensor's angular response written
as a shift-invariant model: a sensor window, widened PSFs and a weighted scene.

NumPy and SciPy, like the rest of `diffcam.io`'s preprocessing: the profile model is
`diffcam.io.preprocessing.fit_sensor_window`'s, with every source's PSF changed by the
terms."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from diffcam.core.errors import DiffcamError, number_in, real_array, whole_number
from diffcam.io.preprocessing import (PROFILE_ROWS, bin_samples, l1_solution, light_profiles,
                                      optical_axis, sampled_planes)

__all__ = ["FIELD_TERMS", "FieldTerms", "fit_field_terms", "AcceptanceSplit",
           "acceptance_split"]


FIELD_TERMS = ("aperture_distance", "acceptance_exponent", "vignetting_exponent")
"""The off-axis terms of `diffcam.model.camera.Camera` (`diffcam.model.off_axis`) that
[`fit_field_terms`][diffcam.io.field_terms.fit_field_terms] fits."""
_EXPONENT_BOUNDS = {"acceptance_exponent": 500.0, "vignetting_exponent": 50.0}


class FieldTerms(NamedTuple):
    """A camera's off-axis terms fitted to a capture's light profiles
    ([`fit_field_terms`][diffcam.io.field_terms.fit_field_terms]), in the units of
    `diffcam.model.camera.Camera`'s fields, and what they leave unexplained.

    Attributes:
        aperture_distance: metres, the stop's distance in front of the diffuser (d).
        acceptance_exponent: unitless, p of the pixels' response ``cos^p θ``.
        vignetting_exponent: unitless, n of the irradiance's fall ``cos^n θ1``.
        misfit: unitless ``(rows, columns)``, ``||A s - p|| / ||p||`` of each profile's
            fit.
        light: unitless, the fitted scene's light (``Σ s``, both profiles) relative to
            the same fit without the terms.
    """

    aperture_distance: float
    acceptance_exponent: float
    vignetting_exponent: float
    misfit: tuple[float, float]
    light: float


class _Profile(NamedTuple):
    """One axis of the profile fit: the capture's profile (unit norm, binned), the fitted
    planes' profiles, the optical axis on the sensor and in the PSF frame (pixels)."""

    target: np.ndarray
    planes: np.ndarray
    sensor_axis: float
    psf_axis: float
    factor: int

    @classmethod
    def of(cls, image, psfs, fitted):
        profile, planes, centres = light_profiles(image, psfs)
        psf_axis = optical_axis(planes, centres)
        factor = -(-planes.shape[1] // PROFILE_ROWS)
        target = bin_samples(profile, factor)
        return cls(target / np.linalg.norm(target), planes[fitted],
                   psf_axis + image.shape[0] // 2 - planes.shape[1] // 2, psf_axis, factor)

    def matrix(self, magnification, angle, shift, p, n) -> np.ndarray:
        """``A``: column ``(t, c)`` is the profile on the sensor of a source whose chief
        ray is ``c`` pixels from the axis, through plane ``t`` (magnification ``M_t``)
        with the terms (``angle`` radians per pixel, ``shift`` the shadow's extra
        displacement per pixel of chief ray, ``p``, ``n``), binned."""
        n_out, m = self.factor * len(self.target), self.planes.shape[1]
        y = np.arange(n_out) - self.sensor_axis
        c = np.arange(-self.sensor_axis - m, n_out - self.sensor_axis + m)
        blocks = []
        for plane, mag, g in zip(self.planes, magnification, shift):
            u = y[:, None] - c[None, :] * (1 + g)         # pixels from the PSF's axis
            h = np.interp(u + self.psf_axis, np.arange(m), plane, left=0, right=0)
            tilt = angle * (y[:, None] * (mag - 1) + c[None, :]) / mag
            calibration = angle * u * (mag - 1) / mag
            log_w = -0.5 * p * (tilt ** 2 - calibration ** 2) - 0.5 * n * (angle * c) ** 2
            block = bin_samples(h * np.exp(np.minimum(log_w, 600)), self.factor)
            blocks.append(bin_samples(block.T, self.factor).T)
        return np.hstack(blocks)


def fit_field_terms(image: np.ndarray, psfs: np.ndarray, z1, z2: float,
                    pixel_pitch: float, free=FIELD_TERMS, samples: int = 5,
                    light_weight: float = 0.02) -> FieldTerms:
    """The camera's off-axis terms (`diffcam.model.off_axis`) that make a PSF stack,
    measured on axis, explain a capture's row and column light profiles.

    The profile model of ``fit_sensor_window`` with every source's PSF changed by the
    terms: a source whose chief ray is ``c`` pixels from the optical axis (sensor
    distance ``y``) lights pixel ``y`` at ``tan θ = q (y (M - 1) + c) / M`` (``q`` =
    pitch / z2, ``M = 1 + z2/z1``) where the calibration's on-axis source lit the same
    PSF pixel at ``tan θ0 = q u (M - 1) / M`` (``u`` the pixel's distance from the PSF's
    axis); the pixels' response weighs it by ``A(θ)/A(θ0)`` with ``A = cos^p θ ≈
    exp(-p tan²θ / 2)`` (the form separates in y and x, so each profile sees it alone);
    the stop's shadow moves the PSF's footprint ``d M / z2`` pixels further per pixel of
    chief ray; vignetting weighs the source by ``cos^n θ1 ≈ exp(-n (q c)² / 2)``. The
    terms in ``free`` minimise the sum over both profiles of ``½ ||A s - p||² + λ Σ s``
    (``s >= 0``; ``λ`` a share ``light_weight`` of the weight that empties the fit
    without terms, whose largest column norm sets the units of ``s``, so that dimmed
    sources cost light), bounded (d < min z1 / 2, p ≤ 500, n ≤ 50), Powell's method.
    Only ``p q²``, ``n q²`` and ``d / z2`` are identifiable beside the planes'
    magnifications.

    Args:
        image: ``(ny, nx)`` capture, counts (bias subtracted).
        psfs: ``(nz, my, mx)`` non-negative PSF stack, ``my <= ny``, ``mx <= nx``, on
            the sensor's pixels (the crop model's centring).
        z1: ``(nz,)`` metres, each plane's source distance from the diffuser.
        z2: metres, the diffuser-to-sensor distance.
        pixel_pitch: metres, the sensor's pixel pitch (of the images given).
        free: the name, or names, of the terms fitted (of `FIELD_TERMS`); the others
            stay 0.
        samples: planes in the fit (at least 1, at most ``nz``).
        light_weight: ``λ`` as a share of the emptying weight, in (0, 1).

    Returns:
        [`FieldTerms`][diffcam.io.field_terms.FieldTerms].
    """
    from scipy.optimize import minimize  # SciPy on first use: fast package import

    free, z1, z2, pixel_pitch = _field_inputs(psfs, free, z1, z2, pixel_pitch)
    samples = whole_number("samples", samples, 1)
    light_weight = number_in("light_weight", light_weight, 1e-6, 1 - 1e-6,
                             "a share of the emptying weight in (0, 1)")
    fitted = sampled_planes(len(z1), samples)
    mag = 1 + z2 / z1[fitted]
    axes = [_Profile.of(image, psfs, fitted), _Profile.of(
        np.asarray(image).T, np.swapaxes(np.asarray(psfs), 1, 2), fitted)]
    q = pixel_pitch / z2
    base = [a.matrix(mag, q, 0 * mag, 0, 0) for a in axes]
    units = [np.linalg.norm(b, axis=0).max() for b in base]
    weights = [light_weight * np.max(b.T @ a.target) / u for a, b, u in zip(axes, base, units)]
    bounds = {"aperture_distance": (0.0, 0.5 * z1.min()), **{
        k: (0.0, v) for k, v in _EXPONENT_BOUNDS.items()}}

    upper = np.array([bounds[k][1] for k in free])

    def solve(x):       # x²: the free terms as shares of their upper bounds
        terms = dict.fromkeys(FIELD_TERMS, 0.0) | dict(zip(free, np.square(x) * upper))
        out = []
        for a, u, w in zip(axes, units, weights):
            matrix = a.matrix(mag, q, terms["aperture_distance"] * mag / z2,
                              terms["acceptance_exponent"], terms["vignetting_exponent"]) / u
            s = l1_solution(matrix, a.target, w)
            r = matrix @ s - a.target
            out.append((0.5 * r @ r + w * s.sum(), float(np.linalg.norm(r)), s.sum()))
        return terms, out

    light0 = sum(o[2] for o in solve(np.zeros(len(free)))[1])
    x = (minimize(lambda x: sum(o[0] for o in solve(x)[1]), np.zeros(len(free)),
                  method="Powell", bounds=[(0.0, 1.0)] * len(free),
                  options={"xtol": 1e-2}).x if free else ())
    terms, out = solve(np.asarray(x))
    return FieldTerms(**{k: float(v) for k, v in terms.items()},
                      misfit=(out[0][1], out[1][1]),
                      light=float(sum(o[2] for o in out) / light0))


def _field_inputs(psfs, free, z1, z2, pixel_pitch):
    """``fit_field_terms``'s geometry checked: the free terms as a tuple, ``z1`` a
    float64 ``(nz,)`` array beyond ``0``, ``z2`` and the pitch positive floats."""
    free = (free,) if isinstance(free, str) else tuple(free)
    if not set(free) <= set(FIELD_TERMS) or len(set(free)) != len(free):
        raise DiffcamError(f"free must name distinct terms of {FIELD_TERMS}; got {free}.")
    z2 = number_in("z2", z2, 1e-9, 1.0, "a distance in metres, > 0")
    pixel_pitch = number_in("pixel_pitch", pixel_pitch, 1e-9, 1e-2,
                            "a pixel pitch in metres, > 0")
    z1 = np.asarray(real_array("z1", z1), np.float64).reshape(-1)
    nz = np.shape(psfs)[0] if np.ndim(psfs) == 3 else None
    if len(z1) != nz or not (np.isfinite(z1).all() and (z1 > 0).all()):
        raise DiffcamError(f"z1 must give one positive distance in metres per PSF plane "
                           f"({nz}); got {len(z1)} value(s) (least {z1.min(initial=0):.3g}).")
    return free, z1, z2, pixel_pitch


class AcceptanceSplit(NamedTuple):
    """The sensor's angular response as a shift-invariant model
    ([`acceptance_split`][diffcam.io.field_terms.acceptance_split]).

    Attributes:
        window: unitless ``(ny, nx)``, the sensor window ``S`` (a solver's
            ``sensor_response``).
        psfs: ``(nz, my, mx)``, the PSF planes widened by ``exp(+β_z |u|² / 2)``.
        scene_scale: pixels⁻² ``(nz,)``: the solved volume is the scene times
            ``exp(-scene_scale_z |c|²)`` (``c`` a voxel's pixels from the axis).
        axis: pixels ``(y, x)``, the optical axis on the sensor.
    """

    window: np.ndarray
    psfs: np.ndarray
    scene_scale: np.ndarray
    axis: tuple[float, float]


def acceptance_split(psfs: np.ndarray, sensor_shape, acceptance_exponent: float, z1,
                     z2: float, pixel_pitch: float) -> AcceptanceSplit:
    """The field-dependent model of a pixel response ``A = cos^p θ ≈ exp(-p tan²θ / 2)``
    (the geometry of [`fit_field_terms`][diffcam.io.field_terms.fit_field_terms]) as
    one sensor window, widened PSFs and a scene weight.

    A source whose chief ray is ``c`` (pixels from the axis) lights sensor pixel ``y =
    u + c`` through plane ``z`` times ``A(θ)/A(θ0) = exp(-β y²/2) · exp(β u²/2) ·
    exp(-p q² c² / 2M)``, ``β = p q² (M - 1)/M``, ``q`` = pitch / z2: a field-dependent PSF
    that is exactly a window on the sensor, each PSF widened, and the scene weighted.
    The window takes the planes' mean ``β`` (the planes' own differ from it by
    ``(M_z - M̄)/M̄``-sized shares); the widening each plane's.

    Args:
        psfs: ``(nz, my, mx)`` PSF stack measured on axis, sensor pixels.
        sensor_shape: ``(ny, nx)`` of the capture, ``ny >= my``, ``nx >= mx``.
        acceptance_exponent: unitless, ``p``.
        z1: ``(nz,)`` metres; ``z2``: metres; ``pixel_pitch``: metres.

    Returns:
        [`AcceptanceSplit`][diffcam.io.field_terms.AcceptanceSplit].
    """
    _, z1, z2, pixel_pitch = _field_inputs(psfs, (), z1, z2, pixel_pitch)
    p = number_in("acceptance_exponent", acceptance_exponent, 0.0,
                  _EXPONENT_BOUNDS["acceptance_exponent"], "unitless, in 0 … 500")
    psfs = np.asarray(psfs, np.float64)
    ny, nx = (int(n) for n in sensor_shape)
    centre = np.array([ny // 2 - psfs.shape[1] // 2, nx // 2 - psfs.shape[2] // 2])
    psf_axis = np.array([optical_axis(*light_profiles(psfs[0], psfs)[1:]), optical_axis(
        *light_profiles(psfs[0].T, np.swapaxes(psfs, 1, 2))[1:])])
    mag = 1 + z2 / z1
    pq2 = p * (pixel_pitch / z2) ** 2
    beta = pq2 * (mag - 1) / mag
    y, x = (np.arange(n)[:, None] for n in (ny, nx))
    sensor_axis = psf_axis + centre
    r2 = (y - sensor_axis[0]) ** 2 + (x.T - sensor_axis[1]) ** 2
    u2 = ((np.arange(psfs.shape[1])[:, None] - psf_axis[0]) ** 2
          + (np.arange(psfs.shape[2])[None] - psf_axis[1]) ** 2)
    return AcceptanceSplit(np.exp(-0.5 * beta.mean() * r2).astype(np.float32),
                           (psfs * np.exp(0.5 * beta[:, None, None] * u2)).astype(np.float32),
                           pq2 / (2 * mag), (float(sensor_axis[0]), float(sensor_axis[1])))
