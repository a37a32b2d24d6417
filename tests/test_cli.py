"""The command line, run as a user runs it (a subprocess)."""

import json
import subprocess
import sys

import pytest

from diffcam.errors import DiffcamError
from diffcam.units import parse_length, parse_length_range


def _diffcam(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "diffcam", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=600)


def test_demo_writes_report(tmp_path):
    """`diffcam demo` (reduced grid and iterations) writes the figures, metrics.json and
    report.md; the calibrated phase beats textbook GS and its PSF matches the truth."""
    out = tmp_path / "report"
    r = _diffcam("demo", "--grid", "768", "--gs-iterations", "100",
                 "--calibration-iterations", "150", "-o", str(out))
    assert r.returncode == 0, r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    for name in ("fig3_phase.png", "fig5_cameraman.png", "fig6_random.png", "fig9_depths.png"):
        assert (out / name).stat().st_size > 10_000
    f3 = metrics["fig3"]
    assert f3["phase_pearson_calibrated"] > 0.98 > f3["phase_pearson_gs"]
    assert metrics["fig5"][-1]["psf_pearson"] > 0.95
    assert len(metrics["fig9"]["z2_1mm"]) == 9
    assert "Fig. 9" in (out / "report.md").read_text()
    assert "diffcam demo:" in r.stdout


def test_plan_reports_and_rejects_bad_units():
    """`diffcam plan` prints the planner's report; a bad unit is one clear line, exit 2."""
    r = _diffcam("plan", "--pixel", "3.45um", "--n", "4096", "--z1", "22mm", "--z2", "1mm",
                 "--aperture-radius", "2.3mm")
    assert r.returncode == 0 and "29.83 mm" in r.stdout
    bad = _diffcam("plan", "--pixel", "3.45furlong", "--n", "8", "--z1", "1", "--z2", "1",
                   "--aperture-radius", "1")
    assert bad.returncode == 2 and "unknown unit" in bad.stderr
    too_big = _diffcam("plan", "--pixel", "5um", "--n", "100", "--z1", "25mm", "--z2", "1mm",
                       "--aperture-radius", "1mm")
    assert too_big.returncode == 2 and "half-width" in too_big.stderr
    assert "Traceback" not in too_big.stderr


def test_units():
    """Lengths with units convert to metres; ranges include their end."""
    assert parse_length("25mm") == pytest.approx(0.025)
    assert parse_length("3.45um") == pytest.approx(3.45e-6)
    assert parse_length("532nm") == pytest.approx(532e-9)
    assert parse_length("1e-3") == pytest.approx(1e-3)
    r = parse_length_range("22mm:30mm:1mm")
    assert len(r) == 9 and r[-1] == pytest.approx(0.030)
    with pytest.raises(DiffcamError, match="unit"):
        parse_length("3 parsecs")
    with pytest.raises(DiffcamError, match="start:stop:step"):
        parse_length_range("1mm:2mm")


@pytest.fixture
def tutorial_files(tmp_path):
    import numpy as np
    import tifffile

    from diffcam.data import load_tutorial_pair

    pair = load_tutorial_pair(downsample_by=2)
    tifffile.imwrite(tmp_path / "psf.tif", np.asarray(pair.psf))
    tifffile.imwrite(tmp_path / "raw.tif", np.asarray(pair.image))
    return tmp_path


def test_reconstruct_writes_png_and_fails_cleanly(tutorial_files):
    """`diffcam reconstruct` writes a PNG; a missing file, a corrupt TIFF and a PSF larger
    than the image give one clear line, exit 2, and leave no output behind."""
    d = tutorial_files
    out = d / "hand.png"
    r = _diffcam("reconstruct", str(d / "raw.tif"), "--psf", str(d / "psf.tif"),
                 "--iterations", "20", "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 1000
    (d / "corrupt.tif").write_bytes(b"II*\x00garbage")
    import numpy as np
    import tifffile
    tifffile.imwrite(d / "big.tif", np.ones((400, 400), np.float32))
    for args, message in [((str(d / "missing.tif"), "--psf", str(d / "psf.tif")), "no such file"),
                          ((str(d / "corrupt.tif"), "--psf", str(d / "psf.tif")), "corrupt"),
                          ((str(d / "raw.tif"), "--psf", str(d / "big.tif")), "larger")]:
        bad_out = d / "bad.png"
        r = _diffcam("reconstruct", *args, "-o", str(bad_out))
        assert r.returncode == 2 and message in r.stderr, r.stderr
        assert "Traceback" not in r.stderr
        assert not bad_out.exists()
        assert not list(d.glob(".bad-*"))
