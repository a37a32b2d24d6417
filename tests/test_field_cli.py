"""``diffcam psf``/``predict`` and ``diffcam compare`` of a field-dependent PSF file
(diffcam.apps.field_cli), on a field that is rank 2 after registration: PSFs
``h_c = shift(Σ_k a_k(c) g_k, c)`` with weights ``a_k`` affine across the field, which
the model's thin-plate spline reproduces between its positions."""

import json

import numpy as np
import tifffile

from diffcam.apps.cli import main
from diffcam.model.field import field_psf, save_field_psf

GRID = np.array([[y, x] for y in (-4.0, 0.0, 4.0) for x in (-5.0, 0.0, 5.0)])
HELD_OUT = np.array([[2.0, -3.0], [-3.0, 4.0]])
KERNELS = np.random.default_rng(3).random((2, 15, 17)) ** 3


def _weights(c):
    """The kernels' weights at field positions ``c`` (pixels): planes across the field."""
    return np.stack([1 + 0.02 * c[:, 0] - 0.01 * c[:, 1], 0.3 + 0.04 * c[:, 1]], axis=-1)


def _psfs(positions):
    """The field's PSFs where they fall: the registered PSF moved to its chief ray."""
    registered = np.einsum("pk,kyx->pyx", _weights(positions), KERNELS)
    return np.stack([np.roll(h, tuple(int(v) for v in c), axis=(-2, -1))
                     for h, c in zip(registered, positions)])


def test_psf_and_compare_of_a_field_file(tmp_path, capsys):
    """``psf --at`` writes the model's registered PSFs there (``predict`` the same); a
    colour file gives one stack per channel; ``compare`` registers PSFs captured at
    held-out positions and scores the field model at Pearson 1 (to float32) where the
    on-axis PSF, which a shift-invariant model uses everywhere, scores less."""
    fp = field_psf(_psfs(GRID).astype(np.float32), GRID.astype(np.float32), rank=2)
    path = tmp_path / "field.npz"
    save_field_psf(path, fp)
    at = ";".join(f"{y:g},{x:g}" for y, x in HELD_OUT)
    assert main(["psf", str(path), "--at", at, "-o", str(tmp_path / "at.tif")]) == 0
    assert "rank 2" in capsys.readouterr().out
    written = tifffile.imread(tmp_path / "at.tif")
    np.testing.assert_allclose(written, fp.at(HELD_OUT.astype(np.float32)), rtol=1e-6)
    assert main(["predict", str(path), "-o", str(tmp_path / "own.npy")]) == 0
    np.testing.assert_allclose(np.load(tmp_path / "own.npy"), fp.at(fp.positions), rtol=1e-6)

    save_field_psf(tmp_path / "rgb.npz", [fp] * 3, channels="RGB")
    assert main(["psf", str(tmp_path / "rgb.npz"), "--at", at, "-o",
                 str(tmp_path / "rgb.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "rgb.npy"), np.stack([written] * 3))

    np.save(tmp_path / "captured.npy", _psfs(HELD_OUT))
    assert main(["compare", str(tmp_path / "captured.npy"), "--model", str(path), "--at", at,
                 "--json", str(tmp_path / "scores.json"), "-o", str(tmp_path / "c.png")]) == 0
    scores = json.loads((tmp_path / "scores.json").read_text())
    assert min(scores["field_model"]) > 1 - 1e-5
    assert max(scores["one_psf"]) < 0.995
    assert "| 2, -3 |" in capsys.readouterr().out and (tmp_path / "c.png").stat().st_size


def test_field_file_options_fail_cleanly(tmp_path, capsys):
    """What a field file does not take is refused in one line, exit 2, nothing written."""
    fp = field_psf(_psfs(GRID).astype(np.float32), GRID.astype(np.float32), rank=2)
    path = str(tmp_path / "field.npz")
    save_field_psf(path, fp)
    np.save(tmp_path / "captured.npy", _psfs(HELD_OUT))
    captured = str(tmp_path / "captured.npy")
    cases = [(["psf", path, "--z1", "20mm", "-o", "o.tif"], "not --z1"),
             (["predict", path, "--kappa", "1", "-o", "o.tif"], "not --kappa"),
             (["psf", path, "--at", "1,2,3", "-o", "o.tif"], "Y,X pixels"),
             (["compare", captured, "--model", path, "-o", "o.png"], "--at Y,X"),
             (["compare", captured, "--model", path, "--at", "0,0", "-o", "o.png"],
              "one per --at position"),
             (["compare", captured, "--model", path, "--at", "0,0;1,1", "--z2", "1mm",
               "-o", "o.png"], "does not take --z2"),
             # beyond the positions' span (y ±4, x ±5) by more than a tenth of it
             (["psf", path, "--at", "1e9,0", "-o", "o.tif"], "outside the model's field"),
             (["compare", captured, "--model", path, "--at=2,-3;-3,6.1", "-o", "o.png"],
              "--at -3,6.1 lies outside"),
             (["psf", path, "--at", "-3,1", "-o", "o.tif"], "--at=-…")]
    for args, message in cases:
        args = [str(tmp_path / a) if a.startswith("o.") else a for a in args]
        try:
            status = main(args)
        except SystemExit as e:
            status = e.code
        err = capsys.readouterr().err
        assert status == 2 and message in err and len(err.strip().splitlines()) == 1, (args,
                                                                                      err)
    assert not list(tmp_path.glob("o.*"))
