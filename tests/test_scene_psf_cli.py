"""``diffcam calibrate-psf`` and ``diffcam reconstruct`` on colour captures: the shipped
Lensless Learning pairs, written as the files a camera gives, calibrate a PSF per channel
(or with ``--field`` a field-dependent PSF) that reconstructs a held-out capture in
colour; bad colour input and misused field files fail with one line before any
compute."""

import numpy as np
import pytest
import tifffile

from diffcam.apps.cli import main
from diffcam.data import load_scene_pairs
from diffcam.evaluate.metrics import pearson
from diffcam.io import read_rgb
from tests.test_cli import _fails_cleanly


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Four pairs at 67 × 120 as RGB TIFFs (raws, truths), a BGR .npy of the first raw,
    and the truths' arrays."""
    d = tmp_path_factory.mktemp("scenes")
    pairs = load_scene_pairs(downsample_by=2)
    for n, raw, truth in zip(pairs.names[:4], pairs.raws, pairs.truths):
        tifffile.imwrite(d / f"raw_{n}.tif", np.moveaxis(raw, 0, -1), photometric="rgb")
        tifffile.imwrite(d / f"truth_{n}.tif", np.moveaxis(truth, 0, -1), photometric="rgb")
    np.save(d / "raw_bgr.npy", np.moveaxis(pairs.raws[0][::-1], 0, -1))
    return d, pairs


@pytest.mark.slow
def test_calibrate_then_reconstruct_in_colour(scenes, capsys):
    """calibrate-psf on pairs 2–4 writes an RGB PSF and reports a held-out Pearson per
    channel ≥ 0.97; reconstruct of pair 1 (never seen) from its BGR .npy writes a colour
    PNG and a float (ny, nx, 3) array whose channels each correlate with the truth."""
    d, pairs = scenes
    names = pairs.names[1:4]
    status = main(["calibrate-psf", *[str(d / f"raw_{n}.tif") for n in names], "--truth",
                   *[str(d / f"truth_{n}.tif") for n in names], "--iterations", "200",
                   "-o", str(d / "psf.tif"), "--quiet"])
    out = capsys.readouterr().out
    assert status == 0 and "held-out pair predicted" in out
    held = [float(v) for v in out.split("Pearson ")[1].split(" →")[0].split(", ")]
    assert len(held) == 3 and min(held) >= 0.97, out
    psf = read_rgb(d / "psf.tif")
    assert psf.shape == (3, 67, 120) and psf.min() >= 0
    for suffix in ("png", "npy"):
        status = main(["reconstruct", str(d / "raw_bgr.npy"), "--channel-order", "BGR",
                       "--psf", str(d / "psf.tif"), "--quiet", "-o", str(d / f"rec.{suffix}")])
        assert status == 0
    png = read_rgb(d / "rec.png")
    assert png.shape == (3, 67, 120)
    rec = np.load(d / "rec.npy")
    assert rec.shape == (67, 120, 3) and rec.dtype == np.float32
    scores = np.asarray(pearson(np.moveaxis(rec, -1, 0), pairs.truths[0]))
    assert (scores > 0.6).all(), scores


def test_bad_colour_input_fails_cleanly(scenes, capsys, tmp_path):
    d, pairs = scenes
    raw, truth = str(d / "raw_im43.tif"), str(d / "truth_im43.tif")
    gray = tmp_path / "gray.tif"
    tifffile.imwrite(gray, pairs.raws[0, 0])
    small = tmp_path / "small.tif"
    tifffile.imwrite(small, np.moveaxis(pairs.truths[0, :, :60], 0, -1), photometric="rgb")
    dark = tmp_path / "dark.tif"
    tifffile.imwrite(dark, np.zeros((67, 120, 3), np.float32), photometric="rgb")
    two = tmp_path / "two.npy"
    np.save(two, np.zeros((67, 120, 2), np.float32))
    out = tmp_path / "psf.tif"
    cases = [
        (["calibrate-psf", raw, "--truth", str(gray)], "channel"),
        (["calibrate-psf", raw, "--truth", str(small)], "resample the truths"),
        (["calibrate-psf", raw, "--truth", str(dark)], "does not overlap the sensor frame"),
        (["calibrate-psf", raw, raw, "--truth", truth], "one truth per raw"),
        (["calibrate-psf", str(d / "raw_bgr.npy"), "--truth", truth], "channel_order"),
        (["reconstruct", str(two), "--psf", str(gray)], "grayscale or colour"),
        (["reconstruct", str(gray), "--psf", raw], "colour PSF for a grayscale raw"),
        (["reconstruct", raw, "--psf", str(gray), "--dark-raw", "1,2"], "three (R,G,B)"),
        (["reconstruct", str(gray), "--psf", str(gray), "--dark-raw", "0,0,0"],
         "needs a colour image"),
    ]
    for args, message in cases:
        _fails_cleanly(capsys, args, message, out)


