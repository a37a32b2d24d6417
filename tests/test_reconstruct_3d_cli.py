"""`diffcam reconstruct --3d`: a volume from a raw capture and a PSF stack given as a
file, a folder, a glob or a stack-fit model; its TIFF (with its run record), max
projection, depth map, projections and montage; the residual it prints; dark levels;
and one clear error (exit 2, outputs untouched) for every bad input."""

import json
import re
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
import tifffile
from scipy.signal import fftconvolve

from diffcam.apps.cli import main
from diffcam.io import border_dark_level, natural_key
from diffcam.reconstruct.admm import VOLUME

N, NZ = 32, 3
POINTS = [(0, 8, 10), (1, 20, 22), (2, 12, 24)]  # (plane, y, x): one point per plane
NAMES = ["psf_8.npy", "psf_9.npy", "psf_10.npy"]  # name order would put psf_10 first


def _caustic(seed: int) -> np.ndarray:
    """A 32×32 random caustic: far-field intensity of a smooth random phase screen."""
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(64)
    smooth = np.exp(-(k[:, None] ** 2 + k[None] ** 2) / (2 * 0.04 ** 2))
    phase = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(64, 64))) * smooth))
    pupil = np.hypot(*np.mgrid[-32:32, -32:32]) < 20
    field = np.exp(1j * 40 * phase / phase.std()) * pupil
    intensity = np.abs(np.fft.fftshift(np.fft.fft2(field)))[16:48, 16:48] ** 2
    return (intensity / intensity.sum()).astype(np.float32)


@pytest.fixture
def scene(tmp_path):
    """raw.npy (the sum of each plane's point convolved with its PSF), the PSFs as a
    multi-page TIFF, a folder of .npy planes (plus a non-image file) and a glob."""
    psfs = np.stack([_caustic(s) for s in range(NZ)])
    volume = np.zeros((NZ, N, N), np.float32)
    for z, y, x in POINTS:
        volume[z, y, x] = 1.0
    raw = sum(fftconvolve(volume[z], psfs[z], mode="same") for z in range(NZ))
    np.save(tmp_path / "raw.npy", np.clip(raw, 0, None).astype(np.float32))
    tifffile.imwrite(tmp_path / "psfs.tif", psfs, photometric="minisblack")
    folder = tmp_path / "planes"
    folder.mkdir()
    for name, psf in zip(NAMES, psfs):
        np.save(folder / name, psf)
    (folder / "notes.txt").write_text("not an image")
    return tmp_path, psfs


def _run(*args) -> int:
    return main(["reconstruct", *map(str, args)])


def _volume(path):
    with tifffile.TiffFile(path) as tif:
        return tif.asarray(), tif.series[0].axes, tif.imagej_metadata


def test_volume_puts_each_point_in_its_plane(scene, capsys):
    """The three outputs exist; the TIFF is ZYX float32 with plane labels; each point's
    energy (5×5 window) is > 95 % in its own plane; the PNGs are not blank."""
    from skimage.io import imread

    d, _ = scene
    out = d / "vol.tif"
    assert _run(d / "raw.npy", "--psf", d / "psfs.tif", "--3d", "--method", "rl",
                "--iterations", 200, "-o", out) == 0
    err = capsys.readouterr().err
    assert "reading" in err and "200 iterations" in err and "writing" in err
    volume, axes, meta = _volume(out)
    assert axes == "ZYX" and volume.shape == (NZ, N, N) and volume.dtype == np.float32
    assert meta["Labels"] == ["plane 0", "plane 1", "plane 2"]
    for z, y, x in POINTS:
        energy = volume[:, y - 2:y + 3, x - 2:x + 3].sum(axis=(1, 2))
        assert energy.argmax() == z and energy[z] > 0.95 * energy.sum(), (z, energy)
    mip = imread(d / "vol_max.png")
    assert mip.dtype == np.uint8 and mip.shape == (N, N) and mip.max() == 255
    depth = imread(d / "vol_depth.png")
    assert depth.ndim == 3 and np.ptp(depth[..., :3].astype(int)) > 100  # not one colour
    for name in ("projections", "montage"):
        view = imread(d / f"vol_{name}.png")
        assert view.ndim == 3 and np.ptp(view[..., :3].astype(int)) > 100, name
    info = json.loads(meta["Info"])
    assert info["method"] == "rl" and info["iterations"] == 200 and info["residual"] < 0.1


