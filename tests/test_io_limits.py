"""Hardening: file outputs are atomic and checked before work starts, readers turn every
damaged file into one DiffcamError line, and the numerical edge cases of magnify_psf,
wiener and the soft aperture.

Each test asserts a DiffcamError (or a valid result) *and* that nothing existing was
damaged: existing files keep their bytes, no temporary file is left behind. The reader
fuzzing (hypothesis) mutates valid files written by the reference writers (Pillow,
tifffile, numpy, scipy.io, h5py, save_phase); examples are few and derandomised so the
module stays fast and deterministic.
"""

import io
import json
import os
import signal
import struct
import subprocess
import sys
import textwrap
import threading
import time

import h5py
import jax
import jax.numpy as jnp
import warnings

import numpy as np
import pytest
import scipy.io
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from conftest import listing as _listing
from conftest import png_declaring as _png_declaring
from conftest import tiff_declaring as _tiff_declaring

import diffcam.io as dio
import diffcam.model.stack as stack_module
from diffcam.calibrate.phase.file import PhaseFile, load_phase, save_phase
from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.evaluate.baseline import magnify_psf, scale_psf
from diffcam.io import (atomic_output, check_output_path, downsample, read_image,
                        read_mat_stack, read_npz, read_psf_stack, subtract_background)
from diffcam.model import Camera
from diffcam.model.stack import StackMeta, load_stack, psf_stack, save_stack
from diffcam.optics.elements import circular_aperture
from diffcam.reconstruct import convolution_model, wiener

LAM = 532e-9
N = 32


@pytest.fixture(scope="module")
def small():
    """A 32² camera and a random phase: every psf_stack here compiles once."""
    cam = Camera(wavelength=LAM, z2=1e-3, dx=5e-6, aperture_radius=50e-6, shape=(N, N))
    phase = np.random.default_rng(0).uniform(-np.pi, np.pi, (N, N)).astype(np.float32)
    return cam, phase


def _phase_file(seed=0, **info):
    rng = np.random.default_rng(seed)
    return PhaseFile(rng.random((8, 9)).astype(np.float32), 5e-6, LAM, 1e-3, info)


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ------------------------------------------------------------------ output paths

def _bad_outputs(tmp_path):
    """(path, message) pairs that must fail before any work."""
    (tmp_path / "afile").write_bytes(b"x")
    (tmp_path / "adir.npz").mkdir(exist_ok=True)
    (tmp_path / "adir.tif").mkdir(exist_ok=True)
    (tmp_path / "adir.npy").mkdir(exist_ok=True)
    cases = []
    for suffix in (".npz", ".tif", ".npy"):
        cases += [(tmp_path / "missing" / f"out{suffix}", "does not exist"),
                  (tmp_path / f"adir{suffix}", "is a folder"),
                  (tmp_path / "afile" / f"out{suffix}", "not a folder")]
    if os.path.isdir("/sys"):  # sysfs refuses new files, even to root
        probe = "/sys/diffcam-hardening-probe"
        try:
            os.close(os.open(probe, os.O_CREAT | os.O_WRONLY, 0o666))
            os.unlink(probe)
        except OSError:
            cases += [(f"/sys/out{suffix}", "cannot create files")
                      for suffix in (".npz", ".tif", ".npy")]
    return cases


def test_check_output_path_finds_problems_before_work(tmp_path, small, monkeypatch):
    """Missing folder, a folder as the target, a file as the folder and an unwritable
    folder raise a DiffcamError from check_output_path, save_phase, save_stack and
    psf_stack(out=...), the last before any PSF is computed."""
    cam, phase = small
    monkeypatch.setattr(stack_module, "iter_psf_stack",
                        lambda *a, **k: pytest.fail("psf_stack computed before the path check"))
    meta = StackMeta(depths=np.array([0.02]), offsets=None, pitch=4e-6,
                     wavelengths=np.array([LAM]), weights=np.array([1.0]), camera={})
    cases = _bad_outputs(tmp_path)
    before = _listing(tmp_path)
    for path, message in cases:
        with pytest.raises(DiffcamError, match=message):
            check_output_path(path)
        suffix = os.fspath(path)[-4:]
        if suffix == ".npz":
            with pytest.raises(DiffcamError, match=message):
                save_phase(path, _phase_file())
        if suffix in (".npz", ".tif"):
            with pytest.raises(DiffcamError, match=message):
                save_stack(path, np.zeros((1, 4, 4), np.float32), meta)
        if suffix in (".tif", ".npy"):
            with pytest.raises(DiffcamError, match=message):
                psf_stack(phase, cam, [0.02], out=path)
    with pytest.raises(DiffcamError, match=r"\.npy, \.npz, \.tif or \.tiff"):
        psf_stack(phase, cam, [0.02], out=tmp_path / "s.png")
    with pytest.raises(DiffcamError, match="must end in .npz"):
        check_output_path(tmp_path / "x.txt", suffixes=(".npz",))
    assert _listing(tmp_path) == before
    assert len(cases) >= 9


