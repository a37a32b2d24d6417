"""diffcam.design: the surfaces keep their fabrication limits, the objective is the
largest Pearson correlation NumPy computes, its gradient matches finite differences, the
design file round-trips (and its TIFF and its PSFs with it), a continued design ends
where an uninterrupted one does, and a short design lowers the correlation."""

import dataclasses
import json
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tifffile
from jax.test_util import check_grads

from diffcam.apps.cli import main
from diffcam.core.errors import DiffcamError, SamplingError
from diffcam.core.units import parse_length
from diffcam.design import (DepthObjective, DesignOptions, LensletArray, SmoothSurface,
                            depth_objective, depth_range, design, evaluate_design,
                            load_design, save_design, tiff_path)
from diffcam.design.objective import source_blurred
from diffcam.design.surfaces import height_map
from diffcam.model import Camera, HeightMap, psf

# lengths as the command line reads them: its design reuses the tests' compiled steps
N, INDEX = 64, 1.5
DX, FEATURE, H_MAX = (parse_length(t) for t in ("3um", "15um", "1um"))
Z1 = depth_range(10e-3, 60e-3, 4)
OPTIONS = DesignOptions(steps=10, progress=False)


def _camera(dtype=float):
    """The camera; Python floats as the command line gives them (float32 unless x64)."""
    return Camera(wavelength=dtype(532e-9), z2=dtype(1e-3), dx=dtype(DX),
                  aperture_radius=dtype(parse_length("60um")), shape=(N, N))


def _smooth(seed=0):
    return SmoothSurface.random(seed, (N, N), DX, FEATURE, H_MAX)


@pytest.fixture(scope="module")
def designed():
    return design(_smooth(), _camera(), Z1, INDEX, OPTIONS)


@pytest.fixture(scope="module")
def saved(designed, tmp_path_factory):
    path = tmp_path_factory.mktemp("design") / "diffuser.npz"
    save_design(designed, path)
    return path


# ------------------------------------------------------------------- parametrisations

def test_smooth_surface_stays_in_its_height_range_whatever_its_coefficients():
    s = _smooth()
    for scale in (1.0, 1e3):
        h = np.asarray(dataclasses.replace(s, coefficients=s.coefficients * scale).height())
        assert h.min() >= 0 and h.max() <= H_MAX
    h = np.asarray(s.height())
    assert h.max() - h.min() > 0.5 * H_MAX      # the random start spans the range