@pytest.mark.parametrize("envelope", [pytest.param("mask", marks=pytest.mark.slow), "auto"])
def test_printed_residual_is_the_written_volumes(scene, capsys, envelope):
    """ADMM-TV: the residual printed is ||A x - b|| / ||b|| of the volume written
    (--full-field: the whole object grid), recomputed with the forward model it used
    (the sensor window of the σ and centre recorded, or the PSFs with the envelope of
    the widths recorded); the split gap is printed and recorded beside it. The
    --background test covers --psf-envelope none."""
    from diffcam.io import SensorWindow, apply_envelope
    from diffcam.reconstruct import convolution_model
    from diffcam.reconstruct.loop import relative_residual

    d, psfs = scene
    out = d / "vol.tif"
    assert _run(d / "raw.npy", "--psf", d / "psfs.tif", "--3d", "--iterations", 40,
                "--full-field", "--quiet", "--psf-envelope", envelope, "-o", out) == 0
    printed = float(re.search(r"residual ([0-9.eE+-]+)", capsys.readouterr().out).group(1))
    volume, _, meta = _volume(out)
    info = json.loads(meta["Info"])
    widths, sigma = info["psf_envelope_sigma_px"], info["sensor_window_sigma_px"]
    assert info["psf_envelope"] == envelope and (sigma is None) == (envelope == "auto")
    used = psfs if widths is None else apply_envelope(psfs, widths)
    raw = np.load(d / "raw.npy")
    window = 1.0 if sigma is None else SensorWindow(
        info["sensor_window_centre_row_px"], sigma).response(raw.shape)
    model = convolution_model(jnp.asarray(used), raw.shape, "crop", volume=True)
    recomputed = float(relative_residual(window * model(jnp.asarray(volume)), raw))
    assert printed == pytest.approx(recomputed, rel=2e-3, abs=1e-4)
    assert info["residual"] == pytest.approx(recomputed, rel=2e-3, abs=1e-4)
    assert info["split_gap"] >= 0 and info["options"]["balance"] is True
    assert info["options"]["relaxation"] == VOLUME.relaxation
    assert info["options"]["mu2"] == VOLUME.mu2


def test_background_is_recorded_and_fits_with_the_volume(scene, capsys):
    """--background 1 on a capture plus a tilted background: the metadata's Legendre
    coefficients rebuild the solve's background, with which the volume written
    reproduces the residual recorded and printed (recomputed with the forward model)."""
    from diffcam.reconstruct import convolution_model
    from diffcam.reconstruct.sensor_terms import legendre_terms
    from diffcam.reconstruct.loop import relative_residual

    d, psfs = scene
    raw = np.load(d / "raw.npy")
    y, x = np.meshgrid(np.linspace(-1, 1, N), np.linspace(-1, 1, N), indexing="ij")
    tilted = (raw + raw.mean() * (0.5 + 0.2 * y - 0.3 * x)).astype(np.float32)
    np.save(d / "tilted.npy", tilted)
    common = ["--psf", d / "psfs.tif", "--3d", "--iterations", 40, "--full-field",
              "--quiet", "--psf-envelope", "none"]
    assert _run(d / "tilted.npy", *common, "--background", 1, "-o", d / "bg.tif") == 0
    printed = float(re.search(r"residual ([0-9.eE+-]+)", capsys.readouterr().out).group(1))
    assert _run(d / "tilted.npy", *common, "-o", d / "plain.tif") == 0
    volume, _, meta = _volume(d / "bg.tif")
    info = json.loads(meta["Info"])
    record = info["background_counts"]
    assert info["options"]["background"] == 1 and record["legendre_ij"] == [[0, 0], [0, 1],
                                                                            [1, 0]]
    terms = legendre_terms(tilted.shape, 1)[0]
    background = np.tensordot(record["coefficients"], terms, 1)
    model = convolution_model(jnp.asarray(psfs), tilted.shape, "crop", volume=True)
    recomputed = float(relative_residual(model(jnp.asarray(volume)) + background, tilted))
    assert info["residual"] == pytest.approx(recomputed, rel=2e-3, abs=1e-4)
    assert printed == pytest.approx(recomputed, rel=5e-3, abs=1e-4)
    assert record["min"] <= record["mean"] <= record["max"]
    assert json.loads(_volume(d / "plain.tif")[2]["Info"])["background_counts"] is None