# ------------------------------------------------------------------ atomic writes

def test_failed_save_phase_leaves_the_old_file(tmp_path):
    """The issue's case: a non-JSON info used to truncate the file to 0 bytes first."""
    path = tmp_path / "phase.npz"
    save_phase(path, _phase_file(1, solver="raar"))
    old = path.read_bytes()
    bad = [(_phase_file(2, when=object()), "info cannot be stored"),
           (_phase_file(2, s={1, 2}), "info cannot be stored"),
           (PhaseFile(np.full((4, 4), np.nan), 5e-6, LAM, 1e-3), "NaN/Inf"),
           (PhaseFile(np.zeros(4), 5e-6, LAM, 1e-3), "2-D"),
           (PhaseFile(np.zeros((4, 4)), -5e-6, LAM, 1e-3), "dx"),
           (PhaseFile(np.zeros((4, 4)), "5um", LAM, 1e-3), "dx"),
           (PhaseFile(np.zeros((4, 4)), 5e-6, float("inf"), 1e-3), "wavelength"),
           (PhaseFile(np.zeros((4, 4)), 5e-6, LAM, 1e-3, info=[1]), "info")]
    for phase_file, message in bad:
        with pytest.raises(DiffcamError, match=message):
            save_phase(path, phase_file)
        assert path.read_bytes() == old
    assert _listing(tmp_path) == ["phase.npz"]


def test_save_phase_accepts_numpy_scalars_and_round_trips(tmp_path):
    """np.int64 counts and np.float32 lengths are accepted where Python numbers are."""
    pf = PhaseFile(np.ones((4, 6), np.float32), np.float32(5e-6), np.float64(LAM),
                   jnp.asarray(1e-3), {"iterations": np.int64(300), "err": np.float32(0.5),
                                       "shape": np.array([4, 6]), "tag": "x"})
    save_phase(tmp_path / "p.npz", pf)
    back = load_phase(tmp_path / "p.npz")
    assert back.info == {"iterations": 300, "err": 0.5, "shape": [4, 6], "tag": "x"}
    assert back.dx == float(np.float32(5e-6)) and back.phase.dtype == np.float32
    np.testing.assert_array_equal(back.phase, pf.phase)
    assert oct(os.stat(tmp_path / "p.npz").st_mode & 0o777) == oct(0o666 & ~_umask())


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_atomic_output_mode_follows_umask(tmp_path, mask):
    old = os.umask(mask)
    try:
        with atomic_output(tmp_path / "a.bin") as temp:
            assert temp.parent == tmp_path and temp.name.startswith(".a.tmp-")
            temp.write_bytes(b"new")
    finally:
        os.umask(old)
    assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o666 & ~mask
    assert _listing(tmp_path) == ["a.bin"]


def test_atomic_output_interrupted_keeps_the_old_bytes(tmp_path):
    """KeyboardInterrupt and errors inside the block: target unchanged, temporary gone,
    the SIGTERM disposition as before; a symlinked target is written through."""
    target = tmp_path / "t.npz"
    target.write_bytes(b"old bytes")
    handler = signal.getsignal(signal.SIGTERM)
    for exc in (KeyboardInterrupt, RuntimeError, DiffcamError):
        with pytest.raises(exc):
            with atomic_output(target) as temp:
                temp.write_bytes(b"half")
                raise exc("stop")
        assert target.read_bytes() == b"old bytes"
        assert _listing(tmp_path) == ["t.npz"]
        assert signal.getsignal(signal.SIGTERM) is handler
    with atomic_output(target, tmp_path / "t.json") as (a, b):
        a.write_bytes(b"A")
        b.write_bytes(b"B")
    assert target.read_bytes() == b"A" and (tmp_path / "t.json").read_bytes() == b"B"
    assert signal.getsignal(signal.SIGTERM) is handler
    (tmp_path / "link.npz").symlink_to(target)
    with atomic_output(tmp_path / "link.npz") as temp:
        temp.write_bytes(b"via link")
    assert (tmp_path / "link.npz").is_symlink() and target.read_bytes() == b"via link"
    assert _listing(tmp_path) == ["link.npz", "t.json", "t.npz"]