def test_lenslet_caps_are_spherical_with_bounded_sag():
    """One lens against the spherical cap h = √(R² − r²) − (R − t), R = (a² + t²)/(2t),
    computed in NumPy; its sag t ≤ min(h_max, slope_max·a/2); every height in range."""
    lens = LensletArray(jnp.array([[0.0, 0.0, 3.0, 3.0]]), (N, N), DX, FEATURE, H_MAX,
                        40e-6, 30e-6)
    _, _, t, a = (float(v[0]) for v in lens.lenses())
    assert 0 < t <= min(H_MAX, lens.slope_max * a / 2) + 1e-15
    r_curv = (a ** 2 + t ** 2) / (2 * t)
    g = (np.arange(N) - N // 2) * DX
    r2 = g[:, None] ** 2 + g[None, :] ** 2
    want = np.where(r2 < a ** 2, np.sqrt(np.abs(r_curv ** 2 - r2)) - (r_curv - t), 0.0)
    np.testing.assert_allclose(np.asarray(lens.height()), want, atol=1e-4 * t)
    many = LensletArray.random(3, (N, N), DX, FEATURE, H_MAX, 9, 40e-6)
    h = np.asarray(many.height())
    assert h.min() >= 0 and 0 < h.max() <= H_MAX


def test_limits_are_checked():
    with pytest.raises(DiffcamError, match="two samples"):
        SmoothSurface.random(0, (N, N), DX, 1.5 * DX, H_MAX)
    with pytest.raises(DiffcamError, match="height_max"):
        SmoothSurface.random(0, (N, N), DX, FEATURE, -1e-6)
    with pytest.raises(DiffcamError, match="lenses"):
        LensletArray.random(0, (N, N), DX, FEATURE, H_MAX, 0, 40e-6)
    with pytest.raises(DiffcamError, match="grid"):
        design(SmoothSurface.random(0, (N + 2, N + 2), DX, FEATURE, H_MAX), _camera(), Z1)
    with pytest.raises(DiffcamError, match="2 different depths"):
        design(_smooth(), _camera(), [20e-3, 20e-3])
    with pytest.raises(DiffcamError, match="refractive_index"):
        design(_smooth(), _camera(), Z1, 1.0)
    with pytest.raises(DiffcamError, match="steps"):
        DesignOptions(steps=0)


def test_an_undersampled_geometry_is_refused_with_advice_design_can_follow():
    """z2 = 2 mm on 64 samples of 3 µm: the Fresnel transfer function of z_eff ≈ 1.9 mm
    aliases (N·dx²/λ ≈ 1.08 mm); `design` has no accept_undersampling to suggest."""
    far = dataclasses.replace(_camera(), z2=2e-3)
    with pytest.raises(SamplingError, match="aliases") as raised:
        design(_smooth(), far, Z1, INDEX, OPTIONS)
    assert "accept_undersampling" not in str(raised.value)
    assert "change the camera or the depth range" in str(raised.value)


# --------------------------------------------------------------------------- objective

def test_objective_is_the_largest_pearson_correlation_of_numpy():
    """ρ_max against np.corrcoef of PSFs computed one depth at a time by psf, and the
    smooth maximum within its bound ρ_max ≤ ρ_τ ≤ ρ_max + τ·log(#pairs)."""
    s, cam = _smooth(1), _camera()
    objective = DepthObjective(cam, Z1, INDEX, temperature=0.01)
    terms = evaluate_design(s, objective)
    hm = height_map(s, INDEX)
    psfs = np.stack([np.asarray(psf(hm, cam, z), np.float64).ravel() for z in Z1])
    c = np.corrcoef(psfs)
    want = c[np.triu_indices(len(Z1), 1)].max()
    assert terms["max_correlation"] == pytest.approx(want, abs=2e-6)
    pairs = len(Z1) * (len(Z1) - 1) // 2
    assert want - 1e-6 <= terms["smooth_max"] <= want + 0.01 * np.log(pairs) + 1e-6
    l1_l2 = np.abs(psfs).sum(1) / (np.sqrt(N * N) * np.sqrt((psfs ** 2).sum(1)))
    assert terms["spread"] == pytest.approx(l1_l2.mean(), rel=1e-5)


def test_source_blur_is_the_mean_of_the_disc_points_images():
    """A Gaussian spot (σ 2 px) blurred by a disc of radius 3 px: the mean of the same
    Gaussian, in closed form, at the disc's centre and six rim points (60° apart)."""
    yy, xx = np.mgrid[:N, :N] - N // 2

    def spot(y, x):
        return np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 2.0 ** 2))
    angles = np.arange(6) * np.pi / 3
    points = [(0.0, 0.0)] + [(3 * np.sin(a), 3 * np.cos(a)) for a in angles]
    want = np.mean([spot(y, x) for y, x in points], axis=0)
    got = source_blurred(jnp.asarray(spot(0, 0), jnp.float32), 3.0)
    np.testing.assert_allclose(np.asarray(got), want, atol=2e-5)


