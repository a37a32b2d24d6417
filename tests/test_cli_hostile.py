"""Every ``diffcam`` subcommand against hostile input: corrupt files, wrong units,
out-of-range counts, hostile environment variables.

The commands are listed from the argparse parser (:func:`diffcam.apps.cli.build_parser`),
so a new command fails :func:`test_every_command_is_driven` until it has a valid command
line here (``VALID``), and is then driven by every test below. Each run calls
``main(argv)`` in the test's process (a subprocess costs 1.5 s of start-up each) and
must end with exit status 2 (0 where the input is actually valid), no traceback, at most
one error line on stderr, and every existing output byte-identical with no temporary
file beside it. A run is also bounded in time (``_RUN_SECONDS``): a hostile count must
be refused before the work, not after it.
"""

from __future__ import annotations

import argparse
import os
import signal
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from diffcam.apps.cli import build_parser, main
from diffcam.core import backend

_RUN_SECONDS = 20      # a refused input is refused well within this (a valid run here: < 5 s)
_OLD = b"an existing output: it must keep these bytes\n"


class In(str):
    """An input file of a command line (the slot a corrupt file is put in)."""


class StandIn(In):
    """An input that stands in for a stack-fit model (a phase file: fitting a model
    costs 20 s; tests/test_reconstruct_3d_cli.py drives real models): the command
    fails on it, so a damaged file in another slot may go unread."""


class Out(str):
    """An output file of a command line (it exists before the run, with :data:`_OLD`)."""