class _Interrupting:
    """Stands in for tqdm in diffcam.model.stack: KeyboardInterrupt at the n-th chunk."""

    def __init__(self, at):
        self.at, self.seen = at, 0

    def __call__(self, *args, **kwargs):
        return self

    def update(self, n):
        self.seen += 1
        if self.seen == self.at:
            raise KeyboardInterrupt

    def close(self):
        pass


@pytest.mark.parametrize("suffix", [".tif", ".npy"])
def test_interrupted_psf_stack_keeps_the_old_file(tmp_path, small, monkeypatch, suffix):
    """Ctrl-C in the middle of psf_stack(out=...): the old file (and .npy's .json) keep
    their bytes, nothing temporary is left; a later run replaces both in full."""
    cam, phase = small
    out = tmp_path / f"s{suffix}"
    out.write_bytes(b"old stack")
    side = tmp_path / f"s{suffix}.json"
    if suffix == ".npy":
        side.write_bytes(b"old meta")
    before = _listing(tmp_path)
    monkeypatch.setattr(stack_module, "tqdm", _Interrupting(at=2))
    with pytest.raises(KeyboardInterrupt):
        psf_stack(phase, cam, np.linspace(20e-3, 30e-3, 6), out=out, batch_size=2)
    assert out.read_bytes() == b"old stack" and _listing(tmp_path) == before
    if suffix == ".npy":
        assert side.read_bytes() == b"old meta"
    monkeypatch.setattr(stack_module, "tqdm", _Interrupting(at=0))
    got = psf_stack(phase, cam, np.linspace(20e-3, 30e-3, 6), out=out, batch_size=2)
    assert got.shape == (6, N, N) and np.isfinite(np.asarray(got)).all()
    back, meta = load_stack(out)
    np.testing.assert_array_equal(back, got)
    assert meta.depths.size == 6 and _listing(tmp_path) == before


def test_save_stack_failure_keeps_the_old_file(tmp_path, monkeypatch):
    meta = StackMeta(depths=np.array([0.02, 0.03]), offsets=None, pitch=4e-6,
                     wavelengths=np.array([LAM]), weights=np.array([1.0]), camera={})
    for name in ("a.npz", "a.tif"):
        (tmp_path / name).write_bytes(b"old")
        with pytest.raises(ShapeError):
            save_stack(tmp_path / name, np.zeros((3, 4, 4)), meta)

        def broken(target, *args, **kwargs):
            if isinstance(target, (str, os.PathLike)):
                with open(target, "wb") as f:
                    f.write(b"partial")
            else:
                target.write(b"partial")
            raise OSError("disk full")

        monkeypatch.setattr(stack_module, "_write_tiff", broken)
        monkeypatch.setattr(np, "savez", broken)
        with pytest.raises(OSError, match="disk full"):
            save_stack(tmp_path / name, np.zeros((2, 4, 4)), meta)
        monkeypatch.undo()
        assert (tmp_path / name).read_bytes() == b"old"
    assert _listing(tmp_path) == ["a.npz", "a.tif"]


@pytest.mark.parametrize("mode", ["default", "swallow", "own-handler"])
def test_sigterm_guard_of_atomic_output(tmp_path, monkeypatch, mode):
    """SIGTERM inside atomic_output while SIGTERM has its default action: the target
    keeps its bytes, no temporary is left, the default action is restored and the
    signal raised again (recorded here instead of ending pytest), also when the block
    swallows the exception. A caller's own handler is left in charge and the write
    completes. (test_sigterm_while_writing runs the real thing in subprocesses.)"""
    target = tmp_path / "t.npz"
    target.write_bytes(b"old")
    raised = []
    monkeypatch.setattr(signal, "raise_signal", raised.append)
    own = []
    previous = signal.signal(signal.SIGTERM, (lambda *a: own.append(1))
                             if mode == "own-handler" else signal.SIG_DFL)
    try:
        if mode == "own-handler":
            with atomic_output(target) as temp:
                temp.write_bytes(b"half")
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
                temp.write_bytes(b"all")
            assert own == [1] and target.read_bytes() == b"all" and raised == []
        else:
            with pytest.raises(dio.Terminated):
                with atomic_output(target) as temp:
                    temp.write_bytes(b"half")
                    try:
                        os.kill(os.getpid(), signal.SIGTERM)
                        time.sleep(1)
                    except BaseException:
                        if mode == "default":
                            raise
                    temp.write_bytes(b"carried on")  # only "swallow" gets here
            assert raised == [signal.SIGTERM] and target.read_bytes() == b"old"
            assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
        assert _listing(tmp_path) == ["t.npz"]
    finally:
        signal.signal(signal.SIGTERM, previous)