def test_white_balance():
    """Grey world brings every channel's mean to the mean of the three; explicit gains
    multiply; a grayscale image is left alone."""
    from diffcam.apps.reconstruct_inputs import white_balance

    image = np.random.default_rng(0).uniform(0, 1, (3, 8, 9)) * np.array([1, 2, 4])[:, None, None]
    balanced = white_balance(image, "auto")
    np.testing.assert_allclose(balanced.mean(axis=(1, 2)), image.mean(), rtol=1e-12)
    np.testing.assert_allclose(white_balance(image, [1, 0.5, 0.25]),
                               image * np.array([1, 0.5, 0.25])[:, None, None])
    gray = image[0]
    assert white_balance(gray, "auto") is gray


def test_working_resolution():
    """Captures up to 480 pixels per side are solved as they are; the tutorial's full
    1200 × 1600 is box-averaged by 4 (to the shipped 300 × 400), and the command says so;
    --downsample overrides."""
    from diffcam.apps.reconstruct_inputs import working_factor

    said = []
    assert working_factor((300, 400), None, said.append) == 1
    assert working_factor((3, 270, 480), None, said.append) == 1 and not said
    assert working_factor((1200, 1600), None, said.append) == 4
    assert said and "300×400" in said[0] and "--downsample 1" in said[0]
    assert working_factor((1200, 1600), 1, said.append) == 1
    assert working_factor((481, 100), None, said.append) == 2


def _field_file(path, channels="RGB", shape=(67, 120), offset=(0.01, 0.02, 0.03)):
    """A small field-dependent PSF file: two kernels per channel at two field positions."""
    import jax.numpy as jnp

    from diffcam.model.field import FieldPSF, save_field_psf

    rng = np.random.default_rng(0)
    models = [FieldPSF(kernels=jnp.asarray(rng.random((2,) + shape), jnp.float32),
                       coefficients=jnp.eye(2, dtype=jnp.float32),
                       positions=jnp.asarray([[0.0, -60.0], [0.0, 60.0]], jnp.float32),
                       singular_values=jnp.ones(2, jnp.float32)) for _ in channels]
    save_field_psf(path, models if len(channels) > 1 else models[0],
                   channels=channels if len(channels) > 1 else None, grid=[1, 2],
                   sensor=list(shape), offset=list(offset[:len(channels)]))
    return path


def test_field_options_and_files_fail_cleanly(scenes, capsys, tmp_path):
    """--field takes GYxGX with two positions or more and writes .npz; a field file is
    refused with one line where it does not apply (3-D, rl/wiener, --dark-raw over the
    calibrated offset, a grayscale raw for a colour model, another sensor size, plane
    choices, psf/predict/compare)."""
    d, pairs = scenes
    raw, truth = str(d / "raw_im43.tif"), str(d / "truth_im43.tif")
    field = str(_field_file(tmp_path / "field.npz"))
    gray = tmp_path / "gray.tif"
    tifffile.imwrite(gray, pairs.raws[0, 0])
    small = tmp_path / "small.tif"
    tifffile.imwrite(small, np.moveaxis(pairs.raws[0, :, :60], 0, -1), photometric="rgb")
    calibrate = ["calibrate-psf", raw, "--truth", truth, "--field"]
    cases = [
        (calibrate + ["1x1"], "leave out --field"),
        (calibrate + ["two"], "e.g. 2x2"),
        (["reconstruct", raw, "--psf", field, "--3d"], "without --3d"),
        (["reconstruct", raw, "--psf", field, "--method", "rl"], "admm or fista"),
        (["reconstruct", raw, "--psf", field, "--dark-raw", "1"], "leave out --dark-raw"),
        (["reconstruct", str(gray), "--psf", field], "colour field model for a grayscale"),
        (["reconstruct", str(small), "--psf", field], "at the model's size"),
        (["reconstruct", raw, "--psf", field, "--plane", "0"], "--plane"),
        (["psf", field, "--z1", "20mm", "--z2", "1mm"], "field-dependent PSF"),
        (["predict", field, "--planes", "0"], "field-dependent PSF"),
        (["compare", raw, "--model", field], "field-dependent PSF"),
    ]
    suffix = {"calibrate-psf": "npz", "reconstruct": "npy", "psf": "npz", "predict": "tif",
              "compare": "png"}
    for args, message in cases:
        _fails_cleanly(capsys, args, message, tmp_path / f"out.{suffix[args[0]]}")
    _fails_cleanly(capsys, calibrate + ["2x2"], "must end in .npz", tmp_path / "psf.tif")


