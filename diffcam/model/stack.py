"""PSF stacks over depths and lateral positions: chunked, sharded, streamed to disk.

`psf_stack` evaluates PSFs for every depth in ``z1`` (and every lateral position)
in chunks of ``batch_size`` depths per device, each copied to a host array (or a
memory-mapped file) while the next one computes, so at most two chunks are in flight
and working memory is set by the chunk, not by the number of depths. A chunk is two
jitted calls: the fields (or spectra) its FFTs start from, then the FFTs and
intensities (see `diffcam.model.point_spread.fields_for_fft`); both write over the last chunk's
two field-sized buffers (donated), which spares a fresh, page-faulted buffer per call.
A chunk holds one field per depth, wavelength and, on the direct path, lateral position.
With
several devices the chunk's depth axis is sharded over a ``jax.sharding.Mesh`` of them.
After ``jax.distributed.initialize()`` ``jax.devices()`` lists every process's devices,
so the mesh spans processes and hosts: each process computes its devices' share of a
chunk, and the chunk is all-gathered so that every process holds it; a stack in memory
is then on every process, and a file is written by process 0 alone
(docs/distributed.md). Everything the depths share (the diffuser's field, or its FFT on
the scaling-theorem path) is computed once per process.

Saving and loading (`save_stack`, `load_stack`) keep the metadata
(`StackMeta`) beside the pixels: ``.npz`` round-trips exactly; ``.tif`` is an
ImageJ hyperstack (axes ``ZYX``, or ``ZCYX`` with lateral positions as channels) with
the metadata as JSON in the ImageJ ``Info`` property and the pitch as resolution.
"""

from __future__ import annotations

import dataclasses
import json
import os
import struct
import warnings
import zipfile
from functools import partial
from typing import Iterator, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import tifffile
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm  # not tqdm.auto: it warns in Jupyter without ipywidgets

from diffcam.model.camera import OFF_AXIS_TERMS, Camera, as_spectrum, real_dtype
from diffcam.model.point_spread import (check_inputs, depth_list, diffuser_fields, fields_for_fft,
                                        fields_per_depth, irradiance_and_fields, items_per_chunk)
from diffcam.core.errors import DiffcamError, ShapeError, check_finite, check_positive
from diffcam.core.options import Options
from diffcam.core.progress import enabled
from diffcam.io import atomic_output, check_output_path, check_read_size, read_npz

__all__ = ["psf_stack", "iter_psf_stack", "PsfStackOptions", "StackMeta", "save_stack", "load_stack",
           "FORMAT_VERSION"]

FORMAT_VERSION = 2  # 2: lateral offsets stored as (y1, x1)
_PROGRESS_FROM = 32  # show a progress bar by default from this many depths


@dataclasses.dataclass(frozen=True)
class StackMeta:
    """What a PSF stack is: axes, units and the camera that made it (SI units).

    Attributes:
        depths: z1 of each slice, metres, shape (nz,).
        offsets: (y1, x1) of each lateral source position, metres, shape (npos, 2), or
            ``None`` when the stack has no position axis (on-axis source). Files of
            format version 1 stored ``positions`` as (x1, y1); they are read into this.
        pitch: sample pitch of the stored images, metres.
        wavelengths: metres; ``weights``: their relative power.
        camera: the camera's fields as plain numbers (``Camera`` attribute names).
        normalised: each PSF sums to one (else physical irradiance).
        format_version: `FORMAT_VERSION` of the writer.
    """

    depths: np.ndarray
    offsets: np.ndarray | None
    pitch: float
    wavelengths: np.ndarray
    weights: np.ndarray
    camera: dict
    normalised: bool = True
    format_version: int = FORMAT_VERSION

    def to_json(self) -> str:
        d = dataclasses.asdict(self)
        for k in ("depths", "offsets", "wavelengths", "weights"):
            d[k] = None if d[k] is None else np.asarray(d[k], dtype=np.float64).tolist()
        return json.dumps(d)

    @classmethod
    def from_json(cls, text: str) -> "StackMeta":
        d = json.loads(text)
        if d.get("format_version", 0) > FORMAT_VERSION:
            raise DiffcamError(f"stack written by format version {d['format_version']}, this "
                               f"diffcam reads ≤ {FORMAT_VERSION}; upgrade diffcam.")
        if "positions" in d:  # format 1: (x1, y1) columns
            legacy = d.pop("positions")
            d["offsets"] = None if legacy is None else np.asarray(legacy)[:, ::-1]
        for k in ("depths", "wavelengths", "weights"):
            d[k] = np.asarray(d[k], dtype=np.float64)
        if d["offsets"] is not None:
            d["offsets"] = np.asarray(d["offsets"], dtype=np.float64).reshape(-1, 2)
            check_finite("offsets", d["offsets"])
        for name in ("depths", "pitch", "wavelengths"):
            check_positive(name, d[name], "m")
        weights = d["weights"]
        if weights.shape != d["wavelengths"].shape or not (
                np.all(weights >= 0) and weights.sum() > 0):
            raise DiffcamError(f"weights {weights.tolist()!r:.60} must be one power ≥ 0 per "
                               f"wavelength, not all 0; the metadata are damaged.")
        return cls(**d)