_CHILD = textwrap.dedent("""
    import sys
    import numpy as np
    import diffcam.model.stack as st
    from diffcam.model import Camera

    class Bar:  # in place of tqdm: says when the first chunk reaches the writer
        def __init__(self, *args, **kwargs):
            self.said = False
        def update(self, n):
            if not self.said:
                print("writing", flush=True)
                self.said = True
        def close(self):
            pass

    st.tqdm = Bar
    out, nz = sys.argv[1], int(sys.argv[2])
    cam = Camera(wavelength=532e-9, z2=1e-3, dx=4e-6, aperture_radius=60e-6, shape=(64, 64))
    phase = np.random.default_rng(0).uniform(-np.pi, np.pi, (64, 64)).astype(np.float32)
    print("ready", flush=True)
    st.psf_stack(phase, cam, np.linspace(20e-3, 30e-3, nz), out=out, batch_size=8)
    print("done", flush=True)
""")


def test_sigterm_while_writing(tmp_path):
    """Three processes stream a 4000-depth stack (64², 65 MB) over an existing file
    and get SIGTERM 0.5 and 2 s after psf_stack starts (during its compilation, the
    temporary file already open) and 0.2 s into the writing (.npy with its .json). Each
    dies by SIGTERM (no traceback) or finishes; its files are byte-identical to the old
    ones or the complete new stack, and no temporary file is left."""
    nz = 4000
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    plan = [(".tif", "ready", 0.5), (".tif", "ready", 2.0), (".npy", "writing", 0.2)]
    runs = []
    for k, (suffix, trigger, delay) in enumerate(plan):
        folder = tmp_path / f"run{k}"
        folder.mkdir()
        out = folder / f"stack{suffix}"
        old = {out.name: os.urandom(4096)}
        if suffix == ".npy":
            old[out.name + ".json"] = b'{"old": true}'
        for name, data in old.items():
            (folder / name).write_bytes(data)
        proc = subprocess.Popen([sys.executable, str(script), str(out), str(nz)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        seen = {}

        def watch(proc=proc, seen=seen):
            for line in proc.stdout:
                seen.setdefault(line.strip(), time.monotonic())

        threading.Thread(target=watch, daemon=True).start()
        runs.append(dict(proc=proc, seen=seen, trigger=trigger, delay=delay, out=out,
                         old=old, folder=folder, killed_at=None))
    deadline = time.monotonic() + 120
    while any(r["proc"].poll() is None for r in runs) and time.monotonic() < deadline:
        for r in runs:
            t = r["seen"].get(r["trigger"])
            if r["killed_at"] is None and t is not None and time.monotonic() >= t + r["delay"]:
                r["killed_at"] = time.monotonic()
                r["proc"].send_signal(signal.SIGTERM)
        time.sleep(0.02)
    mid_write = 0
    for r in runs:
        proc = r["proc"]
        if proc.poll() is None:
            proc.kill()
            pytest.fail("a child did not finish within 120 s")
        stderr = proc.stderr.read()
        assert proc.returncode in (0, -signal.SIGTERM), stderr
        assert "Traceback" not in stderr, stderr
        assert _listing(r["folder"]) == sorted(r["old"]), "a temporary file was left"
        now = {name: (r["folder"] / name).read_bytes() for name in r["old"]}
        if now != r["old"]:  # then it must be the complete new stack, with its metadata
            back, meta = load_stack(r["out"])
            assert back.shape == (nz, 64, 64) and meta.depths.size == nz
            assert np.isfinite(np.asarray(back[-1])).all() and float(back[-1].sum()) > 0
        elif r["killed_at"] is not None and r["killed_at"] > r["seen"].get("writing", 1e300):
            mid_write += 1
        if proc.returncode == 0:
            assert now != r["old"]
    print("SIGTERM outcomes:", [(r["proc"].returncode, sorted(r["seen"]),
                                 None if r["killed_at"] is None else
                                 round(r["killed_at"] - r["seen"][r["trigger"]], 2))
                                for r in runs])
    assert mid_write >= 1, "no SIGTERM landed while pages were being written"


# ------------------------------------------------------------------ readers: fuzzing

def _png_bytes(arr):
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def _file_bytes(tmp, name, write):
    path = tmp / name
    write(path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    """Valid files from the reference writers: {format: (suffix, bytes, reader)}."""
    tmp = tmp_path_factory.mktemp("seeds")
    rng = np.random.default_rng(5)

    def h5(path):
        with h5py.File(path, "w") as f:
            f.create_dataset("psf", data=rng.random((3, 7, 6)))

    return {
        "png8": (".png", _png_bytes(rng.integers(0, 255, (12, 17), dtype=np.uint8)),
                 read_image),
        "png16": (".png", _png_bytes(rng.integers(0, 65535, (12, 17), dtype=np.uint16)),
                  read_image),
        "png_rgb": (".png", _png_bytes(rng.integers(0, 255, (9, 8, 3), dtype=np.uint8)),
                    read_image),
        "tiff16": (".tif", _file_bytes(tmp, "a.tif", lambda p: tifffile.imwrite(
            p, rng.integers(0, 65535, (9, 10), dtype=np.uint16))), read_image),
        "tiff_stack": (".tif", _file_bytes(tmp, "b.tif", lambda p: tifffile.imwrite(
            p, rng.random((3, 5, 6)).astype(np.float32), photometric="minisblack")),
                       read_image),
        "tiff_zlib": (".tif", _file_bytes(tmp, "c.tif", lambda p: tifffile.imwrite(
            p, rng.random((16, 16)).astype(np.float32), compression="zlib")), read_image),
        "npy": (".npy", _file_bytes(tmp, "a.npy", lambda p: np.save(
            p, rng.random((6, 7)).astype(np.float32))), read_image),
        "mat5": (".mat", _file_bytes(tmp, "a.mat", lambda p: scipy.io.savemat(
            p, {"psf": rng.random((6, 7, 3))}, do_compression=True)), read_mat_stack),
        "mat73": (".mat", _file_bytes(tmp, "b.mat", h5), read_mat_stack),
        "phase": (".npz", _file_bytes(tmp, "p.npz", lambda p: save_phase(
            p, _phase_file(3, solver="raar"))), load_phase),
    }


def _valid(result):
    """What a reader may return: finite float32 arrays of the documented shapes."""
    if isinstance(result, PhaseFile):
        arr = result.phase
        assert arr.ndim == 2 and result.dx > 0 and result.wavelength > 0
    elif isinstance(result, dio.Capture):
        arr = result.image
        assert arr.ndim in (2, 3) and arr.dtype == np.float32
    else:
        arr = result
        assert arr.ndim == 3 and arr.dtype == np.float32
    assert arr.size > 0 and np.isfinite(arr).all()


_position = st.one_of(st.integers(0, 63), st.integers(0, 2**20))  # header-heavy
_mutation = st.tuples(
    st.lists(st.tuples(_position, st.integers(0, 255), st.booleans()), max_size=6),
    st.one_of(st.none(), st.floats(0.0, 1.0, exclude_max=True)))


@pytest.mark.parametrize("fmt", ["png8", "png16", "png_rgb", "tiff16", "tiff_stack",
                                 "tiff_zlib", "npy", "mat5", "mat73", "phase"])
@settings(max_examples=15, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mutation=_mutation)
def test_corrupt_bytes_give_one_line_errors(seeds, tmp_path, fmt, mutation):
    """Byte flips (from the end when the flag is set: zip directories live there) and
    truncation of valid files: a valid result or a one-line DiffcamError naming the
    file, never another exception."""
    suffix, raw, reader = seeds[fmt]
    data = bytearray(raw)
    flips, cut = mutation
    for pos, value, from_end in flips:
        i = pos % len(data)
        data[-1 - i if from_end else i] = value
    if cut is not None:
        data = data[:int(cut * len(data))]
    path = tmp_path / f"fuzz{suffix}"
    path.write_bytes(bytes(data))
    try:
        result = reader(path)
    except DiffcamError as err:
        assert str(path) in str(err) and "\n" not in str(err)
    else:
        _valid(result)


# ------------------------------------------------------------------ readers: crafted

def test_crafted_headers_are_refused_before_allocating(tmp_path):
    """Headers declaring 37 GiB (TIFF, PNG), 16 GiB (a 4e9-pixel TIFF row), 63 GiB (a
    MATLAB variable) or 7 TiB (.npy) raise a DiffcamError saying how much was asked,
    before any pixel is read (the old reader allocated, or died with MemoryError)."""
    (tmp_path / "big.tif").write_bytes(_tiff_declaring(100_000, 100_000))
    (tmp_path / "row.tif").write_bytes(_tiff_declaring(2**32 - 1, 1))
    (tmp_path / "big.png").write_bytes(_png_declaring(100_000, 100_000))
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (10**6, 10**6)})
    (tmp_path / "big.npy").write_bytes(header.getvalue() + b"\x00" * 64)
    scipy.io.savemat(tmp_path / "m.mat", {"psf": np.zeros((6, 7, 2))})
    mat = (tmp_path / "m.mat").read_bytes()
    (tmp_path / "big.mat").write_bytes(mat.replace(struct.pack("<iii", 6, 7, 2),
                                                   struct.pack("<iii", 60000, 70000, 2)))
    for name, size in [("big.tif", "37.3 GiB"), ("row.tif", "16 GiB"),
                       ("big.png", "37.3 GiB")]:
        with pytest.raises(DiffcamError, match=f"declares .*{size}.*read limit") as err:
            read_image(tmp_path / name)
        assert name in str(err.value)
    with pytest.raises(DiffcamError, match="big.npy: could not be read"):
        read_image(tmp_path / "big.npy")  # the header asks for more than the file holds
    with pytest.raises(DiffcamError, match=r"'psf' declares shape \(60000, 70000, 2\)"):
        read_mat_stack(tmp_path / "big.mat")


def test_read_limit_is_overridable(tmp_path, monkeypatch):
    """max_bytes per call, diffcam.io.MAX_READ_BYTES for the session (load_phase, which
    has no max_bytes, sees a 64 KiB phase against a 10 kB limit)."""
    np.save(tmp_path / "a.npy", np.zeros((100, 100), np.float32))
    assert read_image(tmp_path / "a.npy").image.shape == (100, 100)
    with pytest.raises(DiffcamError, match=r"39.1 KiB to read\), more than the read limit "
                                           r"1000 bytes"):
        read_image(tmp_path / "a.npy", max_bytes=1000)
    tifffile.imwrite(tmp_path / "a.tif", np.zeros((100, 100), np.uint16))
    with pytest.raises(DiffcamError, match="read limit"):
        read_psf_stack([tmp_path / "a.tif"], max_bytes=np.int64(1000))
    save_phase(tmp_path / "p.npz", PhaseFile(np.zeros((128, 128)), 5e-6, LAM, 1e-3))
    assert (tmp_path / "p.npz").stat().st_size > 60_000
    monkeypatch.setattr(dio, "MAX_READ_BYTES", 10_000)
    with pytest.raises(DiffcamError, match="array 'phase' declares 64"):
        load_phase(tmp_path / "p.npz")
    with pytest.raises(DiffcamError, match="max_bytes must be a positive integer"):
        read_image(tmp_path / "a.npy", max_bytes=0)


def test_wrong_keys_and_wrong_contents(tmp_path):
    """Missing arrays, wrong variable names, a group instead of an array, metadata of the
    wrong type, a colour PNG with alpha, a single path for a list: one DiffcamError line
    naming the file."""
    np.savez(tmp_path / "k.npz", theta=np.zeros((4, 4)))
    with pytest.raises(DiffcamError, match=r"k.npz: not a diffcam phase file: no array "
                                           r"'phase' \(it holds \['theta'\]\)"):
        load_phase(tmp_path / "k.npz")
    with pytest.raises(DiffcamError, match="no array 'b'"):
        read_npz(tmp_path / "k.npz", ("theta", "b"))
    cases = {
        "json.npz": dict(phase=np.zeros((4, 4), np.float32), meta=np.array("{not json")),
        "list.npz": dict(phase=np.zeros((4, 4), np.float32), meta=np.array("[1, 2]")),
        "neg.npz": dict(phase=np.zeros((4, 4), np.float32), meta=np.array(json.dumps(
            {"dx": -1, "wavelength": LAM, "aperture_radius": 1e-3}))),
        "extra.npz": dict(phase=np.zeros((4, 4), np.float32), meta=np.array(json.dumps(
            {"dx": 1e-6, "wavelength": LAM, "aperture_radius": 1e-3, "colour": 1}))),
        "nan.npz": dict(phase=np.full((4, 4), np.nan, np.float32), meta=np.array(json.dumps(
            {"dx": 1e-6, "wavelength": LAM, "aperture_radius": 1e-3}))),
        "1d.npz": dict(phase=np.zeros(4, np.float32), meta=np.array(json.dumps(
            {"dx": 1e-6, "wavelength": LAM, "aperture_radius": 1e-3}))),
        "numeric.npz": dict(phase=np.zeros((4, 4), np.float32), meta=np.array(3.0)),
    }
    for name, arrays in cases.items():
        np.savez(tmp_path / name, **arrays)
        with pytest.raises(DiffcamError, match=name) as err:
            load_phase(tmp_path / name)
        assert "\n" not in str(err.value)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DiffcamError, match="obj.npy"):
        read_image(tmp_path / "obj.npy")
    np.save(tmp_path / "c.npy", np.ones((4, 4), np.complex64))
    with pytest.raises(DiffcamError, match="unsupported data type complex64"):
        read_image(tmp_path / "c.npy")
    with h5py.File(tmp_path / "g.mat", "w") as f:
        f.create_group("psf")
    with pytest.raises(DiffcamError, match="'psf' is not an array"):
        read_mat_stack(tmp_path / "g.mat")
    scipy.io.savemat(tmp_path / "c.mat", {"psf": np.ones((4, 4, 2)) * 1j})
    with pytest.raises(DiffcamError, match="real numeric"):
        read_mat_stack(tmp_path / "c.mat")
    scipy.io.savemat(tmp_path / "w.mat", {"psf": np.ones((4, 4, 2))})
    with pytest.raises(DiffcamError, match=r"no variable 'stack'; it holds \['psf'\]"):
        read_mat_stack(tmp_path / "w.mat", key="stack")
    Image.fromarray(np.zeros((4, 4, 2), np.uint8)).save(tmp_path / "la.png")  # mode LA
    with pytest.raises(DiffcamError, match="alpha"):
        read_image(tmp_path / "la.png")
    with pytest.raises(DiffcamError, match="list of files"):
        read_psf_stack(str(tmp_path / "la.png"))
    (tmp_path / "d.tif").mkdir()
    with pytest.raises(DiffcamError, match="is a folder"):
        read_image(tmp_path / "d.tif")
    np.save(tmp_path / "huge.npy", np.full((2, 2), 1e300))
    with pytest.raises(DiffcamError, match="float32 range"):
        read_image(tmp_path / "huge.npy")