@pytest.mark.slow
def test_broadband_disc_source_objective_matches_numpy():
    """ρ_max with a 3-line spectrum and a 20 µm source against np.corrcoef of `psf`'s
    broadband PSFs, each moved to the disc's 7 points (image radius 20 µm·z2/z1) by
    scipy.ndimage.fourier_shift and averaged."""
    from scipy import ndimage
    s, cam = _smooth(1), _camera()
    lines = (cam.wavelength + 6e-9 * np.array([-1.0, 0.0, 1.0]), np.array([0.5, 1.0, 0.5]))
    objective = DepthObjective(cam, Z1, INDEX, spectrum=lines, source_radius=20e-6)
    terms = evaluate_design(s, objective)
    angles = np.arange(6) * np.pi / 3
    unit = np.concatenate([[[0.0, 0.0]], np.stack([np.sin(angles), np.cos(angles)], 1)])
    hm, blurred = height_map(s, INDEX), []
    for z in Z1:
        spectrum = np.fft.fft2(np.asarray(psf(hm, cam, z, spectrum=lines), np.float64))
        shifts = unit * 20e-6 * cam.z2 / (z * cam.dx)
        blurred.append(np.mean([np.fft.ifft2(ndimage.fourier_shift(spectrum, d)).real
                                for d in shifts], axis=0).ravel())
    c = np.corrcoef(np.stack(blurred))
    assert terms["max_correlation"] == pytest.approx(c[np.triu_indices(len(Z1), 1)].max(),
                                                     abs=5e-6)
    assert terms["max_correlation"] > evaluate_design(
        s, DepthObjective(cam, Z1, INDEX))["max_correlation"]


@pytest.mark.slow
def test_pixel_integrated_objective_matches_a_finer_field_binned_by_hand():
    """ρ_max with ``oversample`` 2 against np.corrcoef of `psf` on a hand-made camera of
    half the pitch (the height cubic-interpolated) integrated over each pixel: both
    grids are centred on the axis, so a pixel holds the fine sample at its centre whole
    and the ones on its edges by half (weights ½, 1, ½ per axis). Pixels average detail
    that the centre samples keep, so the correlation differs from the point-sampled
    one."""
    s, cam = _smooth(1), dataclasses.replace(_camera(), pad=(32, 32))
    terms = evaluate_design(s, DepthObjective(cam, Z1, INDEX, oversample=2))
    fine = Camera(wavelength=cam.wavelength, z2=cam.z2, dx=cam.dx / 2,
                  aperture_radius=cam.aperture_radius, shape=(2 * N, 2 * N), pad=64)
    height = jax.image.resize(height_map(s, INDEX).height, (2 * N, 2 * N), "cubic")
    def integrated(a, axis):
        g = np.moveaxis(np.pad(a, [(1, 1) if k == axis else (0, 0) for k in (0, 1)]),
                        axis, 0)
        return np.moveaxis(0.5 * g[0:-2:2] + g[1:-1:2] + 0.5 * g[2::2], 0, axis)
    binned = [integrated(integrated(np.asarray(psf(HeightMap(height, INDEX), fine, z),
                                               np.float64), 0), 1).ravel() for z in Z1]
    c = np.corrcoef(np.stack(binned))[np.triu_indices(len(Z1), 1)].max()
    assert terms["max_correlation"] == pytest.approx(c, abs=5e-6)
    point = evaluate_design(s, DepthObjective(cam, Z1, INDEX))["max_correlation"]
    assert abs(point - c) > 1e-4


def test_light_source_and_pixel_options_are_checked():
    with pytest.raises(DiffcamError, match="bandwidth must be ≥ 0"):
        DesignOptions(bandwidth=-1e-9)
    with pytest.raises(DiffcamError, match="oversample"):
        DesignOptions(oversample=0)
    o = DesignOptions(bandwidth=6e-9, source_radius=50e-6, oversample=2)
    assert o.problem()["source_radius"] == 50e-6 and o.problem()["oversample"] == 2


def test_oversampled_design_checks_the_finer_grid():
    """The unpadded camera samples the transfer function at its pitch but not at half
    of it: a pixel-integrated design refuses it and says what to change."""
    with pytest.raises(SamplingError, match="pad"):
        design(_smooth(), _camera(), Z1, INDEX, dataclasses.replace(OPTIONS, oversample=2))