def camera_record(camera: Camera) -> dict:
    """The camera as JSON-able numbers (a mask is recorded by its shape only)."""
    rec = {"wavelength": float(camera.wavelength), "z2": float(camera.z2),
           "dx": float(camera.dx), "shape": list(camera.shape), "pad": list(camera.pad),
           "crop": list(camera.out_shape), "method": camera.method, "edge": camera.edge}
    traced = ("aperture_radius", *OFF_AXIS_TERMS)
    rec.update({n: float(getattr(camera, n)) for n in traced if getattr(camera, n) is not None})
    if camera.aperture_mask is not None:
        rec["aperture_mask_shape"] = list(np.shape(camera.aperture_mask))
    return rec


# ----------------------------------------------------------------------------- compute

def _per_device(fn, sharding, batched, shared):
    """``fn(*batched, *shared)``, with a ``sharding`` over devices: each device computes
    ``fn`` on its own slice of the ``batched`` arguments (their leading axis) with the
    ``shared`` ones replicated (``jax.shard_map``). Left to XLA's partitioner, the FFTs
    were all-gathered and every device computed the whole chunk. No collective runs
    inside (``check_vma=False``: the loops inside need no replication types)."""
    if sharding is None:
        return fn(*batched, *shared)
    per_device = jax.shard_map(lambda b, s: fn(*b, *s), mesh=sharding.mesh,
                               in_specs=(sharding.spec, PartitionSpec()),
                               out_specs=sharding.spec, check_vma=False)
    return per_device(batched, shared)


@partial(jax.jit, static_argnames=("sharding",), donate_argnums=0, keep_unused=True)
def _chunk_inputs(scratch, prepared, camera, wavelengths, z1, positions, sharding):
    """The FFT inputs of a chunk, written over ``scratch`` (donated)."""
    del scratch
    fields = jax.vmap(lambda z, p, c, w, x: fields_for_fft(p, c, w, z, x),
                      in_axes=(0, None, None, None, None))
    return _per_device(fields, sharding, (z1,), (prepared, camera, wavelengths, positions))


@partial(jax.jit, static_argnames=("normalise", "sharding"), donate_argnums=(0, 1),
         keep_unused=True)
def _chunk_outputs(inputs, scratch, camera, wavelengths, weights, z1, positions, normalise,
                   sharding):
    """PSFs of a chunk, and the two buffers its FFTs wrote: ``inputs`` and ``scratch``
    (both donated) are written over, so no fresh N² buffer is page-faulted in per chunk."""
    del scratch
    psfs = jax.vmap(lambda u, z, c, w, g, x: irradiance_and_fields(u, c, w, g, z, x,
                                                                    normalise),
                    in_axes=(0, 0, None, None, None, None))
    return _per_device(psfs, sharding, (inputs, z1), (camera, wavelengths, weights,
                                                      positions))