# ------------------------------------------------------------------ non-finite inputs

def test_non_finite_inputs_are_named():
    """NaN/Inf anywhere an array or number enters (readers' preprocessing,
    magnify_psf, wiener) raise a DiffcamError naming the argument."""
    ok = np.ones((8, 8), np.float32)
    bad = ok.copy()
    bad[2, 3] = np.nan
    psf = np.zeros((4, 4))
    psf[1:3, 1:3] = 1.0
    calls = [
        (lambda: subtract_background(bad, 0.0), "image"),
        (lambda: subtract_background(ok, np.inf), "background"),
        (lambda: dio.normalise_l2(bad), "image"),
        (lambda: downsample(bad, 2), "image"),
        (lambda: magnify_psf(bad, 5e-6, 22e-3, 25e-3, 1e-3), "psf_ref"),
        (lambda: magnify_psf(ok, 5e-6, 22e-3, [25e-3, np.nan], 1e-3), "z1"),
        (lambda: magnify_psf(ok, np.inf, 22e-3, 25e-3, 1e-3), "dx"),
        (lambda: magnify_psf(ok, 5e-6, 22e-3, 25e-3, 1e-3, (np.nan, 0.0)), "centre"),
        (lambda: wiener(bad, psf), "image"),
        (lambda: wiener(ok, np.where(psf > 0, np.inf, 0.0)), "psf"),
        (lambda: wiener(ok, psf, np.nan), "regularization"),
        (lambda: wiener(ok, psf, np.inf), "regularization"),
    ]
    for call, name in calls:
        with pytest.raises(DiffcamError, match=name):
            call()
    with pytest.raises(DiffcamError, match="non-negative with some light"):
        magnify_psf(np.zeros((8, 8)), 5e-6, 22e-3, 25e-3, 1e-3)
    with pytest.raises(ShapeError, match="one 2-D PSF"):
        magnify_psf(np.ones((2, 8, 8)), 5e-6, 22e-3, 25e-3, 1e-3)
    with pytest.raises(DiffcamError, match="positive integer"):
        downsample(ok, True)
    assert downsample(ok, np.int64(2)).shape == (4, 4)
    assert np.isfinite(np.asarray(wiener(ok, psf, np.int64(1)).image)).all()