def test_folder_and_glob_give_the_stack_volume(scene):
    """A folder (natural name order: psf_8, psf_9, psf_10) and a glob of the same planes
    give the stack file's volume; --quiet prints no progress."""
    d, _ = scene
    names = sorted(NAMES, key=natural_key)
    assert names == NAMES and sorted(NAMES) != NAMES
    outs = {}
    for name, source in [("stack", d / "psfs.tif"), ("folder", d / "planes"),
                         ("glob", f"{d}/planes/psf_*.npy")]:
        outs[name] = d / f"{name}.tif"
        assert _run(d / "raw.npy", "--psf", source, "--3d", "--iterations", 30, "--quiet",
                    "-o", outs[name]) == 0
    stack = _volume(outs["stack"])[0]
    for name in ("folder", "glob"):
        volume, _, meta = _volume(outs[name])
        np.testing.assert_allclose(volume, stack, rtol=1e-5, atol=1e-6 * stack.max())
        assert meta["Labels"][2] == "plane 2 (psf_10.npy)"


def test_planes_select_and_folder_works_in_2d(scene):
    """--planes picks planes of a stack (the volume has that many); a folder source
    also serves a 2-D reconstruction with --plane."""
    d, psfs = scene
    assert _run(d / "raw.npy", "--psf", d / "planes", "--planes", "0,2", "--3d",
                "--iterations", 20, "--quiet", "-o", d / "two.tif") == 0
    volume, _, meta = _volume(d / "two.tif")
    assert volume.shape == (2, N, N) and meta["Labels"][1].startswith("plane 2 ")
    for source in (d / "planes", d / "psfs.tif"):
        assert _run(d / "raw.npy", "--psf", source, "--plane", 1, "--iterations", 20,
                    "--quiet", "-o", d / f"{source.stem}.npy") == 0
    np.testing.assert_allclose(np.load(d / "planes.npy"), np.load(d / "psfs.npy"),
                               rtol=1e-5, atol=1e-7)


