"""``diffcam calibrate-psf`` and ``diffcam reconstruct`` on colour captures: the shipped
Lensless Learning pairs, written as the files a camera gives, calibrate a PSF per channel
that reconstructs a held-out capture in colour; bad colour input fails with one line
before any compute."""

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