def _commands() -> list[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sorted(sub.choices)


def _subparser(command: str) -> argparse.ArgumentParser:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Small valid inputs: a raw capture and its PSF, a PSF stack, a phase file."""
    from diffcam.calibrate.phase.file import PhaseFile, save_phase

    d = tmp_path_factory.mktemp("inputs")
    rng = np.random.default_rng(0)
    psf = np.zeros((24, 32), np.float32)
    psf[rng.integers(4, 20, 12), rng.integers(4, 28, 12)] = 1.0
    scene = rng.random((40, 48)).astype(np.float32)
    from scipy.signal import fftconvolve

    raw = np.maximum(fftconvolve(scene, psf, mode="same"), 0).astype(np.float32) + 0.01
    np.save(d / "raw.npy", raw)
    np.save(d / "psf.npy", psf)
    np.save(d / "stack.npy", np.stack([np.roll(psf, k, axis=1) for k in range(3)]) + 1e-3)
    save_phase(d / "phase.npz", PhaseFile(rng.normal(size=(32, 32)).astype(np.float32),
                                          10e-6, 532e-9, 100e-6, {}))
    np.save(d / "truth.npy", scene)
    return {p.stem: p for p in d.iterdir()}


def _valid(command: str, f: dict[str, Path], o: Path) -> list[str]:
    """A valid command line of ``command`` on the small inputs, writing into ``o``."""
    raw, psf, stack, phase = (In(f[k]) for k in ("raw", "psf", "stack", "phase"))
    lines = {
        "calibrate": [raw, In(f["truth"]), "--focal-length", "5cm", "--wavelength", "532nm",
                      "--pixel", "10um", "--aperture-radius", "0.1mm", "--iterations", "2",
                      "--restarts", "1", "-o", Out(o / "cal.npz")],
        "calibrate-psf": [raw, "--truth", In(f["truth"]), "--iterations", "2", "--flip",
                          "none", "--quiet", "-o", Out(o / "psf.tif")],
        "compare": [stack, "--phase", phase, "--z1", "20mm,21mm,22mm", "--z2", "1mm",
                    "--pixel", "10um", "-o", Out(o / "cmp.png")],
        "compare-stack": [stack, "--model", StandIn(f["phase"]), "-o", Out(o / "cmps.png")],
        "data": ["hand", "-o", str(o / "captures")],
        "design": ["--grid", "32", "--aperture", "36um", "--z2", "1mm", "--depths", "3",
                   "--feature", "12um", "--height", "1um", "--steps", "2", "--no-progress",
                   "-o", Out(o / "design.npz")],
        "demo": ["--grid", "600", "--gs-iterations", "1", "--calibration-iterations", "1",
                 "-o", str(o / "report")],
        "fit": [stack, "--planes", "0,2", "--max-steps", "1", "--no-progress",
                "-o", Out(o / "model.npz")],
        "plan": ["--pixel", "3.45um", "--n", "512", "--z1", "20mm", "--z2", "1mm",
                 "--aperture-radius", "0.5mm"],
        "predict": [StandIn(f["phase"]), "--planes", "0:2", "-o", Out(o / "pred.tif")],
        "psf": [phase, "--z1", "20mm", "--z2", "1mm", "-o", Out(o / "psfs.npz")],
        "reconstruct": [raw, "--psf", psf, "--method", "wiener", "--iterations", "3",
                        "--quiet", "-o", Out(o / "rec.png")],
    }
    return [command, *lines[command]]


def _run(argv, env=None) -> tuple[int, str]:
    """``main(argv)`` in this process with ``env`` set: (exit status, stderr)."""
    import contextlib
    import io

    saved = {k: os.environ.get(k) for k in env or {}}
    os.environ.update(env or {})
    before = dict(backend._setting)
    backend._setting.update(backend=None, why_not_fftw=None)  # read the environment anew
    err = io.StringIO()
    previous = signal.signal(signal.SIGALRM, _too_long)
    signal.alarm(_RUN_SECONDS)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                status = main([str(a) for a in argv])
            except SystemExit as e:   # argparse's usage errors
                status = e.code
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        backend._setting.update(before)
        for k, v in saved.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
    return status, err.getvalue()


class _TooLong(Exception):
    pass


def _too_long(signum, frame):
    raise _TooLong(f"still running after {_RUN_SECONDS} s: the input was not refused "
                   f"before the work")


def _check(argv, expected=(2,), env=None) -> str:
    """Run ``argv`` with its outputs in place holding :data:`_OLD`; assert the status,
    no traceback, one error line, the outputs' bytes kept (on failure) and no
    temporary file. Returns stderr."""
    outputs = [Path(a) for a in argv if isinstance(a, Out)]
    for p in outputs:
        p.write_bytes(_OLD)
    status, err = _run(argv, env)
    assert "Traceback" not in err, (argv, err)
    errors = [line for line in err.splitlines() if "error:" in line]
    assert status in expected, (argv, status, err)
    if status != 0:
        assert len(errors) == 1 and err.strip().endswith(errors[0]), (argv, err)
        for p in outputs:
            assert p.read_bytes() == _OLD, f"{p} was changed by a failed run {argv}"
    for p in outputs:
        assert not list(p.parent.glob(f".{p.stem}.tmp-*")), "a temporary file was left"
    return err


def test_every_command_is_driven(files, tmp_path):
    """Every command the parser lists has a valid command line here."""
    for command in _commands():
        assert _valid(command, files, tmp_path)[0] == command


# ------------------------------------------------------------------ corrupt files

def _broken_zip(data: bytes) -> bytes:
    """A zip archive whose central directory lost its signature: ``zipfile.is_zipfile``
    (which reads the end record) says yes, ``zipfile.ZipFile`` raises BadZipFile."""
    start = data.find(b"PK\x01\x02")
    return data[:start] + b"XX" + data[start + 2:]


def _corrupt_variants(good: Path, folder: Path) -> dict[str, Path]:
    """Damaged copies of ``good`` under its own suffix: truncated, a broken zip
    directory (.npz), PNG bytes, empty, a folder, missing."""
    suffix = good.suffix
    data = good.read_bytes()
    out = {}

    def put(name, content):
        p = folder / f"{name}{suffix}"
        p.write_bytes(content)
        out[name] = p

    put("truncated", data[:max(len(data) // 2, 1)])
    if suffix == ".npz":
        put("broken_zip", _broken_zip(data))
    from skimage.io import imsave

    png = folder / "image.png"
    imsave(png, np.zeros((8, 8), np.uint8), check_contrast=False)
    put("png_inside", png.read_bytes())
    put("empty", b"")
    (folder / f"folder{suffix}").mkdir()
    out["folder"] = folder / f"folder{suffix}"
    out["missing"] = folder / f"missing{suffix}"
    return out


@pytest.mark.parametrize("command", _commands())
def test_corrupt_input_files(command, files, tmp_path):
    """Each input file of each command, replaced in turn by each damaged variant: one
    error line, exit 2, the existing output kept."""
    argv = _valid(command, files, tmp_path)
    slots = [i for i, a in enumerate(argv) if isinstance(a, In)]
    if command == "data":   # no input file: its -o is the hostile path
        existing = tmp_path / "a_file"
        existing.write_bytes(_OLD)
        _check(["data", "hand", "-o", existing])
        assert existing.read_bytes() == _OLD
        return
    assert slots or command in ("demo", "plan", "design"), command
    for i in slots:
        folder = tmp_path / f"slot{i}"
        folder.mkdir()
        for name, bad in _corrupt_variants(Path(argv[i]), folder).items():
            err = _check(argv[:i] + [In(bad)] + argv[i + 1:])
            if not any(isinstance(a, StandIn) for a in argv[:i] + argv[i + 1:]):
                assert str(bad) in err, (command, name, err)


def test_a_broken_zip_is_one_line_everywhere(files, tmp_path):
    """An .npz whose central directory is broken (zipfile.BadZipFile) as a phase file,
    a PSF source, a model and a stack: one line saying it cannot be read."""
    bad = tmp_path / "broken.npz"
    bad.write_bytes(_broken_zip(files["phase"].read_bytes()))
    raw = files["raw"]
    for argv in (["psf", bad, "--z1", "20mm", "--z2", "1mm", "-o", Out(tmp_path / "a.npz")],
                 ["reconstruct", raw, "--psf", bad, "-o", Out(tmp_path / "b.png")],
                 ["predict", bad, "-o", Out(tmp_path / "c.tif")],
                 ["compare", bad, "--model", bad, "-o", Out(tmp_path / "d.png")],
                 ["compare-stack", bad, "--model", bad, "-o", Out(tmp_path / "e.png")],
                 ["fit", bad, "--planes", "0,1", "-o", Out(tmp_path / "f.npz")]):
        assert "BadZipFile" in _check(argv), argv


def test_a_file_is_named_by_its_real_format(files, tmp_path):
    """A PNG named .npz is called a PNG image, not 'another format'."""
    from skimage.io import imsave

    fake = tmp_path / "phase.npz"
    imsave(tmp_path / "x.png", np.zeros((8, 8), np.uint8), check_contrast=False)
    fake.write_bytes((tmp_path / "x.png").read_bytes())
    err = _check(["psf", fake, "--z1", "20mm", "--z2", "1mm", "-o", Out(tmp_path / "o.npz")])
    assert "it is a PNG image" in err


# ------------------------------------------------------------ units and counts

def _typed_options(command: str):
    """The options of ``command`` that convert their value (lengths, counts, planes…)."""
    for action in _subparser(command)._actions:
        if action.option_strings and action.type is not None:
            yield action


_HOSTILE_VALUES = ["20", "abc", "", "nan", "-inf", "1e400", "20 parsecs", "0:100000000",
                   "-1", "0", "10**9", "1e9", "5mm:1mm", "\x00", "mm"]


@pytest.mark.parametrize("command", _commands())
def test_hostile_option_values_are_usage_errors_or_accepted(command, files, tmp_path):
    """Each converting option of each command given each hostile text: the parser
    either refuses it as one line (exit 2, no usage block) or accepts a value."""
    parser = build_parser()
    valid = [str(a) for a in _valid(command, files, tmp_path)]
    for action in _typed_options(command):
        for text in _HOSTILE_VALUES:
            status, err = _parse([*valid, action.option_strings[-1], text], parser)
            assert status in (0, 2) and "Traceback" not in err, (action.dest, text, err)
            if status == 2:
                assert len(err.strip().splitlines()) == 1 and "usage:" not in err, err


def _parse(argv, parser) -> tuple[int, str]:
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            parser.parse_args(argv)
            return 0, err.getvalue()
        except SystemExit as e:
            return e.code, err.getvalue()


def test_a_missing_unit_is_one_line():
    """``--z1 20``: the one-line error and where to look, not the usage block."""
    status, err = _run(["plan", "--pixel", "3um", "--n", "64", "--z1", "20", "--z2", "1mm",
                        "--aperture-radius", "0.1mm"])
    assert status == 2
    assert err.strip() == ("diffcam plan: error: argument --z1: z1: '20' has no unit; write "
                           "e.g. 20mm, 20um or 20m (see diffcam plan --help)")


_COUNTS = ["0", "-1", "-1000", "1000000000", "100000000"]


@pytest.mark.parametrize("command", _commands())
def test_out_of_range_counts(command, files, tmp_path):
    """Every integer option of every command at 0, negative and 10⁸–10⁹: refused
    before the work (exit 2, one line, the output kept) or a valid, bounded run."""
    argv = _valid(command, files, tmp_path)
    counts = [a.option_strings[-1] for a in _typed_options(command)
              if a.type is int or a.type.__name__ == "count"]
    for option in counts:
        if option == "--seed":
            continue            # any integer is a seed
        for value in _COUNTS:
            _check(_replaced(argv, option, value), expected=(0, 2))


def _replaced(argv, option, value):
    """``argv`` with ``option`` set to ``value`` (replaced, or added)."""
    argv = list(argv)
    if option in argv:
        argv[argv.index(option) + 1] = value
        return argv
    return argv + [option, value]


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(first=st.integers(-10**12, 10**12), length=st.integers(0, 10**12),
       step=st.integers(-3, 10**6))
def test_plane_ranges(files, tmp_path, first, length, step):
    """``--planes A:B:S`` of any size: refused as one line before anything is built
    (past diffcam.calibrate.stack.result.MAX_PLANES, negative, reversed or a bad step),
    or within the stack (exit 0)."""
    text = f"{first}:{first + length}:{step}"
    argv = _replaced(_valid("reconstruct", files, tmp_path), "--planes", text)
    argv = argv[:3] + [In(files["stack"])] + argv[4:]
    _check(argv + ["--plane", "0"], expected=(0, 2))


# ------------------------------------------------------------ the environment

@pytest.mark.parametrize("env", [{"DIFFCAM_FFT": "bogus"}, {"DIFFCAM_FFT_THREADS": "abc"},
                                 {"DIFFCAM_FFT_THREADS": "0"}, {"DIFFCAM_FFT_THREADS": "²"},
                                 {"DIFFCAM_FFT": "auto", "DIFFCAM_FFT_THREADS": "abc"},
                                 {"DIFFCAM_FFT": "fftw", "DIFFCAM_FFT_THREADS": "-2"}])
@pytest.mark.parametrize("command", _commands())
def test_hostile_environment(command, env, files, tmp_path):
    """Every command refuses a hostile FFT setting first: one line naming the variable,
    exit 2, before any input is read."""
    err = _check(_valid(command, files, tmp_path), env=env)
    assert ("DIFFCAM_FFT_THREADS" if "DIFFCAM_FFT_THREADS" in env else "DIFFCAM_FFT") in err


def test_auto_fft_is_a_valid_setting(files, tmp_path):
    """``DIFFCAM_FFT=auto`` runs (FFTW where it loads, else XLA)."""
    _check(_valid("reconstruct", files, tmp_path), expected=(0,), env={"DIFFCAM_FFT": "auto"})


def test_help_states_the_caps(capsys):
    """``--help`` of every command ends with what it checks, naming the constants."""
    for command in _commands():
        text = " ".join(_subparser(command).format_help().split())
        assert "exit status 2" in text
        if command not in ("data", "demo", "plan"):
            assert "diffcam.io.MAX_READ_BYTES" in text, command
    assert "MAX_ITERATIONS" in _subparser("reconstruct").format_help().replace("\n", "")
    assert "MAX_PLANES" in _subparser("predict").format_help()


# ------------------------------------------------------------ the inputs' content

def test_no_light_is_named(files, tmp_path):
    """An all-zero raw or PSF: 'no light', naming the file (it was 'N NaN/Inf values')."""
    zero = tmp_path / "zero.npy"
    np.save(zero, np.zeros((40, 48), np.float32))
    out = Out(tmp_path / "o.png")
    for argv, named in ((["reconstruct", zero, "--psf", files["psf"], "-o", out], zero),
                        (["reconstruct", files["raw"], "--psf", zero, "-o", out], zero)):
        err = _check(argv)
        assert "no light" in err and str(named) in err and "NaN" not in err, err


def test_swapped_raw_and_psf_are_warned(tmp_path):
    """The shipped hand capture and its PSF swapped: a warning on stderr (the raw lights
    fewer effective pixels than the PSF), and none in the right order."""
    from diffcam.data import export_captures

    export_captures("hand", tmp_path)
    raw, psf = tmp_path / "hand_raw.tif", tmp_path / "hand_psf.tif"
    out = Out(tmp_path / "o.png")
    right = _check(["reconstruct", raw, "--psf", psf, "--method", "wiener", "-o", out], (0,))
    swapped = _check(["reconstruct", psf, "--psf", raw, "--method", "wiener", "-o", out],
                     (0,))
    assert "warning:" not in right
    assert "warning:" in swapped and "are the two files swapped?" in swapped


def test_a_nan_plane_is_called_nan(files, tmp_path):
    """A stack with a NaN plane through compare-stack: the plane named, 'NaN' said."""
    stack = np.load(files["stack"])
    stack[1] = np.nan
    np.savez(tmp_path / "nan.npz", stack=stack)
    err = _check(["compare-stack", tmp_path / "nan.npz", "--model", files["phase"],
                  "-o", Out(tmp_path / "c.png")])
    assert "plane(s) [1]" in err and "NaN" in err


def test_calibrate_checks_its_output_first_and_names_no_temporary_file(files, tmp_path):
    """A read-only existing output (refused for root too) and a missing folder: refused
    before the captures are read (they are missing here), naming the output."""
    locked = tmp_path / "locked.npz"
    locked.write_bytes(_OLD)
    locked.chmod(0o444)
    common = ["--focal-length", "5cm", "--wavelength", "532nm", "--pixel", "10um",
              "--aperture-radius", "0.1mm"]
    for out in (locked, tmp_path / "no" / "cal.npz"):
        err = _check(["calibrate", tmp_path / "missing1.npy", tmp_path / "missing2.npy",
                      *common, "-o", out])
        assert str(out) in err and "tmp-" not in err and "missing1" not in err, err
    assert locked.read_bytes() == _OLD


# ------------------------------------------- the third round (issue #50): paths, scale

def test_an_output_folder_that_cannot_be_one(tmp_path):
    """``data``'s and ``demo``'s -o: a path under a file (NotADirectoryError), an empty
    name (it wrote into the working folder), a file where usaf3d's psfs/ folder goes:
    one line, exit 2, the file kept."""
    existing = tmp_path / "a_file"
    existing.write_bytes(_OLD)
    taken = tmp_path / "taken"
    (taken / "psfs").parent.mkdir()
    (taken / "psfs").write_bytes(_OLD)
    link = tmp_path / "link"
    link.symlink_to(existing)
    for argv in (["data", "hand", "-o", existing / "sub"],
                 ["data", "usaf3d", "-o", existing / "sub" / "deeper"],
                 ["data", "scenes", "-o", ""],
                 ["data", "usaf3d", "-o", taken],
                 ["data", "hand", "-o", link],
                 ["demo", "--grid", "600", "-o", existing / "report"]):
        err = _check(argv)
        assert ("empty name" if argv[-1] == "" else "a file stands where") in err, err
    assert existing.read_bytes() == _OLD and (taken / "psfs").read_bytes() == _OLD
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "link", "taken"]
    try:                       # sysfs refuses new folders, even to root
        os.mkdir("/sys/diffcam-hardening-probe")
        os.rmdir("/sys/diffcam-hardening-probe")
    except OSError:
        assert "cannot create files" in _check(["data", "hand", "-o",
                                                "/sys/diffcam-hardening-probe"])


def test_white_balance_of_a_grayscale_raw(files, tmp_path):
    """--white-balance on a grayscale capture was ignored: one line saying so."""
    for gains in ("auto", "1,2,3"):
        err = _check(_valid("reconstruct", files, tmp_path) + ["--white-balance", gains])
        assert "grayscale" in err and "--white-balance" in err


def test_a_raw_beyond_the_solvers_range(files, tmp_path):
    """A raw ×1e37 (finite float32) through Richardson–Lucy: refused before the solve,
    its estimate leaving float32 (the scaled fit of ``calibrate-psf`` is
    tests/test_scene_psf.py::test_the_fit_and_its_prediction_scale_with_the_raws)."""
    huge = tmp_path / "huge.npy"
    np.save(huge, (np.load(files["raw"]).astype(np.float64) * 1e37).astype(np.float32))
    argv = _replaced(_valid("reconstruct", files, tmp_path), "--method", "rl")
    assert "float32" in _check([argv[0], In(huge)] + argv[2:])


@pytest.mark.parametrize("address", ["node1", "node1:http", "node1:99999"])
def test_a_coordinator_address_without_a_port(files, tmp_path, address):
    """JAX_COORDINATOR_ADDRESS must be host:port: an IndexError inside JAX's
    initialize was the last line of ``diffcam psf`` (the command that joins a run of
    several processes); now it is refused first, naming the variable."""
    env = {"JAX_COORDINATOR_ADDRESS": address, "JAX_NUM_PROCESSES": "2",
           "JAX_PROCESS_ID": "0"}
    assert "JAX_COORDINATOR_ADDRESS" in _check(_valid("psf", files, tmp_path), env=env)
