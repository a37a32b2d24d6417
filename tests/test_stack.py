"""PSF stacks (diffcam.model.stack): chunking, positions, sharding, streaming, save/load."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
import tifffile

from diffcam.model import Camera, psf, random_diffuser
from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.model.stack import FORMAT_VERSION, StackMeta, load_stack, psf_stack, save_stack

LAM = 532e-9
N = 96


@pytest.fixture(scope="module")
def setup():
    cam = Camera(wavelength=LAM, z2=1e-3, dx=4e-6, aperture_radius=0.15e-3, shape=(N, N),
                 crop=(80, 72))
    phase = np.asarray(random_diffuser(jax.random.key(0), (N, N), 4e-6, LAM, 40e-6))
    return cam, phase


def test_stack_equals_single_psfs_and_batch_size_does_not_matter(setup):
    """Every slice equals psf() at that depth and position (float32 round-off, 1e-5 of
    the peak), for batch sizes that do and do not divide the number of depths."""
    cam, phase = setup
    z = np.array([20e-3, 22e-3, 25e-3, 30e-3, 40e-3])
    pos = np.array([[0.0, 0.0], [-20e-6, 40e-6]])  # (y1, x1)
    a = psf_stack(phase, cam, z, offsets=pos, batch_size=2)
    b = psf_stack(phase, cam, z, offsets=pos, batch_size=5)
    assert a.shape == (5, 2, 80, 72)
    ref = np.asarray(psf(phase, cam, z[3], y1=-20e-6, x1=40e-6))
    np.testing.assert_allclose(a[3, 1], ref, atol=1e-5 * ref.max())
    np.testing.assert_allclose(a, b, atol=1e-6 * a.max())


@pytest.mark.slow
def test_on_axis_stack_and_the_old_spelling_of_offsets(setup):
    """Without offsets, the on-axis slices of a stack with offsets; the deprecated
    ``positions`` ((x1, y1) rows) still gives the same stack, with a warning."""
    cam, phase = setup
    z = np.array([20e-3, 22e-3, 25e-3, 30e-3, 40e-3])
    pos = np.array([[0.0, 0.0], [-20e-6, 40e-6]])  # (y1, x1)
    a = psf_stack(phase, cam, z, offsets=pos, batch_size=2)
    with pytest.warns(DeprecationWarning, match="offsets"):  # old spelling: (x1, y1) rows
        old = psf_stack(phase, cam, z[3:4], positions=pos[:, ::-1])
    np.testing.assert_allclose(old[0], a[3], atol=1e-6 * a.max())
    on_axis = psf_stack(phase, cam, z, batch_size=3)
    assert on_axis.shape == (5, 80, 72)
    np.testing.assert_allclose(on_axis, a[:, 0], atol=1e-6 * a.max())


def test_direct_stack_and_spectrum(setup):
    """The direct path and a broadband spectrum run through the same chunked loop."""
    cam, phase = setup
    import dataclasses
    direct = dataclasses.replace(cam, method="direct")
    z = np.array([30e-3, 50e-3])
    spec = ([500e-9, 560e-9], [1.0, 2.0])
    s = psf_stack(phase, direct, z, spectrum=spec, batch_size=1)
    ref = np.asarray(psf(phase, direct, 50e-3, spectrum=spec))
    np.testing.assert_allclose(s[1], ref, atol=1e-5 * ref.max())


def test_empty_depths_and_bad_positions(setup):
    cam, phase = setup
    with pytest.raises(DiffcamError, match="empty"):
        psf_stack(phase, cam, [])
    with pytest.raises(ShapeError, match="offsets"):
        psf_stack(phase, cam, [25e-3], offsets=[1e-6, 2e-6])
    with pytest.raises(DiffcamError, match="z1"):
        psf_stack(phase, cam, [25e-3, -1e-3])


def test_stream_to_npy_and_tiff_match_memory(setup, tmp_path, capsys):
    """out='.npy', '.tif' and '.npz' write the same numbers as the in-memory stack, with
    their metadata; the TIFF is an ImageJ hyperstack; progress=True shows a bar."""
    cam, phase = setup
    z = np.linspace(20e-3, 30e-3, 7)
    mem = psf_stack(phase, cam, z, batch_size=3)
    npy = psf_stack(phase, cam, z, batch_size=3, out=tmp_path / "s.npy", progress=True)
    np.testing.assert_array_equal(np.asarray(npy), mem)
    assert "PSF stack" in capsys.readouterr().err
    tif = psf_stack(phase, cam, z, batch_size=3, out=tmp_path / "s.tif")
    np.testing.assert_array_equal(np.asarray(tif), mem)
    with tifffile.TiffFile(tmp_path / "s.tif") as f:
        assert f.is_imagej and len(f.pages) == 7
    stack, meta = load_stack(tmp_path / "s.tif")
    np.testing.assert_array_equal(stack, mem)
    np.testing.assert_allclose(meta.depths, z)
    stack, meta = load_stack(tmp_path / "s.npy")
    np.testing.assert_array_equal(stack, mem)
    assert meta.camera["crop"] == [80, 72]
    npz = psf_stack(phase, cam, z, batch_size=3, out=tmp_path / "s.npz")  # streamed
    np.testing.assert_array_equal(npz, mem)
    with np.load(tmp_path / "s.npz") as f:  # a plain .npz numpy reads
        np.testing.assert_array_equal(f["stack"], mem)


def test_save_load_round_trip(setup, tmp_path):
    """.npz round-trips pixels and metadata exactly; .tif keeps float32 pixels exactly
    (positions as the ImageJ channel axis)."""
    cam, phase = setup
    z = np.array([21e-3, 27e-3])
    pos = np.array([[0.0, 0.0], [10e-6, 5e-6], [-3e-6, 0.0]])
    s = psf_stack(phase, cam, z, offsets=pos)
    meta = StackMeta(depths=z, offsets=pos, pitch=4e-6, wavelengths=np.array([LAM]),
                     weights=np.array([1.0]), camera={"z2": 1e-3})
    for name in ("a.npz", "a.tif"):
        save_stack(tmp_path / name, s, meta)
        back, m2 = load_stack(tmp_path / name)
        np.testing.assert_array_equal(back, s)
        np.testing.assert_array_equal(m2.depths, z)
        np.testing.assert_array_equal(m2.offsets, pos)
        assert m2.format_version == FORMAT_VERSION and m2.camera == {"z2": 1e-3}
    with pytest.raises(ShapeError):
        save_stack(tmp_path / "b.npz", s[:1], meta)
    future = json.loads(meta.to_json())
    future["format_version"] = FORMAT_VERSION + 1
    with pytest.raises(DiffcamError, match="upgrade"):
        StackMeta.from_json(json.dumps(future))


def test_new_depths_reuse_the_compiled_chunk(setup):
    """A new set of depths of the same chunk size reuses the compiled chunk (both of its
    jitted halves, each compiled twice: for the first chunk, which allocates its buffers,
    and for the later ones, which write over them)."""
    from diffcam.model.stack import _chunk_inputs, _chunk_outputs

    cam, phase = setup
    psf_stack(phase, cam, [20e-3, 21e-3, 22e-3], batch_size=2)
    before = [f._cache_size() for f in (_chunk_inputs, _chunk_outputs)]
    psf_stack(phase, cam, [30e-3, 31e-3, 32e-3, 33e-3], batch_size=2)
    assert [f._cache_size() for f in (_chunk_inputs, _chunk_outputs)] == before


@pytest.mark.slow
def test_sharded_matches_unsharded():
    """On 4 forced host devices the depth axis is sharded over a Mesh; the result equals
    the single-device stack to float32 round-off (1e-6 of the peak)."""
    code = textwrap.dedent("""
        import jax, numpy as np
        from diffcam.model.camera import Camera, random_diffuser
        from diffcam.model.stack import psf_stack
        assert len(jax.devices()) == 4
        cam = Camera(wavelength=532e-9, z2=1e-3, dx=4e-6, aperture_radius=0.15e-3,
                     shape=(96, 96))
        ph = random_diffuser(jax.random.key(0), (96, 96), 4e-6, 532e-9, 40e-6)
        z = np.linspace(20e-3, 30e-3, 10)
        pos = np.array([[0.0, 0.0], [20e-6, 0.0]])
        a = psf_stack(ph, cam, z, offsets=pos, batch_size=2)
        b = psf_stack(ph, cam, z, offsets=pos, batch_size=2, devices=jax.devices()[:1])
        print(float(np.abs(a - b).max() / b.max()))
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4",
               JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert float(out.stdout.strip().splitlines()[-1]) < 1e-6


