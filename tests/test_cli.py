"""The command line, run as a user runs it (a subprocess). The error cases call
``main()`` in the test's process instead (a subprocess each cost 1.5 s of start-up);
`test_plan_reports_and_rejects_bad_units` checks errors through the real command."""

import json
import os
import subprocess
import sys

import pytest

from diffcam.core.errors import DiffcamError
from diffcam.core.units import parse_length, parse_length_range


def _diffcam(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "diffcam", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=600)


def _fails_cleanly(capsys, args, message, out):
    """``diffcam ARGS -o OUT`` in the test's process: exit 2, one error line on stderr
    that says ``message``, and no output or temporary file left behind."""
    from diffcam.apps.cli import main

    capsys.readouterr()
    try:
        status = main([*args, "-o", str(out)])
    except SystemExit as e:  # argparse's own errors
        status = e.code
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert status == 2 and len(errors) == 1 and message in errors[0], (args, err)
    assert not out.exists() and not list(out.parent.glob(f".{out.stem}.*")), \
        "an output or a temporary file (diffcam.io: .name.tmp-*) was left"


@pytest.mark.slow
def test_demo_writes_report(tmp_path):
    """`diffcam demo` (reduced grid and iterations) writes the figures, metrics.json and
    report.md; on the higher-fidelity data the calibrated phase beats textbook GS, and
    nothing scores 1 by construction (the true phase through diffcam's model included)."""
    out = tmp_path / "report"
    r = _diffcam("demo", "--grid", "640", "--gs-iterations", "50",
                 "--calibration-iterations", "120", "-o", str(out))
    assert r.returncode == 0, r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    for name in ("fig3_phase.png", "fig5_cameraman.png", "fig6_random.png", "fig9_depths.png"):
        assert (out / name).stat().st_size > 10_000
    f3 = metrics["fig3"]
    assert "higher-fidelity" in metrics["data"]
    assert f3["phase_pearson_calibrated"] > f3["phase_pearson_gs"] + 0.1   # 0.91 vs 0.73
    truth, gs, calibrated = metrics["fig5"][0], metrics["fig5"][1], metrics["fig5"][-1]
    assert calibrated["phase_mse"] < 0.5 * gs["phase_mse"]
    assert calibrated["psf_pearson"] > gs["psf_pearson"]
    assert 0.9 < truth["psf_pearson"] < 0.995                             # 0.971 measured
    rows = metrics["fig9"]["z2_1mm"]
    assert len(rows) == 9 and all(0.9 < r["model_true_phase"] < 0.999 for r in rows)
    assert "Fig. 9" in (out / "report.md").read_text()
    assert "diffcam demo:" in r.stdout


def test_plan_reports_and_rejects_bad_units():
    """`diffcam plan` prints the planner's report; a bad unit is one clear line, exit 2."""
    r = _diffcam("plan", "--pixel", "3.45um", "--n", "4096", "--z1", "22mm", "--z2", "1mm",
                 "--aperture-radius", "2.3mm")
    assert r.returncode == 0 and "29.83 mm" in r.stdout
    bad = _diffcam("plan", "--pixel", "3.45furlong", "--n", "8", "--z1", "1m", "--z2", "1m",
                   "--aperture-radius", "1m")
    assert bad.returncode == 2 and "unknown unit" in bad.stderr
    too_big = _diffcam("plan", "--pixel", "5um", "--n", "100", "--z1", "25mm", "--z2", "1mm",
                       "--aperture-radius", "1mm")
    assert too_big.returncode == 2 and "half-width" in too_big.stderr
    assert "Traceback" not in too_big.stderr


def test_quiet_and_verbose():
    """`diffcam -q` prints nothing on stdout; `diffcam -v` adds the FFT backend, the
    allocator policy, the device and the wall time on stderr; both at once is a usage error (exit 2)."""
    plan = ["plan", "--pixel", "3.45um", "--n", "4096", "--z1", "22mm", "--z2", "1mm",
            "--aperture-radius", "2.3mm"]
    quiet = _diffcam("-q", *plan)
    assert quiet.returncode == 0 and quiet.stdout == "" and quiet.stderr == ""
    loud = _diffcam("-v", *plan)
    assert loud.returncode == 0 and "29.83 mm" in loud.stdout
    # DIFFCAM_FFT=auto takes FFTW where it loads, else XLA
    backends = {"fftw": ("FFTW",), "auto": ("FFTW", "XLA")}.get(
        os.environ.get("DIFFCAM_FFT", "").strip().lower(), ("XLA",))
    assert any(f"FFT: {b}" in loud.stderr for b in backends)
    assert "cpu" in loud.stderr.lower()
    assert "memory: " in loud.stderr
    assert loud.stderr.rstrip().endswith(" s")
    both = _diffcam("-q", "-v", *plan)
    assert both.returncode == 2 and "not allowed with" in both.stderr