def test_oversampling_a_masked_aperture_is_refused_and_a_factor_of_one_keeps_it():
    """A drawn aperture has no finer grid to be redrawn on: oversampling it is an error,
    while factor 1 (every design without pixel integration) leaves the camera as it is."""
    from diffcam.model.camera import oversampled

    masked = dataclasses.replace(_camera(), aperture_radius=None,
                                 aperture_mask=np.ones(_camera().shape))
    assert oversampled(masked, 1) is masked
    with pytest.raises(DiffcamError, match="circular aperture"):
        oversampled(masked, 2)


@pytest.mark.usefixtures("x64")
@pytest.mark.slow  # 8 s a surface; the objective's value by default (NumPy's Pearson)
@pytest.mark.parametrize("kind", ["smooth", "lenslets"])
def test_gradient_matches_finite_differences(kind):
    """The loss's reverse-mode gradient in the surface's parameters against central
    differences (float64, jax.test_util.check_grads)."""
    cam = _camera(np.float64)  # float64 under x64
    objective = DepthObjective(cam, Z1[:3], INDEX, temperature=0.05)
    if kind == "smooth":
        s = _smooth(2)
        s = dataclasses.replace(s, coefficients=jnp.asarray(s.coefficients, jnp.float64))
        field = "coefficients"
    else:
        s = LensletArray.random(2, (N, N), DX, FEATURE, H_MAX, 4, 40e-6)
        s = dataclasses.replace(s, params=jnp.asarray(s.params, jnp.float64))
        field = "params"

    def loss(p):
        return depth_objective(dataclasses.replace(s, **{field: p}), objective)[0]
    check_grads(jax.jit(loss), (getattr(s, field),), order=1, modes=("rev",), atol=1e-5, rtol=1e-4)


# ------------------------------------------------------------------------ the design

def test_a_short_design_lowers_the_largest_correlation(designed):
    start = evaluate_design(_smooth(), designed.objective())
    assert designed.history[0, 2] == pytest.approx(start["max_correlation"], abs=1e-6)
    assert designed.final["max_correlation"] < start["max_correlation"] - 1e-3
    assert designed.steps == OPTIONS.steps and designed.stop_reason == "10 steps"


def test_continued_design_ends_where_an_uninterrupted_one_does(designed, tmp_path):
    path = tmp_path / "checkpoint.npz"
    half = dataclasses.replace(OPTIONS, steps=4, checkpoint=str(path), checkpoint_every=3)
    design(_smooth(), _camera(), Z1, INDEX, half)
    assert load_design(path).steps == 4
    rest = design(_smooth(), _camera(), Z1, INDEX, dataclasses.replace(half, steps=10))
    np.testing.assert_array_equal(rest.history, designed.history)
    np.testing.assert_array_equal(rest.surface.coefficients, designed.surface.coefficients)
    assert rest.final == designed.final
    other = dataclasses.replace(half, steps=12, temperature=0.02)
    with pytest.raises(DiffcamError, match="another problem"):
        design(_smooth(), _camera(), Z1, INDEX, other)


def test_a_time_budget_stops_the_design(designed):
    """A budget shorter than one step: the design stops after its first step and says
    why (the step budget alone would have run ten)."""
    result = design(_smooth(), _camera(), Z1, INDEX,
                    dataclasses.replace(OPTIONS, time_budget=1e-9))
    assert result.steps == 1 and result.stop_reason.startswith("time budget")
    np.testing.assert_array_equal(result.history, designed.history[:1])


# ------------------------------------------------------------------------- the file

def test_design_file_round_trips_with_its_psfs(designed, saved):
    """The file's height map (design file and TIFF) gives the PSFs the optimiser saw."""
    back = load_design(saved)
    np.testing.assert_array_equal(back.history, designed.history)
    np.testing.assert_array_equal(back.surface.coefficients, designed.surface.coefficients)
    assert back.final == designed.final and back.refractive_index == INDEX
    np.testing.assert_array_equal(back.z1, Z1)
    tiff = tifffile.imread(tiff_path(saved))
    assert tiff.dtype == np.float32
    cam, seen = back.camera, designed.height_map()
    for z in Z1[[0, -1]]:
        want = np.asarray(psf(seen, cam, z))
        for diffuser in (back.height_map(), HeightMap(tiff, INDEX)):
            np.testing.assert_allclose(np.asarray(psf(diffuser, cam, z)), want,
                                       rtol=1e-5, atol=1e-6 * want.max())