def _chunk(prepared, camera, wavelengths, weights, z1, positions, normalise, sharding,
           buffers=None):
    """PSFs (nz, npos, ny, nx) for the depths ``z1``, and the ``buffers`` to pass to the
    next call. Two jitted calls, so that the second one starts with its FFTs (see
    `diffcam.model.point_spread.fields_for_fft`); both write over the last chunk's
    buffers. The first chunk has none to write over (``None``): it allocates them, and a
    stack of one chunk allocates nothing more."""
    scratch = (None, None) if buffers is None else buffers
    inputs = _chunk_inputs(scratch[0], prepared, camera, wavelengths, z1, positions,
                           sharding)
    return _chunk_outputs(inputs, scratch[1], camera, wavelengths, weights, z1, positions,
                          normalise, sharding)


_prepare = jax.jit(diffuser_fields)


def _offsets_array(positions):
    if positions is None:
        return np.zeros((1, 2))
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 2 or pos.shape[0] == 0:
        raise ShapeError(f"offsets must be an (npos, 2) array of (y1, x1) in metres, "
                         f"got shape {pos.shape}.")
    if not np.all(np.isfinite(pos)):
        raise DiffcamError("offsets contain NaN/Inf; give finite (y1, x1) in metres.")
    return pos


class PsfStackOptions(Options):
    """How [`psf_stack`][diffcam.model.stack.psf_stack] and
    [`iter_psf_stack`][diffcam.model.stack.iter_psf_stack] compute.

    Attributes:
        normalise: each PSF sums to one (default) or is the physical irradiance.
        batch_size: depths per device per chunk; working memory grows with it.
            Default: about 2**20 field samples per chunk (one depth from 1024², or
            from fewer samples with several wavelengths or direct-path positions).
        devices: devices to shard the depth axis over (default ``jax.devices()``:
            every process's, after ``jax.distributed.initialize()``).
        accept_undersampling: turn sampling errors into warnings.
        progress: [`psf_stack`][diffcam.model.stack.psf_stack] shows a tqdm bar (on process
            0 of several); default on from 32 depths; ``DIFFCAM_PROGRESS=0`` turns it off.
        to_host: [`iter_psf_stack`][diffcam.model.stack.iter_psf_stack] yields host numpy
            arrays (default) or device arrays.
    """

    normalise: bool = True
    batch_size: int | None = None
    devices: Sequence | None = None
    accept_undersampling: bool = False
    progress: bool | None = None
    to_host: bool = True


def _options_and_offsets(options, offsets, overrides):
    """The `PsfStackOptions` and the source offsets (y1, x1); the deprecated
    ``positions=`` (x1, y1) keyword among ``overrides`` is turned into offsets."""
    positions = overrides.pop("positions", None)
    return PsfStackOptions.of(options, **overrides), _legacy_positions(offsets, positions)


def _legacy_positions(offsets, positions):
    """``offsets`` (y1, x1), or the deprecated ``positions`` (x1, y1) turned into them."""
    if positions is None:
        return offsets
    if offsets is not None:
        raise DiffcamError("give offsets (y1, x1) or the deprecated positions (x1, y1), "
                           "not both.")
    warnings.warn("positions= (x1, y1) is deprecated: pass offsets= with (y1, x1) rows, "
                  "the array order every lateral pair in diffcam uses.", DeprecationWarning,
                  stacklevel=4)
    return np.asarray(positions, dtype=np.float64)[:, ::-1]


