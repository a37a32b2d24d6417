"""The notebooks (jupytext percent format) execute, at a reduced size, so they cannot rot."""

import os
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

# every notebook takes 20-60 s even reduced (04_real_data: 20-24 s): they run with the
# slow tests, which .ci/run runs too
NOTEBOOKS = [pytest.param(p, id=p.stem, marks=[pytest.mark.slow])
             for p in sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.py"))]


@pytest.mark.parametrize("path", NOTEBOOKS)
def test_notebook_executes(path, tmp_path):
    """Run the notebook's source as a script (cells in order), headless; it writes its
    figures, and none is blank."""
    figures = tmp_path / "figures"
    env = dict(os.environ, DIFFCAM_NOTEBOOK_SMALL="1", MPLBACKEND="Agg",
               DIFFCAM_FIGURES=str(figures))
    r = subprocess.run([sys.executable, str(path)], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    written = sorted(figures.glob(f"{path.stem}_*.png"))
    assert written, f"{path.name} wrote no figure to $DIFFCAM_FIGURES"
    for png in written:
        pixels = plt.imread(png)[..., :3]
        # a blank figure is one colour; a drawn one has axes, text and data
        assert pixels.std() > 0.02 and (pixels < 0.5).mean() > 0.002, png.name