# ------------------------------------------------------------------ magnify_psf

@pytest.mark.parametrize("shape", [(31, 40), (17, 9)])
@pytest.mark.parametrize("kind", ["cubic", "area"])
def test_magnify_psf_is_the_identity_at_m_1_with_light_at_the_edge(shape, kind):
    """m = 1 returns the reference (to 1e-5 of its peak, float32) even with light on
    every edge row and column: the periodic spline prefilter used to wrap the opposite
    edge in (an error of 0.27 of the peak on both shapes)."""
    rng = np.random.default_rng(3)
    ref = np.zeros(shape, np.float32)
    ref[0, :] = rng.random(shape[1])
    ref[-1, :] = rng.random(shape[1])
    ref[:, 0] += rng.random(shape[0])
    ref[:, -1] += 1.0
    ref[shape[0] // 3, shape[1] // 2] = 3.0
    out = np.asarray(magnify_psf(ref, 5e-6, 22e-3, 22e-3, 1e-3, kind=kind))
    np.testing.assert_allclose(out, ref, atol=1e-5 * ref.max())
    with warnings.catch_warnings():   # the old name warns once (tests/test_deprecation.py)
        warnings.simplefilter("ignore", DeprecationWarning)
        old = np.asarray(scale_psf(ref, 5e-6, 22e-3, 22e-3, 1e-3, kind=kind))
    np.testing.assert_allclose(old, ref, atol=1e-5 * ref.max())


def test_magnify_psf_shrinks_into_zeros_not_wrapped_light():
    """m < 1 of a frame lit on one edge: the far edge stays dark (zero-extended frame)."""
    ref = np.zeros((32, 32), np.float32)
    ref[:, -2:] = 1.0
    out = np.asarray(magnify_psf(ref, 5e-6, 22e-3, 30e-3, 5e-3))
    assert np.abs(out[:, :4]).max() < 1e-6 * out.max()
    np.testing.assert_allclose(out.sum(), ref.sum(), rtol=1e-5)


# ------------------------------------------------------------------ wiener

def test_wiener_does_not_depend_on_the_psf_scale(x64):
    """Scaling the PSF by 7 (or by a different factor per batch slice) leaves the
    estimate unchanged; it equals the dense Tikhonov solution for psf/sum(psf)."""
    rng = np.random.default_rng(12)
    image, psf = rng.random((8, 10)) + 0.1, rng.random((3, 4)) ** 2
    for boundary in ("circular", "same", "crop"):
        a = np.asarray(wiener(image, psf, 1e-2, boundary=boundary).image)
        b = np.asarray(wiener(image, 7 * psf, 1e-2, boundary=boundary).image)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max())
    unit = psf / psf.sum()
    model = convolution_model(jnp.asarray(unit), image.shape, "circular")
    n = image.size
    dense = np.stack([np.asarray(model(e)).ravel()
                      for e in np.eye(n).reshape((n,) + image.shape)], axis=1)
    lam = 1e-2 * float(np.max(np.abs(np.asarray(model.otf)) ** 2))
    ref = np.linalg.solve(dense.T @ dense + lam * np.eye(n), dense.T @ image.ravel())
    got = np.asarray(wiener(image, psf, 1e-2).image).ravel()
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
    stacked = wiener(np.stack([image, image]), np.stack([psf, 7 * psf]), 1e-2)
    np.testing.assert_allclose(stacked.image[1], stacked.image[0], rtol=1e-12)
    jitted = jax.jit(lambda h: wiener(image, h, 1e-2).image)(jnp.asarray(7 * psf))
    np.testing.assert_allclose(np.asarray(jitted).ravel(), ref, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------ soft aperture

@pytest.mark.parametrize("shape", [(9, 9), (8, 12)])
def test_soft_aperture_gradients_are_finite_at_the_centre_sample(debug_nans, x64, shape):
    """The centre sample has r = 0, where d sqrt(r²) is infinite: the gradients with
    respect to dx, radius and centre were NaN (dx, centre). They are finite now, and
    match central differences (relative step 1e-6, rtol 1e-5)."""
    w = jnp.asarray(np.random.default_rng(4).random(shape))

    def f(dx, radius, c):
        return jnp.sum(w * circular_aperture(shape, dx, radius, (c, 0.3 * c), edge="soft"))

    args = (1.0e-6, 2.7e-6, 0.0)
    grads = jax.jit(jax.grad(f, argnums=(0, 1, 2)))(*args)
    value = jax.jit(f)
    for k, g in enumerate(grads):
        assert np.isfinite(float(g))
        h = 1e-6 * max(abs(args[k]), 1e-6)
        plus, minus = list(args), list(args)
        plus[k] += h
        minus[k] -= h
        fd = (float(value(*plus)) - float(value(*minus))) / (2 * h)
        np.testing.assert_allclose(float(g), fd, rtol=1e-5, atol=1e-6 * max(abs(fd), 1.0))