def test_dark_levels(scene):
    """--dark-raw/--dark-psf (numbers) and --bias remove offsets added to the data; auto
    is the median of the 6-pixel border ring, per plane."""
    d, psfs = scene
    raw = np.load(d / "raw.npy")
    np.save(d / "raw_dark.npy", raw + 2.0)
    tifffile.imwrite(d / "psfs_dark.tif", psfs + 2.0, photometric="minisblack")
    common = ["--3d", "--iterations", 30, "--quiet"]
    assert _run(d / "raw.npy", "--psf", d / "psfs.tif", *common, "-o", d / "clean.tif") == 0
    assert _run(d / "raw_dark.npy", "--psf", d / "psfs_dark.tif", "--dark-raw", 2,
                "--dark-psf", "2", *common, "-o", d / "dark.tif") == 0
    assert _run(d / "raw_dark.npy", "--psf", d / "psfs_dark.tif", "--bias", 2, *common,
                "-o", d / "bias.tif") == 0
    clean = _volume(d / "clean.tif")[0]
    for name in ("dark", "bias"):
        np.testing.assert_allclose(_volume(d / f"{name}.tif")[0], clean,
                                   atol=1e-3 * clean.max())
    frames = np.full((2, 20, 24), 100.0, np.float32)
    frames[0] += 5
    frames[:, 8:12, 8:16] = 1e4  # bright centre: not in the ring
    frames[1, 0, :3] = 1e4       # a few hot pixels in the ring: the median ignores them
    np.testing.assert_array_equal(border_dark_level(frames), [105, 100])


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Stack-fit models of the shipped stack at 1/8 size (10 steps: a quick, rough fit):
    one knowing its 44 planes, one fitted from a dict (plane count unknown)."""
    from diffcam.calibrate import fit_stack
    from diffcam.data import load_psf_stack_3d, load_raw_3d

    d = tmp_path_factory.mktemp("models")
    stack = load_psf_stack_3d(downsample_by=8)
    np.save(d / "raw.npy", load_raw_3d(downsample_by=8))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit_stack(stack, [5, 27], max_steps=10, progress=False).save(d / "model.npz")
        fit_stack({5: stack[5], 27: stack[27]}, [5, 27], max_steps=10,
                  progress=False).save(d / "model_unknown.npz")
    return d


@pytest.mark.slow
def test_stack_fit_model_as_psf_source(models):
    """A model renders its planes: all 44 by default, or --planes; a model that does not
    know its plane count needs --planes."""
    d = models
    raw, common = d / "raw.npy", ["--3d", "--iterations", 10, "--quiet"]
    assert _run(raw, "--psf", d / "model.npz", *common, "-o", d / "all.tif") == 0
    assert _volume(d / "all.tif")[0].shape == (44, 33, 40)
    assert _run(raw, "--psf", d / "model.npz", "--planes", "0:43:6", *common,
                "-o", d / "some.tif") == 0
    volume, _, meta = _volume(d / "some.tif")
    assert volume.shape == (8, 33, 40) and meta["Labels"][1] == "plane 6"
    assert np.isfinite(volume).all() and volume.max() > 0
    assert _run(raw, "--psf", d / "model_unknown.npz", *common, "-o", d / "x.tif") == 2
    assert _run(raw, "--psf", d / "model_unknown.npz", "--planes", "5,27", *common,
                "-o", d / "x.tif") == 0


def _bad_inputs(d):
    """(arguments, words of the error) for every bad input."""
    (d / "empty").mkdir()
    mixed = d / "mixed"
    mixed.mkdir()
    np.save(mixed / "a1.npy", np.ones((32, 32), np.float32))
    np.save(mixed / "a2.npy", np.ones((30, 30), np.float32))
    np.save(d / "small_raw.npy", np.ones((24, 24), np.float32))
    np.save(d / "one_psf.npy", _caustic(0))
    np.savez(d / "fake_model.npz", metadata=np.array('{"format": "diffcam-stack-fit"}'))
    raw, psf = d / "raw.npy", d / "psfs.tif"
    return [
        ((raw, "--psf", d / "empty", "--3d"), "holds no"),
        ((raw, "--psf", f"{d}/nothing_*.png", "--3d"), "no files match"),
        ((raw, "--psf", mixed, "--3d"), "one shape"),
        ((d / "small_raw.npy", "--psf", psf, "--3d"), "larger than the image"),
        ((raw, "--psf", psf, "--3d", "--downsample", 40), "smaller than one"),
        ((raw, "--psf", psf, "--3d", "--plane", 1), "--plane and --depth"),
        ((raw, "--psf", psf, "--3d", "--depth", "25mm"), "--plane and --depth"),
        ((raw, "--psf", psf, "--3d", "--bias", 1, "--dark-raw", "auto"), "not both"),
        ((raw, "--psf", psf, "--3d", "--planes", "1:5"), "outside the stack"),
        ((raw, "--psf", d / "one_psf.npy", "--3d"), "needs a PSF stack"),
        ((raw, "--psf", psf, "--3d", "--method", "wiener"), "2-D only"),
        ((raw, "--psf", d / "fake_model.npz", "--3d"), "stack-fit"),
        ((raw, "--psf", psf, "--3d", "--dark-raw", 1e6), "background"),
        ((raw, "--psf", psf, "--3d", "--downsample", 0), "--downsample"),
        ((raw, "--psf", psf, "--psf-envelope", "auto"), "with --3d"),
        ((raw, "--psf", psf, "--background", 1), "with --3d"),
        ((raw, "--psf", psf, "--3d", "--method", "rl", "--background", 1), "ADMM solve"),
        ((raw, "--psf", psf, "--3d", "--method", "rl", "--psf-envelope", "mask"),
         "--method admm"),
    ]


def test_bad_inputs_exit_2_and_leave_outputs(scene, capsys):
    """Each bad input: exit 2, one `error:` line naming the problem, no traceback, and the
    existing OUT.tif, OUT_max.png, OUT_depth.png byte-identical, no temporary files."""
    d, _ = scene
    outs = [d / "vol.tif", d / "vol_max.png", d / "vol_depth.png"]
    for k, path in enumerate(outs):
        path.write_bytes(bytes([k]) * 100)
    for args, words in _bad_inputs(d):
        assert _run(*args, "--iterations", 5, "-o", outs[0]) == 2, args
        err = capsys.readouterr().err
        assert "diffcam reconstruct: error:" in err and words in err, (args, err)
        assert "Traceback" not in err
        assert [p.read_bytes() for p in outs] == [bytes([k]) * 100 for k in range(3)]
    assert _run(d / "raw.npy", "--psf", d / "psfs.tif", "--3d", "-o", d / "vol.png") == 2
    assert "must end in .tif" in capsys.readouterr().err
    assert not list(d.glob(".vol*"))


def test_help_shows_defaults_with_units(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["reconstruct", "--help"])
    assert stop.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for words in ("default: 100 for admm, 1000 for rl, 200 for fista; with --3d 60 for admm, "
                  "300 for rl",
                  "(default: admm)", "default: 1 up to 480 pixels per side", "counts", "'auto'", "--3d",
                  "natural name order"):
        assert words in text, words


def test_real_capture_matches_the_api(tmp_path):
    """The shipped DiffuserCam capture at 1/8 size (33×40, 44 planes) through the CLI
    gives the volume admm_tv_3d (the default method, with the CLI's settings
    diffcam.reconstruct.admm.VOLUME on the raw scaled to unit L2 norm and the PSF
    envelope matched to the capture, the volume scaled back) gives called directly
    (cropped to the sensor frame as the CLI does): finite,
    max projections correlated (measured:
    Pearson 1.000000; a CLI that changed the data, the crop or the plane order would
    fall well below the bound)."""
    from diffcam.core.grid import crop_to
    from diffcam.data import load_psf_stack_3d, load_raw_3d
    from diffcam.io import apply_envelope, envelope_widths
    from diffcam.reconstruct import admm_tv_3d

    raw, psfs = load_raw_3d(downsample_by=8), load_psf_stack_3d(downsample_by=8)
    assert raw.shape == (33, 40) and psfs.shape == (44, 33, 40)
    np.save(tmp_path / "raw.npy", raw)
    tifffile.imwrite(tmp_path / "psfs.tif", psfs)
    assert _run(tmp_path / "raw.npy", "--psf", tmp_path / "psfs.tif", "--3d",
                "--iterations", 60, "--quiet", "-o", tmp_path / "vol.tif") == 0
    volume = _volume(tmp_path / "vol.tif")[0]
    assert volume.shape == (44, 33, 40) and np.isfinite(volume).all()
    norm = np.linalg.norm(raw)
    matched = apply_envelope(psfs, envelope_widths(raw, psfs))
    direct = np.asarray(crop_to(admm_tv_3d(raw / norm, matched, 60, VOLUME).image,
                                raw.shape))
    assert np.allclose(volume.max(), direct.max() * norm, rtol=1e-3)
    pearson = np.corrcoef(volume.max(axis=0).ravel(), direct.max(axis=0).ravel())[0, 1]
    assert pearson > 0.999, pearson


def test_stack_with_depths_labels_planes_by_depth(scene):
    """A stack from `diffcam psf` (.npz with depths) gives the same volume, its planes
    labelled by source depth in the TIFF and in the depth map's colour bar."""
    from diffcam.model.stack import StackMeta, save_stack

    d, psfs = scene
    meta = StackMeta(depths=np.array([20e-3, 25e-3, 30e-3]), offsets=None, pitch=5e-6,
                     wavelengths=np.array([532e-9]), weights=np.array([1.0]), camera={})
    save_stack(d / "psfs.npz", psfs, meta)
    for name, source in [("tif", d / "psfs.tif"), ("npz", d / "psfs.npz")]:
        assert _run(d / "raw.npy", "--psf", source, "--3d", "--iterations", 30, "--quiet",
                    "-o", d / f"{name}.tif") == 0
    volume, axes, labels = _volume(d / "npz.tif")
    assert axes == "ZYX" and labels["Labels"] == ["z1 20 mm", "z1 25 mm", "z1 30 mm"]
    np.testing.assert_allclose(volume, _volume(d / "tif.tif")[0], rtol=1e-5,
                               atol=1e-6 * volume.max())
    assert (d / "npz_depth.png").stat().st_size > 5000