def iter_psf_stack(phase, camera: Camera, z1, *, offsets=None, spectrum=None,
                   options: PsfStackOptions | None = None, **overrides
                   ) -> Iterator[tuple[int, np.ndarray | jax.Array]]:
    """Yield ``(start, psfs)`` chunk by chunk: ``psfs[i]`` is depth ``z1[start + i]``,
    shape ``(n, npos, ny, nx)``: host numpy, or with ``to_host=False`` the device array
    (for work that stays on the device, a GPU reconstruction say; with several
    processes, a global array whose shards are on each process's devices). Other
    arguments as in
    [`psf_stack`][diffcam.model.stack.psf_stack]; the inputs are checked when this is
    called, before the first chunk.

    It runs on the host (it loops over chunks), so it cannot be traced and its input checks
    always run; to jit or differentiate through PSFs, ``jax.vmap``
    [`psf`][diffcam.model.point_spread.psf] over ``z1`` (its checks are skipped under
    ``jax.jit``: call it once eagerly to validate).
    """
    depths = depth_list(z1)
    opts, offsets = _options_and_offsets(options, offsets, overrides)
    pos = _offsets_array(offsets)
    wavelengths, weights = as_spectrum(spectrum, camera)
    batch_size, devices = opts.batch_size, opts.devices
    if batch_size is None:
        batch_size = items_per_chunk(camera, len(wavelengths) * fields_per_depth(camera, len(pos)))
    if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise DiffcamError(f"batch_size must be a positive int, got {batch_size!r}.")
    check_inputs(phase, camera, depths, np.hypot(pos[:, 0], pos[:, 1]), wavelengths,
                 opts.accept_undersampling)
    devices = list(jax.devices()) if devices is None else list(devices)
    # no larger than the depths need, to a power of two (few compilations): a chunk is
    # padded to its full size, and 64 slots for 32 depths computed twice the PSFs (128²)
    need = -(-depths.size // len(devices))
    batch_size = min(int(batch_size), 1 << (need - 1).bit_length())
    return _chunks(phase, camera, depths, pos, wavelengths, weights, opts.normalise,
                   batch_size, devices, opts.to_host)


def _chunks(phase, camera, depths, pos, wavelengths, weights, normalise, batch_size,
            devices, host):
    sharding = None
    step = batch_size * len(devices)
    if len(devices) > 1:
        mesh = Mesh(np.array(devices), ("batch",))
        sharding = NamedSharding(mesh, PartitionSpec("batch"))
        replicate = NamedSharding(mesh, PartitionSpec())
        put = lambda a: jax.device_put(a, replicate)  # noqa: E731
    else:
        put = lambda a: jax.device_put(a, devices[0])  # noqa: E731
    dtype = real_dtype(camera)
    camera, phase = put(camera), put(phase)
    wavelengths, weights = put(wavelengths.astype(dtype)), put(weights.astype(dtype))
    prepared = _prepare(phase, camera, wavelengths)
    pos_dev = put(jnp.asarray(pos, dtype))

    # a chunk spanning other processes' devices is all-gathered as soon as it is
    # dispatched, so that every process can copy it out while the next chunk computes
    gather = host and sharding is not None and not sharding.is_fully_addressable

    def to_host(start, out, n):
        if not host:
            return start, out[:n]
        whole = out.addressable_data(0) if gather else out
        return start, np.asarray(jax.device_get(whole))[:n]

    pending = buffers = None  # the chunk in flight is copied out after the next one starts
    for start in range(0, depths.size, step):
        block = depths[start:start + step]
        n = block.size
        block = np.pad(block, (0, step - n), mode="edge")  # fixed shape: one compilation
        zb = jnp.asarray(block, dtype)
        zb = jax.device_put(zb, sharding) if sharding is not None else put(zb)
        out, buffers = _chunk(prepared, camera, wavelengths, weights, zb, pos_dev, normalise,
                              sharding, buffers)
        if gather:
            out = _all_gather(out, replicate)
        if pending is not None:
            yield to_host(*pending)
        pending = (start, out, n)
    yield to_host(*pending)


def _identity(x):
    return x


def _all_gather(out, replicate):
    """``out`` on every device (``replicate``: a replicated sharding of its mesh), the
    collective dispatched and not waited for."""
    return jax.jit(_identity, out_shardings=replicate)(out)


def psf_stack(phase, camera: Camera, z1, *, offsets=None, spectrum=None,
              out: str | os.PathLike | None = None,
              options: PsfStackOptions | None = None, **overrides) -> np.ndarray:
    """PSFs for every depth in ``z1`` and every lateral position, chunk by chunk.

    It runs on the host (it loops over chunks and may write a file), so it cannot be traced
    and its input checks always run; to jit or differentiate through PSFs, ``jax.vmap``
    [`psf`][diffcam.model.point_spread.psf] over ``z1`` (its checks are skipped under
    ``jax.jit``: call it once eagerly to validate).

    Args:
        phase: the diffuser (phase in radians at ``camera.wavelength``, or a
            [`HeightMap`][diffcam.model.camera.HeightMap]).
        camera: the [`Camera`][diffcam.model.camera.Camera].
        z1: depths, metres, shape (nz,) (non-empty, all > 0).
        offsets: ``(npos, 2)`` lateral source positions ``(y1, x1)``, metres (array
            order, like every lateral pair in diffcam); ``None`` for an on-axis source
            (the position axis is then dropped). ``positions=`` of (x1, y1) rows is the
            deprecated spelling.
        spectrum: ``(wavelengths, weights)`` as in
            [`diffcam.model.point_spread.psf`][diffcam.model.point_spread.psf].
        out: stream the stack to this file instead of memory: ``.npy`` (a memory-mapped
            array; metadata in ``<out>.json``), ``.npz`` (uncompressed, ``stack`` and
            ``meta`` members, as [`save_stack`][diffcam.model.stack.save_stack] writes) or
            ``.tif``/``.tiff`` (ImageJ hyperstack written page by page, metadata inside).
            ``None`` keeps it in memory. The
            path is checked before anything is computed
            ([`diffcam.io.check_output_path`][diffcam.io.writing.check_output_path]), and
            the file is written atomically
            ([`diffcam.io.atomic_output`][diffcam.io.writing.atomic_output]): an existing
            file is replaced only once the whole stack is written, and an error, Ctrl-C or
            SIGTERM meanwhile leaves it as it was, with no temporary file behind. With
            several processes (``jax.distributed``) process 0 writes it, and every process
            returns its memory map once it is written: the folder must be one they all see.
        options: [`PsfStackOptions`][diffcam.model.stack.PsfStackOptions] (``normalise``,
            ``batch_size``, ``devices``, ``accept_undersampling``, ``progress``); keywords
            named after its fields replace them.

    Returns:
        float array ``(nz, npos, ny, nx)`` (or ``(nz, ny, nx)`` without positions):
        numpy in memory, or a read-only memory map of ``out``; the whole stack on
        every process.
    """
    outputs = _output_paths(out)  # before any work: a bad path costs nothing
    depths = depth_list(z1)
    opts, offsets = _options_and_offsets(options, offsets, overrides)
    chunks = iter_psf_stack(phase, camera, depths, offsets=offsets, spectrum=spectrum,
                            options=dataclasses.replace(opts, to_host=True))
    npos = 1 if offsets is None else len(offsets)
    full = (depths.size, npos) + tuple(camera.out_shape)
    shape = full if offsets is not None else (full[0],) + full[2:]
    show = depths.size >= _PROGRESS_FROM if opts.progress is None else opts.progress
    show = enabled(show) and jax.process_index() == 0  # one bar, however many processes
    bar = tqdm(total=depths.size, unit="depth", disable=not show, desc="PSF stack")
    meta = _meta(camera, depths, offsets, spectrum, opts.normalise)

    def pages():
        for start, block in chunks:
            bar.update(block.shape[0])
            yield block if offsets is not None else block[:, 0]

    try:
        if out is None:
            stack = np.empty(shape, np.float32)
            for start, block in _blocks(pages()):
                stack[start:start + len(block)] = block
            return stack
        if jax.process_index() == 0:
            _write(outputs, pages(), shape, meta)
        else:  # process 0 writes the file; the others compute their shares of each chunk
            for _ in pages():
                pass
        if jax.process_count() > 1:  # the file is complete before any process opens it
            multihost_utils.sync_global_devices("diffcam.psf_stack: file written")
        return _open_written(outputs[0])
    finally:
        bar.close()


def _write(outputs, pages, shape, meta: StackMeta) -> None:
    """Stream ``pages`` (blocks of PSFs) into ``outputs`` (`_output_paths`)
    atomically: the old files stay as they were until every block is written."""
    path = outputs[0]
    if path.endswith(".npy"):  # pixels and metadata replace the old pair together
        with atomic_output(*outputs) as (temp, temp_json):
            stack = np.lib.format.open_memmap(temp, mode="w+", dtype=np.float32,
                                              shape=shape)
            for start, block in _blocks(pages):
                stack[start:start + len(block)] = block
            stack.flush()
            del stack
            with open(temp_json, "w") as f:
                f.write(meta.to_json())
    elif path.endswith(".npz"):
        with atomic_output(path) as temp:
            _write_npz(temp, pages, shape, meta)
    else:
        with atomic_output(path) as temp:
            _write_tiff(temp, (page for block in pages for page in block), shape, meta)


def _open_written(path: str) -> np.ndarray:
    """A read-only memory map of the stack in ``path``, written by `_write`."""
    if path.endswith(".npy"):
        return np.load(path, mmap_mode="r")
    if path.endswith(".npz"):
        return _memmap_npz_stack(path)
    return tifffile.memmap(path, mode="r")


def _output_paths(out) -> tuple[str, ...]:
    """The files ``psf_stack(out=...)`` will write, checked: ``()`` for ``None``."""
    if out is None:
        return ()
    path = os.fspath(check_output_path(out))
    if path.endswith(".npy"):
        return path, os.fspath(check_output_path(path + ".json"))
    if path.endswith((".tif", ".tiff", ".npz")):
        return (path,)
    raise DiffcamError(f"out must end in .npy, .npz, .tif or .tiff, got {path!r}.")


def _blocks(pages):
    start = 0
    for block in pages:
        yield start, block
        start += len(block)


def _meta(camera, depths, offsets, spectrum, normalise):
    wavelengths, weights = as_spectrum(spectrum, camera)
    return StackMeta(depths=np.asarray(depths, np.float64),
                     offsets=None if offsets is None else _offsets_array(offsets),
                     pitch=float(camera.dx), wavelengths=np.asarray(wavelengths, np.float64),
                     weights=np.asarray(weights, np.float64), camera=camera_record(camera),
                     normalised=bool(normalise))


# ------------------------------------------------------------------------ save / load

def _write_tiff(path, pages, shape, meta: StackMeta):
    axes = "ZCYX" if len(shape) == 4 else "ZYX"
    um = meta.pitch * 1e6
    dz = float(np.median(np.diff(meta.depths))) * 1e3 if meta.depths.size > 1 else 1.0
    with tifffile.TiffWriter(path, imagej=True) as tif:
        tif.write(pages, shape=shape, dtype=np.float32, resolution=(1 / um, 1 / um),
                  metadata={"axes": axes, "unit": "um", "spacing": dz,
                            "Info": meta.to_json()}, contiguous=True)


def _write_npz(path, blocks, shape, meta: StackMeta):
    """``stack`` and ``meta`` members of an uncompressed ``.npz``, the stack streamed
    block by block (memory stays one block whatever the number of depths)."""
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float32)),
              "fortran_order": False, "shape": tuple(shape)}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
        with archive.open("stack.npy", "w", force_zip64=True) as member:
            np.lib.format.write_array_header_2_0(member, header)
            for block in blocks:
                member.write(np.ascontiguousarray(block, np.float32).tobytes())
        with archive.open("meta.npy", "w") as member:
            np.lib.format.write_array(member, np.array(meta.to_json()))