def _power_beyond(h, frequency):
    """Share of the height map's power (mean removed) at spatial frequencies above
    ``frequency`` (cycles/m)."""
    h = np.asarray(h, np.float64)
    power = np.abs(np.fft.fft2(h - h.mean())) ** 2
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(N, DX), np.fft.fftfreq(N, DX), indexing="ij"))
    return power[f > frequency].sum() / power.sum()


def test_written_height_map_keeps_its_range_and_feature_size(saved):
    """Measured on the TIFF: heights within [0, h_max], and little of the power at
    periods shorter than 2s (features narrower than s: the cubic B-spline's spectrum is
    sinc⁴(f·s), the logistic squash adds a little), where a surface made the same way
    with features s/2 puts much more."""
    h = tifffile.imread(tiff_path(saved))
    with tifffile.TiffFile(tiff_path(saved)) as tif:
        meta = json.loads(tif.pages[0].description)
    assert meta["unit"] == "m" and meta["surface"]["feature_size"] == FEATURE
    assert 0 <= h.min() and h.max() <= H_MAX
    assert _power_beyond(h, 0.5 / FEATURE) < 0.15
    finer = SmoothSurface.random(0, (N, N), DX, FEATURE / 2, H_MAX).height()
    assert _power_beyond(finer, 0.5 / FEATURE) > 0.3