def test_units():
    """Lengths with units convert to metres; ranges include their end."""
    assert parse_length("25mm") == pytest.approx(0.025)
    assert parse_length("3.45um") == pytest.approx(3.45e-6)
    assert parse_length("532nm") == pytest.approx(532e-9)
    assert parse_length("1e-3m") == pytest.approx(1e-3)
    assert parse_length("0") == 0.0
    with pytest.raises(DiffcamError, match="no unit"):
        parse_length("25", name="z1")  # 25 metres is almost never meant
    with pytest.raises(DiffcamError, match="expands to"):
        parse_length_range("20mm:30mm:1nm")
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


def test_reconstruct_writes_png_and_fails_cleanly(tutorial_files, capsys):
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
        _fails_cleanly(capsys, ["reconstruct", *args], message, d / "bad.png")


@pytest.fixture(scope="module")
def calibration_files(tmp_path_factory):
    """Synthetic near/far captures (12-bit, shot noise, background) of a random diffuser
    and a captured PSF stack of it, as files."""
    import jax
    import numpy as np
    import tifffile

    from diffcam.model.camera import Camera, random_diffuser
    from diffcam.optics.elements import circular_aperture
    from diffcam.calibrate import CalibrationGeometry, synthetic_captures
    from diffcam.model.stack import StackMeta, camera_record, psf_stack, save_stack

    d = tmp_path_factory.mktemp("calibration")
    n, dx, lam = 256, 5e-6, 532e-9
    geometry = CalibrationGeometry(dx=dx, wavelength=lam, focal_length=n * dx * dx / lam)
    phase = np.asarray(random_diffuser(jax.random.PRNGKey(1), (n, n), dx, lam,
                                       feature_size=60e-6, deflection=np.deg2rad(0.3)))
    aperture = circular_aperture((n, n), dx, 0.3e-3)
    near, far = synthetic_captures(phase, aperture, geometry, jax.random.PRNGKey(2),
                                   sensor_pitch=dx, sensor_shape=(n, n))
    tifffile.imwrite(d / "near.tif", near.astype(np.uint16))
    tifffile.imwrite(d / "far.tif", far.astype(np.uint16))
    cam = Camera(wavelength=lam, z2=1e-3, dx=dx, aperture_radius=0.3e-3, shape=(n, n),
                 crop=(200, 200))
    depths = np.array([20e-3, 22e-3, 24e-3])
    captured = psf_stack(phase, cam, depths)
    tifffile.imwrite(d / "psf22.tif", captured[1])
    save_stack(d / "captured.tif", captured,
               StackMeta(depths=depths, offsets=None, pitch=dx, wavelengths=np.array([lam]),
                         weights=np.array([1.0]), camera=camera_record(cam)))
    return d, f"{geometry.focal_length * 1e3:.4f}mm"


@pytest.mark.slow
def test_calibrate_psf_compare_pipeline(calibration_files):
    """calibrate (twin resolved by one captured PSF) → psf → compare on files: each writes
    its output, the PSF stack has the requested depths (range end included) and its
    metadata, and the model PSFs of the calibrated phase match the captured ones
    (registered Pearson > 0.95 at every depth)."""
    import numpy as np

    from diffcam.model.stack import load_stack

    d, focal = calibration_files
    common = ["--focal-length", focal, "--wavelength", "532nm", "--pixel", "5um",
              "--aperture-radius", "0.3mm", "--grid", "256", "--background", "82"]
    r = _diffcam("calibrate", str(d / "near.tif"), str(d / "far.tif"), *common,
                 "--iterations", "150", "--restarts", "2", "--psf", str(d / "psf22.tif"),
                 "--psf-z1", "22mm", "--psf-z2", "1mm", "-o", str(d / "phase.npz"))
    assert r.returncode == 0, r.stderr
    assert "twin resolved" in r.stdout
    r = _diffcam("psf", str(d / "phase.npz"), "--z1", "20mm:24mm:2mm", "--z2", "1mm",
                 "--crop", "200", "-o", str(d / "psfs.tif"))
    assert r.returncode == 0, r.stderr
    stack, meta = load_stack(d / "psfs.tif")
    assert stack.shape == (3, 200, 200) and np.allclose(meta.depths, [20e-3, 22e-3, 24e-3])
    assert np.allclose(stack.sum(axis=(1, 2)), 1, rtol=1e-4)
    r = _diffcam("compare", str(d / "captured.tif"), "--phase", str(d / "phase.npz"),
                 "--z2", "1mm", "-o", str(d / "compare.png"))
    assert r.returncode == 0, r.stderr
    model = [float(line.split("|")[2]) for line in r.stdout.splitlines()
             if line.startswith("| 2")]
    assert len(model) == 3 and min(model) > 0.95
    assert (d / "compare.png").stat().st_size > 5000
    # --model takes the phase file too (one option for either kind of camera model)
    r2 = _diffcam("compare", str(d / "captured.tif"), "--model", str(d / "phase.npz"),
                  "--z2", "1mm", "-o", str(d / "compare2.png"))
    assert r2.returncode == 0, r2.stderr
    assert r2.stdout.replace("compare2.png", "compare.png") == r.stdout