@pytest.mark.slow
def test_calibrate_field_then_reconstruct_as_the_benchmark(scenes, capsys):
    """calibrate-psf --field 2x2 on pairs 2–4 prints the rank, model error and both
    models' held-out Pearson, and writes a colour field file; reconstruct with it (ADMM
    and FISTA) says which model it used and gives, to float32 rounding, what
    benchmarks/bench_scene_psf.py computes from the same file, correlated with the
    truth of the pair it never saw."""
    from benchmarks.bench_scene_psf import reconstruct
    from diffcam.model.field import load_field_psf

    d, pairs = scenes
    names = pairs.names[1:4]
    status = main(["calibrate-psf", *[str(d / f"raw_{n}.tif") for n in names], "--truth",
                   *[str(d / f"truth_{n}.tif") for n in names], "--iterations", "100",
                   "--field", "2x2", "-o", str(d / "field.npz"), "--quiet"])
    out = capsys.readouterr().out
    assert status == 0 and "rank 4" in out and "(one PSF: " in out, out
    fields, meta = load_field_psf(d / "field.npz")
    assert meta["channels"] == "RGB" and meta["grid"] == [2, 2] and len(fields) == 3
    assert len(meta["holdout"]["field_pearson"]) == 3
    raw = pairs.raws[0] - np.asarray(meta["offset"], np.float32)[:, None, None]
    for method in ("admm", "fista"):
        status = main(["reconstruct", str(d / "raw_bgr.npy"), "--channel-order", "BGR",
                       "--psf", str(d / "field.npz"), "--method", method, "--quiet",
                       "-o", str(d / f"field_{method}.npy")])
        line = capsys.readouterr().out
        assert status == 0 and "field-dependent model (2×2 field positions), rank 4" in line
        rec = np.moveaxis(np.load(d / f"field_{method}.npy"), -1, 0)
        bench = reconstruct(method, raw, fields)
        np.testing.assert_allclose(rec, bench, rtol=1e-3, atol=1e-4 * np.abs(bench).max())
        assert (np.asarray(pearson(rec, pairs.truths[0])) > 0.6).all()


@pytest.mark.slow
def test_reconstruct_grayscale_with_a_field_file(tmp_path, capsys):
    """A grayscale raw made by a two-kernel field model plus a dark offset, and the
    model's file with that offset: reconstruct --method fista removes the offset and
    solves with the field operator; the estimate, put back through the model, explains
    the raw less its offset within 2 %."""
    import jax.numpy as jnp

    from diffcam.core.grid import pad_to
    from diffcam.model.field import load_field_psf
    from diffcam.reconstruct import field_model

    shape = (24, 32)
    path = _field_file(tmp_path / "gray.npz", channels="L", shape=shape, offset=(0.5,))
    field, _ = load_field_psf(path)
    operator = field_model(field, shape)
    scene = np.random.default_rng(1).random(operator.object_shape).astype(np.float32)
    raw = np.asarray(operator(jnp.asarray(scene))) + 0.5
    np.save(tmp_path / "raw.npy", raw)
    status = main(["reconstruct", str(tmp_path / "raw.npy"), "--psf", str(path), "--method",
                   "fista", "--iterations", "300", "--full-field", "--quiet",
                   "-o", str(tmp_path / "rec.npy")])
    line = capsys.readouterr().out
    assert status == 0 and "field-dependent model (1×2 field positions), rank 2" in line
    estimate = np.load(tmp_path / "rec.npy")
    misfit = np.linalg.norm(np.asarray(operator(pad_to(jnp.asarray(estimate),
                                                       operator.object_shape))) - (raw - 0.5))
    assert misfit / np.linalg.norm(raw - 0.5) < 0.02


def test_channel_order_is_the_raws_and_an_rgb_psf_file_stays_rgb(scenes, tmp_path):
    """A BGR .npy raw with an RGB TIFF PSF (calibrate-psf's) reconstructs as its RGB
    TIFF with the same PSF: --channel-order reorders the raw, not the PSF file."""
    d, pairs = scenes
    psf = tmp_path / "psf.tif"
    tifffile.imwrite(psf, np.moveaxis(pairs.truths[1] * [[[1.0]], [[0.5]], [[0.2]]], 0, -1)
                     .astype(np.float32), photometric="rgb")
    for raw, order in ((d / "raw_bgr.npy", ["--channel-order", "BGR"]), (d / "raw_im43.tif", [])):
        assert main(["reconstruct", str(raw), *order, "--psf", str(psf), "--method", "wiener",
                     "--quiet", "-o", str(tmp_path / f"{raw.suffix[1:]}.npy")]) == 0
    np.testing.assert_allclose(np.load(tmp_path / "npy.npy"), np.load(tmp_path / "tif.npy"),
                               rtol=1e-5, atol=1e-6)