def test_bad_design_files_are_one_line_errors(saved, tmp_path):
    with pytest.raises(DiffcamError, match="no such file|does not exist|not found"):
        load_design(tmp_path / "missing.npz")
    text = tmp_path / "text.npz"
    text.write_text("not a zip")
    with pytest.raises(DiffcamError, match="not a diffcam design file"):
        load_design(text)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(DiffcamError, match="no array"):
        load_design(other)
    with np.load(saved) as data:
        arrays = dict(data)
    meta = json.loads(str(arrays["metadata"]))
    for change, match in (({"version": 99}, "upgrade diffcam"),
                          ({"format": "diffcam-stack-fit"}, "not a diffcam design file")):
        bad = tmp_path / "bad.npz"
        np.savez(bad, **{**arrays, "metadata": np.array(json.dumps({**meta, **change}))})
        with pytest.raises(DiffcamError, match=match):
            load_design(bad)
    older = dict(meta, version=3, options={k: v for k, v in meta["options"].items()
                                           if k != "oversample"})
    np.savez(tmp_path / "v3.npz", **{**arrays, "metadata": np.array(json.dumps(older))})
    assert load_design(tmp_path / "v3.npz").options.oversample == 1
    edited = tmp_path / "edited.npz"
    np.savez(edited, **{**arrays, "height": arrays["height"] * 0.5})
    with pytest.raises(DiffcamError, match="edited"):
        load_design(edited)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(saved.read_bytes()[: saved.stat().st_size // 2])
    with pytest.raises(DiffcamError):
        load_design(truncated)
    assert zipfile.is_zipfile(saved)


@pytest.mark.slow
def test_lenslet_design_file_carries_the_lens_table(tmp_path):
    lenses = LensletArray.random(4, (N, N), DX, FEATURE, H_MAX, 4, 40e-6)
    result = design(lenses, _camera(), Z1, INDEX, dataclasses.replace(OPTIONS, steps=2))
    path = save_design(result, tmp_path / "mla.npz", tiff=False)
    assert not tiff_path(path).exists()
    with np.load(path) as data:
        table = json.loads(str(data["metadata"]))["lenses"]
    sag, a = np.array(table["sag"]), np.array(table["aperture_radius"])
    radius = np.array(table["radius_of_curvature"])
    np.testing.assert_allclose(radius, (a ** 2 + sag ** 2) / (2 * sag))
    np.testing.assert_allclose(np.array(table["focal_length"]), radius / (INDEX - 1))
    assert isinstance(load_design(path).surface, LensletArray)


CLI_PROBLEM = ["design", "--grid", str(N), "--pixel", "3um", "--aperture", "60um", "--z2",
               "1mm", "--depths", "4", "--feature", "15um", "--height", "1um",
               "--no-progress"]
"""`diffcam design` of the tests' problem (its start is `_smooth`)."""


def test_command_line_writes_the_design_and_its_tiff(tmp_path, capsys):
    out = tmp_path / "cli.npz"
    args = [*CLI_PROBLEM, "--steps", "3", "-o", str(out)]
    assert main(args) == 0
    said = capsys.readouterr().out
    assert "max cross-depth PSF correlation" in said and str(tiff_path(out)) in said
    assert load_design(out).steps == 3 and tiff_path(out).is_file()
    assert main(args[:-3] + ["5", "--resume", "-o", str(out)]) == 0
    assert load_design(out).steps == 5
    assert main(args[:-2] + ["-o", str(tmp_path / "x.txt")]) == 2


class _Stopped(Exception):
    """Raised in place of the optimiser."""


@pytest.mark.parametrize("option, text, field, value", [
    ("--bandwidth", "20nm", "bandwidth", 20e-9),
    ("--source-radius", "50um", "source_radius", 50e-6),
    ("--oversample", "2", "oversample", 2)])
def test_command_line_light_source_and_pixel_options_reach_the_design(
        option, text, field, value, monkeypatch, tmp_path):
    """The option reaches `DesignOptions`, and the camera the command line builds passes
    the design's sampling check with it (2× oversampled, the unpadded camera fails it:
    `test_oversampled_design_checks_the_finer_grid`)."""
    from diffcam.design.optimise import _check

    call = []
    monkeypatch.setattr("diffcam.design.design", lambda *a: call.extend(a) or _raise())
    with pytest.raises(_Stopped):
        main([*CLI_PROBLEM, option, text, "-o", str(tmp_path / "light.npz")])
    surface, camera, z1, index, options = call
    assert getattr(options, field) == pytest.approx(value)
    _check(surface, camera, z1, index, options)


def _raise():
    raise _Stopped


@pytest.mark.slow  # 20–40 s: compiles the design step with all three
def test_command_line_designs_through_the_light_source_and_pixels_it_is_given(tmp_path):
    """The optimiser's first step saw the PSFs of the options: its start correlation is
    their objective's, not the one-line point-source one's."""
    out = tmp_path / "light.npz"
    assert main([*CLI_PROBLEM, "--bandwidth", "20nm", "--source-radius", "50um",
                 "--oversample", "2", "--steps", "1", "-o", str(out)]) == 0
    made = load_design(out)
    seen = made.history[0, 2]
    assert seen == pytest.approx(evaluate_design(_smooth(), made.objective())[
        "max_correlation"], abs=1e-5)
    point = DepthObjective(made.camera, made.z1, INDEX)
    assert abs(seen - evaluate_design(_smooth(), point)["max_correlation"]) > 1e-4


def test_command_line_refuses_light_it_cannot_design_through(tmp_path, capsys):
    out = str(tmp_path / "bad.npz")
    assert main([*CLI_PROBLEM, "--bandwidth", "600nm", "-o", out]) == 2
    said = capsys.readouterr().err
    assert "at most 0.25 of the camera's wavelength" in said and len(said.splitlines()) == 1
    # a source imaged wider than an eighth of the frame (its blur wraps around it)
    assert main([*CLI_PROBLEM, "--source-radius", "1m", "-o", out]) == 2
    assert "wrap around" in capsys.readouterr().err
    assert main([*CLI_PROBLEM, "--bandwidth=-1nm", "-o", out]) == 2
    assert "bandwidth must be ≥ 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*CLI_PROBLEM, "--oversample", "0", "-o", out])