@pytest.mark.slow
def test_calibrate_with_a_projection_solver(calibration_files, tmp_path):
    """`--solver raar` runs the projections alone and writes a phase file that loads."""
    from diffcam.calibrate import load_phase

    d, focal = calibration_files
    r = _diffcam("calibrate", str(d / "near.tif"), str(d / "far.tif"), "--focal-length", focal,
                 "--wavelength", "532nm", "--pixel", "5um", "--aperture-radius", "0.3mm",
                 "--grid", "256", "--background", "82", "--solver", "raar", "--iterations",
                 "100", "-o", str(tmp_path / "raar.npz"))
    assert r.returncode == 0, r.stderr
    loaded = load_phase(tmp_path / "raar.npz")
    assert loaded.phase.shape == (256, 256) and loaded.info["solver"] == "raar"
    assert loaded.info["seed"] == 0          # the random starts' seed, recorded
    assert loaded.dx == pytest.approx(5e-6)


@pytest.mark.slow
def test_calibrate_psf_compare_failures(calibration_files, tmp_path, capsys):
    """Missing files, wrong units, a corrupt TIFF, mismatched shapes and a non-phase file:
    one clear line on stderr, exit 2, no output left behind."""
    import numpy as np
    import tifffile

    from diffcam.calibrate import PhaseFile, save_phase

    d, focal = calibration_files
    phase = tmp_path / "phase.npz"
    save_phase(phase, PhaseFile(np.zeros((64, 64)), 5e-6, 532e-9, 0.1e-3))
    (tmp_path / "corrupt.tif").write_bytes(b"II*\x00nonsense")
    tifffile.imwrite(tmp_path / "small.tif", np.ones((100, 120), np.uint16))
    common = ["--focal-length", focal, "--wavelength", "532nm", "--pixel", "5um",
              "--aperture-radius", "0.3mm", "--grid", "256"]
    out = tmp_path / "out.npz"
    cases = [
        (["calibrate", str(tmp_path / "none.tif"), str(d / "far.tif"), *common], "no such file"),
        (["calibrate", str(tmp_path / "corrupt.tif"), str(d / "far.tif"), *common], "corrupt"),
        (["calibrate", str(d / "near.tif"), str(d / "far.tif"), *common[:-1], "256",
          "--pixel", "5 parsecs"], "unit"),
        (["psf", str(d / "near.tif"), "--z1", "20mm", "--z2", "1mm"], "phase file"),
        (["psf", str(tmp_path / "none.npz"), "--z1", "20mm", "--z2", "1mm"], "no such file"),
        (["psf", str(phase), "--z1", "20mm:10mm:1mm", "--z2", "1mm"], "start ≤ stop"),
        (["psf", str(phase), "--z2", "1mm"], "needs --z1"),
        (["psf", str(phase), "--planes", "0:3", "--z1", "20mm", "--z2", "1mm"],
         "--planes is for a stack-fit model"),
        (["compare", str(tmp_path / "small.tif"), "--phase", str(phase),
          "--z2", "1mm"], "stack"),
        (["compare", str(tmp_path / "small.tif"), "--phase", str(phase)],
         "needs --z2"),
        (["compare", str(tmp_path / "small.tif")], "give the camera model"),
        (["compare", str(tmp_path / "small.tif"), "--model", str(d / "near.tif")],
         "not a diffcam camera model"),

    ]
    for args, message in cases:
        _fails_cleanly(capsys, args, message, out)
    # a phase file where plane indices are needed: the command that renders it instead
    for args in (["predict", str(phase)],
                 ["reconstruct", str(d / "near.tif"), "--psf", str(phase)]):
        _fails_cleanly(capsys, args, f"diffcam psf {phase} --z1", tmp_path / "o.tif")


def test_version_is_the_installed_distribution(capsys):
    """`diffcam --version` prints the version pip installed (pyproject.toml), exit 0."""
    from importlib.metadata import version

    from diffcam.apps.cli import build_parser

    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"diffcam {version('diffcam')}"


@pytest.mark.slow
def test_warnings_are_one_line(tmp_path):
    """A warning on the command line is one line naming the command and the warning's
    category, without Python's file name and source line."""
    import numpy as np

    rng = np.random.default_rng(0)
    psf = rng.random((48, 48)).astype(np.float32)
    psf[0, 0] = -1e-7                       # rounding left by a background subtraction
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "raw.npy", 100 * rng.random((48, 48)).astype(np.float32))
    r = _diffcam("reconstruct", str(tmp_path / "raw.npy"), "--psf", str(tmp_path / "psf.npy"),
                 "--iterations", "2", "-o", str(tmp_path / "out.npy"))
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    warned = [line for line in lines if "BackgroundWarning" in line]
    assert warned == [line for line in lines if "clipped to 0" in line]
    assert len(warned) == 1 and warned[0].startswith("diffcam reconstruct: warning (")
    assert not [line for line in lines if ".py:" in line or line.startswith("  ")], r.stderr