def _declaring(model, folder, n_planes):
    """A copy of ``model`` whose metadata declare ``n_planes`` planes."""
    with np.load(model) as arrays:
        contents = dict(arrays)
    meta = json.loads(str(contents["metadata"][()]))
    meta["n_planes"] = n_planes
    contents["metadata"] = np.array(json.dumps(meta))
    path = folder / f"declares_{n_planes}.npz"
    np.savez(path, **contents)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("n_planes", [0, -3, 10**9])
def test_a_model_declaring_a_hostile_plane_count(models, tmp_path, capsys, n_planes):
    """A model file declaring 0, −3 or 10⁹ planes, through predict, psf, reconstruct
    --3d: one error line naming the file and the count, exit 2, before anything is
    rendered (10⁹ planes once grew past 4 GiB); --planes still works."""
    model = _declaring(models / "model.npz", tmp_path, n_planes)
    raw = models / "raw.npy"
    for argv in (["predict", model, "-o", tmp_path / "p.tif"],
                 ["psf", model, "-o", tmp_path / "q.tif"],
                 ["reconstruct", raw, "--psf", model, "--3d", "--quiet",
                  "-o", tmp_path / "v.tif"]):
        capsys.readouterr()
        assert main([str(a) for a in argv]) == 2
        errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
        assert len(errors) == 1 and f"declares {n_planes} planes" in errors[0], errors
    assert main(["predict", str(model), "--planes", "5,6", "-o", str(tmp_path / "p.tif")]) == 0