_PROCESS = textwrap.dedent("""
    import sys
    import numpy as np
    import diffcam as dc            # importing diffcam leaves JAX's backend unstarted
    import jax
    address, rank, folder = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=address, num_processes=2,
                               process_id=rank)
    assert jax.process_count() == 2 and len(jax.devices()) == 2
    cam = dc.Camera(wavelength=532e-9, z2=1e-3, dx=4e-6, aperture_radius=0.15e-3,
                    shape=(96, 96), crop=(80, 72))
    args = dict(offsets=np.array([[0.0, 0.0], [-20e-6, 40e-6]]), batch_size=1,
                spectrum=dc.Spectrum(np.array([500e-9, 560e-9]), np.array([1.0, 2.0])))
    phase, z = np.load(f"{folder}/phase.npy"), np.linspace(20e-3, 30e-3, 5)
    np.save(f"{folder}/memory{rank}.npy", dc.psf_stack(phase, cam, z, **args))
    for suffix in ("npy", "npz", "tif"):
        stack = dc.psf_stack(phase, cam, z, out=f"{folder}/stack.{suffix}", **args)
        np.save(f"{folder}/returned{rank}-{suffix}.npy", stack)
""")


@pytest.mark.slow  # 25 s: both processes compile the sharded chunk (9-13 s on 2 cores)
def test_two_processes_equal_one(setup, tmp_path):
    """Two JAX processes (``jax.distributed.initialize``, gloo collectives on CPU, one
    device each) split every chunk's depths between them. The stack with two lateral
    positions and a two-line Spectrum, in memory on each process and streamed by process
    0 to .npy, .npz and .tif (what every process returns, and what load_stack reads),
    equals the single-process stack bit for bit."""
    from diffcam.apps.processes import free_port
    from diffcam.model.camera import Spectrum

    cam, phase = setup
    np.save(tmp_path / "phase.npy", phase)
    address = f"localhost:{free_port()}"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = [subprocess.Popen([sys.executable, "-c", _PROCESS, address, str(rank),
                               str(tmp_path)], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for rank in (0, 1)]
    logs = [p.communicate(timeout=240)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], logs
    pos = np.array([[0.0, 0.0], [-20e-6, 40e-6]])
    spectrum = Spectrum(np.array([500e-9, 560e-9]), np.array([1.0, 2.0]))
    one = psf_stack(phase, cam, np.linspace(20e-3, 30e-3, 5), offsets=pos,
                    spectrum=spectrum, batch_size=1)
    assert one.shape == (5, 2, 80, 72)
    for rank in (0, 1):
        np.testing.assert_array_equal(np.load(tmp_path / f"memory{rank}.npy"), one)
    for suffix in ("npy", "npz", "tif"):
        for rank in (0, 1):
            returned = np.load(tmp_path / f"returned{rank}-{suffix}.npy")
            np.testing.assert_array_equal(returned.reshape(one.shape), one)
        stack, meta = load_stack(tmp_path / f"stack.{suffix}")
        np.testing.assert_array_equal(stack, one)
        np.testing.assert_array_equal(meta.offsets, pos)
    assert not [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]


def test_format_1_positions_are_read_as_offsets():
    """Files of format 1 stored (x1, y1) rows as ``positions``; they load as (y1, x1)."""
    old = json.dumps({"depths": [0.02], "positions": [[1e-6, 2e-6]], "pitch": 4e-6,
                      "wavelengths": [LAM], "weights": [1.0], "camera": {},
                      "normalised": True, "format_version": 1})
    meta = StackMeta.from_json(old)
    np.testing.assert_array_equal(meta.offsets, [[2e-6, 1e-6]])