def _memmap_npz_stack(path) -> np.memmap:
    """A read-only memory map of the ``stack`` member `_write_npz` stored
    uncompressed: the array starts after the zip entry's local header and its .npy
    header (format 2.0), so nothing is read into memory."""
    with zipfile.ZipFile(path) as archive:
        start = archive.getinfo("stack.npy").header_offset
    with open(path, "rb") as f:
        f.seek(start + 26)  # the local file header: name and extra-field lengths at 26
        name_len, extra_len = struct.unpack("<HH", f.read(4))
        f.seek(start + 30 + name_len + extra_len)
        np.lib.format.read_magic(f)
        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        return np.memmap(path, dtype=dtype, mode="r", offset=f.tell(), shape=shape)


def save_stack(path: str | os.PathLike, stack, meta: StackMeta) -> None:
    """Write ``stack`` with ``meta`` to ``.npz`` (exact round trip) or ``.tif``/``.tiff``
    (ImageJ hyperstack, float32; the ImageJ Z spacing is the median depth step in mm).

    The path is checked first and the file written atomically
    ([`diffcam.io.atomic_output`][diffcam.io.writing.atomic_output]): an existing file is
    untouched on any failure."""
    path = os.fspath(path)
    if not path.endswith((".npz", ".tif", ".tiff")):
        raise DiffcamError(f"save_stack writes .npz, .tif or .tiff, got {path!r}.")
    check_output_path(path)
    stack = np.asarray(stack)
    nz = meta.depths.size
    want = 3 if meta.offsets is None else 4
    if stack.ndim != want or stack.shape[0] != nz or (
            want == 4 and stack.shape[1] != len(meta.offsets)):
        npos = None if meta.offsets is None else len(meta.offsets)
        raise ShapeError(f"stack shape {stack.shape} does not match the metadata "
                         f"({nz} depths, {npos} positions).")
    text = meta.to_json()
    with atomic_output(path) as temp:
        if path.endswith(".npz"):
            with open(temp, "wb") as fh:  # a file object: numpy appends no second suffix
                np.savez(fh, stack=stack, meta=np.array(text))
        else:
            _write_tiff(temp, stack.astype(np.float32), stack.shape, meta)


def load_stack(path: str | os.PathLike) -> tuple[np.ndarray, StackMeta]:
    """Read a stack written by [`save_stack`][diffcam.model.stack.save_stack] or
    [`psf_stack`][diffcam.model.stack.psf_stack] (``out=``).

    Raises:
        DiffcamError: one line naming the file and what is wrong with it (not a stack,
            damaged, metadata missing or not matching the pixels).
    """
    path = os.fspath(path)
    what = "a diffcam PSF stack"
    if path.endswith(".npz"):
        arrays = read_npz(path, ["stack", "meta"], what=what)
        stack, meta = arrays["stack"], _meta_from(path, str(arrays["meta"]))
    elif path.endswith(".npy"):
        try:
            with open(path + ".json") as f:
                text = f.read()
        except OSError as e:
            raise DiffcamError(f"{path}: its metadata {path}.json cannot be read "
                               f"({e.strerror or e}).") from None
        meta = _meta_from(path, text)
        try:
            stack = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as e:
            raise DiffcamError(f"{path}: not {what} ({e}).") from None
    elif path.endswith((".tif", ".tiff")):
        try:
            with tifffile.TiffFile(path) as tif:
                info = (tif.imagej_metadata or {}).get("Info")
                if info is None:
                    raise DiffcamError(f"{path} has no diffcam metadata (ImageJ Info); was it "
                                       f"written by diffcam.model.stack?")
                meta = _meta_from(path, info)
                series = tif.series[0]
                check_read_size(path, "the TIFF", series.shape, series.dtype)
                stack = series.asarray()
        except DiffcamError:
            raise
        except Exception as e:  # tifffile raises many kinds on damaged files
            raise DiffcamError(f"{path}: not {what} ({type(e).__name__}: {e}).") from None
    else:
        raise DiffcamError(f"load_stack reads .npz, .npy or .tif files, got {path!r}.")
    nz = meta.depths.size
    shape = (nz,) + (() if meta.offsets is None else (len(meta.offsets),))
    if stack.ndim < 2 or stack.size != int(np.prod(shape)) * int(np.prod(stack.shape[-2:])):
        raise DiffcamError(f"{path}: {stack.shape} pixels do not match its metadata "
                           f"({nz} depths{'' if meta.offsets is None else f', {len(meta.offsets)} offsets'}).")
    stack = stack.reshape(shape + stack.shape[-2:])
    if not path.endswith(".npy") and not np.all(np.isfinite(stack)):
        raise DiffcamError(f"{path}: the stack holds NaN/Inf values; the file is damaged.")
    return stack, meta


def _meta_from(path, text) -> StackMeta:
    try:
        return StackMeta.from_json(text)
    except DiffcamError as e:
        raise DiffcamError(f"{path}: {e}") from None
    except (ValueError, TypeError, KeyError, AttributeError) as e:
        raise DiffcamError(f"{path}: damaged stack metadata ({type(e).__name__}: {e}).") \
            from None

