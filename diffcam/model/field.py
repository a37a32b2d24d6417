"""The camera across its field: a low-rank model of a field-dependent PSF (Yanny et al.,
"Miniscope3D", Light Sci. Appl. 9, 171, 2020).

A diffuser camera's PSF changes with the source's lateral position: the aperture's
shadow moves, the sensor accepts some angles less than others, the edges vignette.
Sampled at ``P`` field positions, the PSFs ``h_p`` are first *registered*: each is moved
so that its chief ray (where the PSF of that source is centred on the sensor) lies on the
optical axis. What is left is the PSF's change of *shape*, which varies slowly and is
well described by a few terms. The singular value decomposition of the registered stack
``H[p, :] = h_p(r + c_p)`` (``P × my·mx``),

    H = U S Vᵀ,    h_p(r + c_p) ≈ Σ_{k<K} α_{p,k} g_k(r),

gives ``K`` kernels ``g_k`` (rows of ``S Vᵀ``) and their weights ``α_{p,k}`` (columns of
``U``) at the field positions. Interpolating the weights over the field (a thin-plate
spline through the positions ``c_p``) gives ``w_k(y, x)``, and the sensor image of a scene
``x`` is

    b = crop( Σ_k g_k ∗ (w_k · x) ),

a sum of ``K`` shift-invariant convolutions of the scene weighted across the field
(`diffcam.reconstruct.operators.field_model` builds the operator). In 3-D every
depth has its own kernels and weights, and the sensor sums over depths. ``K`` is the
smallest rank whose relative model error ``||H - H_K||_F / ||H||_F`` (the discarded
singular values) is within a stated tolerance.

Coordinates: positions are in sensor pixels relative to the optical axis (index
``n//2``, `diffcam.core.grid`), ``(y, x)``; the object grid of a reconstruction is
on the same pixels, so the weight ``w_k`` at object pixel ``c_p`` is ``α_{p,k}``.
A source at ``(y1, x1, z1)`` has its chief ray at ``−(y1, x1)·z2/z1`` on the sensor
(`chief_rays`).
"""

from __future__ import annotations

import json
import os
from functools import partial
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jaxtyping import ArrayLike, Float

from diffcam.core.backend import irfft2, rfft2
from diffcam.core.errors import DiffcamError, ShapeError, check_field, is_concrete
from diffcam.io import atomic_output, check_output_path, read_npz

__all__ = ["FieldPSF", "field_psf", "chief_rays", "register", "thin_plate_weights",
           "save_field_psf", "load_field_psf", "FORMAT"]

FORMAT = "diffcam-field-psf"
FORMAT_VERSION = 2
"""Version 2 adds colour files (one model per channel, ``channels`` in the metadata);
version 1 files hold one model and are read as before."""
_DEGENERATE = 1e-6   # a direction of the positions' spread below this (relative) is flat


def chief_rays(offsets: ArrayLike, z1: ArrayLike, z2: float, pitch: float
               ) -> Float[Array, "*depth npos 2"]:
    """Where the PSF of each source is centred on the sensor: ``−(y1, x1)·z2/z1 / pitch``.

    Args:
        offsets: ``(npos, 2)`` source positions ``(y1, x1)``, metres.
        z1: source distance, metres: a scalar, or ``(nz,)`` for one set per depth.
        z2: diffuser-to-sensor distance, metres.
        pitch: sensor pixel pitch, metres.

    Returns:
        ``([nz,] npos, 2)`` chief-ray positions ``(y, x)``, sensor pixels from the axis.
    """
    offsets = jnp.asarray(offsets)
    z1 = jnp.asarray(z1, offsets.dtype)
    return -offsets * (z2 / pitch) / z1[..., None, None]


def register(psfs: Float[Array, "*depth npos my mx"],
             positions: Float[Array, "*depth npos 2"]) -> Float[Array, "*depth npos my mx"]:
    """Move each PSF so that its chief ray ``positions[p]`` (pixels, ``(y, x)``) lands on
    the optical axis: ``h_p(r) → h_p(r + c_p)``, a sub-pixel Fourier shift.

    The shift is circular on the PSF grid: give PSFs whose support, moved back to the
    axis, stays inside it (what leaves one side comes in at the other)."""
    my, mx = psfs.shape[-2:]
    ky = jnp.fft.fftfreq(my)[:, None]
    kx = jnp.fft.rfftfreq(mx)[None, :]
    cy, cx = positions[..., 0, None, None], positions[..., 1, None, None]
    ramp = jnp.exp(2j * jnp.pi * (ky * cy + kx * cx)).astype(
        jnp.result_type(psfs.dtype, jnp.complex64))
    return irfft2(rfft2(psfs) * ramp, s=(my, mx))


class FieldPSF(eqx.Module):
    """A field-dependent PSF as ``K`` kernels with weights at the field positions.

    Build it with `field_psf`; turn it into a forward model with
    `diffcam.reconstruct.operators.field_model`.

    Attributes:
        kernels: ``(K, [nz,] my, mx)`` the registered kernels ``g_k`` (optical axis at
            ``(my//2, mx//2)``, the PSFs' units); ``g_0`` is the mean registered PSF
            of a field whose shape does not change.
        coefficients: ``(K, [nz,] npos)`` the weights ``α_{p,k}`` at the positions
            (each kernel's weights have unit rms over the positions, ``α_0 ≥ 0`` on
            average).
        positions: ``([nz,] npos, 2)`` chief rays ``c_p``, sensor pixels ``(y, x)``
            from the axis.
        singular_values: ``([nz,] min(npos, my·mx))`` of the registered stack, largest
            first (all of them, also those the rank discarded).
    """

    kernels: Float[Array, "k *depth my mx"]
    coefficients: Float[Array, "k *depth npos"]
    positions: Float[Array, "*depth npos 2"]
    singular_values: Float[Array, "*depth s"]

    @property
    def rank(self) -> int:
        """``K``, the number of kernels."""
        return self.kernels.shape[0]

    @property
    def volume(self) -> bool:
        """True if the model has a depth axis."""
        return self.kernels.ndim == 4

    def error(self, rank: int | None = None) -> Array:
        """Relative model error of the registered stack at ``rank`` (default: the
        model's): ``sqrt(Σ_{k≥K} σ_k² / Σ σ_k²)``, the largest over depths."""
        return _rank_errors(self.singular_values)[..., self.rank if rank is None else rank].max()

    def weights(self, object_shape: Sequence[int]) -> Float[Array, "k *depth oy ox"]:
        """The weights ``w_k`` on an object grid ``(oy, ox)`` centred on the axis:
        the thin-plate spline through the coefficients at the positions."""
        return _weights_on_grid(self.positions, self.coefficients,
                                tuple(int(n) for n in object_shape[-2:]))

    def at(self, positions: Float[Array, "*depth m 2"]) -> Float[Array, "*depth m my mx"]:
        """The registered PSFs ``Σ_k w_k(c) g_k`` at field positions ``c`` (pixels):
        the weights interpolate between the model's positions and extrapolate, unchecked,
        outside their span."""
        w = _thin_plate(self.positions, self.coefficients, positions)   # (K, [nz,] m)
        return jnp.einsum("k...m,k...yx->...myx", w, self.kernels)


def _rank_errors(s):
    """``e[K] = sqrt(Σ_{k≥K} σ_k² / Σ σ_k²)`` for ``K = 0 … len(s)`` along the last
    axis (``e[0] = 1``, the last is 0)."""
    energy = s ** 2
    tail = jnp.cumsum(energy[..., ::-1], axis=-1)[..., ::-1]
    tail = jnp.concatenate([tail, jnp.zeros_like(tail[..., :1])], axis=-1)
    total = jnp.maximum(tail[..., :1], jnp.finfo(energy.dtype).tiny)
    return jnp.sqrt(tail / total)


def field_psf(psfs: ArrayLike, positions: ArrayLike, *, tolerance: float = 1e-2,
              rank: int | None = None) -> FieldPSF:
    """The low-rank field-dependent PSF of PSFs sampled across the field.

    Args:
        psfs: ``([nz,] npos, my, mx)`` PSFs of sources at ``npos`` field positions (one
            set per depth), on one common scale, optical axis at ``(my//2, mx//2)``.
        positions: ``([nz,] npos, 2)`` or ``(npos, 2)`` (shared by every depth) chief
            rays of the PSFs, sensor pixels ``(y, x)`` from the axis (see
            `chief_rays`).
        tolerance: the relative model error ``||H - H_K||_F / ||H||_F`` of the
            registered stack that the rank must reach (at every depth).
        rank: ``K`` itself (static; then ``tolerance`` is not used and the function is
            jit-compatible and differentiable in ``psfs`` and ``positions``).

    Returns:
        `FieldPSF`; its `FieldPSF.error` is the model error of the rank
        chosen.
    """
    check_field(psfs, "psfs")
    shape = np.shape(psfs)
    if len(shape) not in (3, 4):
        raise ShapeError(f"psfs must be (npos, my, mx) or (nz, npos, my, mx), got shape "
                         f"{shape}.")
    psfs = jnp.asarray(psfs)
    npos = shape[-3]
    positions = jnp.broadcast_to(jnp.asarray(positions, psfs.dtype), shape[:-2] + (2,)) \
        if np.shape(positions)[-2:] == (npos, 2) else None
    if positions is None:
        raise ShapeError(f"positions must be ({npos}, 2) or {shape[:-2] + (2,)} chief rays "
                         f"(y, x) in pixels, one per PSF; got shape {np.shape(positions)}.")
    if rank is None:
        if not 0 < tolerance < 1:
            raise DiffcamError(f"tolerance is a relative model error in (0, 1), e.g. 1e-2; "
                               f"got {tolerance!r}.")
    elif not (isinstance(rank, (int, np.integer)) and 1 <= rank <= npos):
        raise DiffcamError(f"rank must be an int from 1 to the number of positions "
                           f"({npos}), got {rank!r}.")
    u, s, vt = _registered_svd(psfs, positions)
    if rank is None:
        if not is_concrete(s):
            raise DiffcamError("field_psf chooses the rank from concrete PSFs; under jit "
                               "give rank= (an int).")
        within = np.asarray(_rank_errors(s)).max(axis=tuple(range(s.ndim - 1))) <= tolerance
        rank = int(np.argmax(within))
    return _truncated(u, s, vt, positions, rank=rank, shape=shape)


@jax.jit
def _registered_svd(psfs, positions):
    """The SVD ``U S Vᵀ`` of the registered stack ``([nz,] npos, my·mx)``."""
    registered = register(psfs, positions)
    return jnp.linalg.svd(registered.reshape(registered.shape[:-2] + (-1,)),
                          full_matrices=False)


@partial(jax.jit, static_argnames=("rank", "shape"))
def _truncated(u, s, vt, positions, *, rank, shape):
    """The `FieldPSF` of the first ``rank`` singular triplets."""
    singular_values = s
    u, s, vt = u[..., :rank], s[..., :rank], vt[..., :rank, :]
    # each kernel's weights: unit rms over the positions, non-negative on average
    scale = jnp.sqrt(jnp.mean(u ** 2, axis=-2)) * jnp.where(jnp.mean(u, axis=-2) < 0, -1, 1)
    coefficients = jnp.moveaxis(u / scale[..., None, :], -1, 0)
    kernels = jnp.moveaxis((s * scale)[..., None] * vt, -2, 0)
    return FieldPSF(kernels=kernels.reshape((rank,) + shape[:-3] + shape[-2:]),
                    coefficients=coefficients, positions=positions,
                    singular_values=singular_values)


def _polynomial(positions, points):
    """The thin-plate spline's affine part at ``points``: ``[1, d₁·p, d₂·p]`` with
    ``d`` the principal directions of the positions' spread, a direction dropped
    (zeroed) where the positions do not spread along it (one point, or a line)."""
    centre = positions.mean(axis=-2, keepdims=True)
    # the spline does not depend on the directions where both are kept (the affine
    # span is the same), so they carry no gradient
    _, spread, directions = jnp.linalg.svd(lax.stop_gradient(positions - centre),
                                           full_matrices=True)
    spread = jnp.concatenate([spread, jnp.zeros_like(positions[..., 0, :])], -1)[..., :2]
    keep = spread > _DEGENERATE * jnp.maximum(spread[..., :1], 1.0)
    coords = jnp.einsum("...mi,...ji->...mj", points - centre, directions) * keep[..., None, :]
    return jnp.concatenate([jnp.ones_like(coords[..., :1]), coords], axis=-1)


def _tps_kernel(r2):
    """``φ(r) = r² log r``, written in ``r²`` (0 at ``r = 0``)."""
    return 0.5 * r2 * jnp.log(jnp.where(r2 > 0, r2, 1.0))


def _squared_distances(a, b):
    return jnp.sum((a[..., :, None, :] - b[..., None, :, :]) ** 2, axis=-1)


def _thin_plate_fit(positions, values):
    """Coefficients ``(a, c)`` of the thin-plate spline ``f(p) = Σ_j a_j φ(|p - c_j|) +
    c·[1, p]`` through ``values (..., npos)`` at ``positions (..., npos, 2)`` (lengths
    in units of the positions' extent, for conditioning)."""
    npos = positions.shape[-2]
    poly = _polynomial(positions, positions)
    system = jnp.concatenate([
        jnp.concatenate([_tps_kernel(_squared_distances(positions, positions)), poly], -1),
        jnp.concatenate([jnp.swapaxes(poly, -1, -2), jnp.zeros(poly.shape[:-2] + (3, 3),
                                                               poly.dtype)], -1)], -2)
    rhs = jnp.concatenate([values, jnp.zeros(values.shape[:-1] + (3,), values.dtype)], -1)
    solution = jnp.einsum("...ij,k...j->k...i", jnp.linalg.pinv(system), rhs)
    return solution[..., :npos], solution[..., npos:]


def _thin_plate(positions, values, points):
    """The spline through ``values (K, ..., npos)`` at ``positions`` evaluated at
    ``points (..., m, 2)``: ``(K, ..., m)``."""
    return _thin_plate_spline(positions, values)(points)


def _thin_plate_spline(positions, values):
    """The spline through ``values (K, ..., npos)`` at ``positions``, fitted once: a
    function of ``points (..., m, 2)`` returning ``(K, ..., m)``. Lengths are taken in
    units of the positions' extent (conditioning)."""
    extent = jnp.maximum(jnp.max(jnp.abs(positions - positions.mean(axis=-2, keepdims=True))),
                         1.0)
    positions = positions / extent
    a, c = _thin_plate_fit(positions, values)

    def evaluate(points):
        points = points / extent
        phi = _tps_kernel(_squared_distances(points, positions))
        return (jnp.einsum("...mj,k...j->k...m", phi, a)
                + jnp.einsum("...mi,k...i->k...m", _polynomial(positions, points), c))
    return evaluate


@partial(jax.jit, static_argnames=("object_shape",))
def _weights_on_grid(positions, values, object_shape):
    return thin_plate_weights(positions, values, object_shape)


def thin_plate_weights(positions: Float[Array, "*depth npos 2"],
                       values: Float[Array, "k *depth npos"],
                       object_shape: Sequence[int]) -> Float[Array, "k *depth oy ox"]:
    """The thin-plate spline through ``values`` at ``positions`` (pixels ``(y, x)`` from
    the axis) on every pixel of an object grid ``(oy, ox)`` centred on the axis
    (`diffcam.core.grid`); one row of the grid at a time, so memory is
    ``ox × npos`` per row. Beyond the positions it continues as a plane."""
    oy, ox = (int(n) for n in object_shape[-2:])
    x = jnp.arange(ox, dtype=positions.dtype) - ox // 2
    lead = positions.shape[:-2]
    spline = _thin_plate_spline(positions, values)

    def row(y):
        points = jnp.stack([jnp.full_like(x, y), x], axis=-1)
        return spline(jnp.broadcast_to(points, lead + points.shape))
    rows = lax.map(row, jnp.arange(oy, dtype=positions.dtype) - oy // 2)   # (oy, K, ..., ox)
    return jnp.moveaxis(rows, 0, -2)


# ---------------------------------------------------------------------------- files

_ARRAYS = ("kernels", "coefficients", "positions", "singular_values")


def save_field_psf(path: str | os.PathLike, model: FieldPSF | Sequence[FieldPSF], /, *,
                   channels: str | None = None, **metadata) -> None:
    """Write a `FieldPSF`, or one per colour channel, to ``.npz`` (exact round trip),
    with ``metadata`` (JSON-serialisable keywords: the camera, the tolerance, …) beside
    it. The file is written atomically (`diffcam.io.atomic_output`).

    Args:
        path: the ``.npz`` file.
        model: a `FieldPSF`, or with ``channels`` one per channel, all of one shape
            (stored on a leading channel axis).
        channels: the channels' order, one letter each (e.g. ``"RGB"``), for a colour
            model; ``None`` for one model.
        metadata: recorded beside the arrays (``load_field_psf`` returns it); the file's
            ``rank`` and ``error`` (the largest over the channels) are added.
    """
    path = os.fspath(path)
    check_output_path(path, suffixes=(".npz",))
    models = _channel_models(model, channels)
    first = models[0]
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "rank": first.rank,
            "volume": first.volume, "error": max(float(m.error()) for m in models),
            "channels": channels, **metadata}
    try:
        text = json.dumps(meta)
    except TypeError as e:
        raise DiffcamError(f"metadata must be JSON-serialisable ({e}).") from None
    arrays = {name: np.stack([np.asarray(getattr(m, name)) for m in models])
              if channels else np.asarray(getattr(first, name)) for name in _ARRAYS}
    with atomic_output(path) as temp, open(temp, "wb") as fh:
        np.savez(fh, **arrays, meta=np.array(text))


def _channel_models(model, channels) -> tuple[FieldPSF, ...]:
    """``model`` as a tuple of `FieldPSF`, one per channel of ``channels`` (one model
    for ``None``), checked to share their shapes."""
    if channels is None:
        if not isinstance(model, FieldPSF):
            raise DiffcamError("save_field_psf: give one FieldPSF, or one per channel with "
                               "channels= (e.g. 'RGB').")
        return (model,)
    models = (model,) if isinstance(model, FieldPSF) else tuple(model)
    if (not isinstance(channels, str) or len(channels) != len(models) or not channels
            or not all(isinstance(m, FieldPSF) for m in models)):
        raise DiffcamError(f"save_field_psf: channels names one channel per FieldPSF "
                           f"(e.g. 'RGB' for three); got {channels!r} for "
                           f"{len(models)} model(s).")
    shapes = {tuple(np.shape(getattr(m, name)) for name in _ARRAYS) for m in models}
    if len(shapes) != 1:
        raise ShapeError("save_field_psf: the channels' models differ in shape; give one "
                         "rank, grid and kernel size for every channel.")
    return models


def load_field_psf(path: str | os.PathLike) -> tuple[FieldPSF | tuple[FieldPSF, ...], dict]:
    """Read a file written by `save_field_psf`: ``(model, metadata)``, the model a
    `FieldPSF`, or for a colour file a tuple of them in the order of
    ``metadata["channels"]``. Version 1 files (one model) are read too.

    Raises:
        DiffcamError: one line naming the file and what is wrong with it."""
    path = os.fspath(path)
    arrays = read_npz(path, _ARRAYS + ("meta",), what="a diffcam field-dependent PSF")
    try:
        meta = json.loads(str(arrays["meta"]))
        assert isinstance(meta, dict)
    except (ValueError, AssertionError):
        raise DiffcamError(f"{path}: damaged metadata (not a JSON object); write the file "
                           f"with diffcam.model.field.save_field_psf.") from None
    if meta.get("format") != FORMAT or meta.get("version", 0) > FORMAT_VERSION:
        raise DiffcamError(f"{path}: not a {FORMAT} file of version <= {FORMAT_VERSION} "
                           f"(format {meta.get('format')!r}, version {meta.get('version')!r}).")
    channels = meta.get("channels")
    if channels is None:
        return _checked_model(path, {k: arrays[k] for k in _ARRAYS}, meta), meta
    if not isinstance(channels, str) or any(len(arrays[k]) != len(channels) for k in _ARRAYS):
        raise DiffcamError(f"{path}: its channels {channels!r} do not match its arrays "
                           f"(kernels {arrays['kernels'].shape}); the file is damaged.")
    return tuple(_checked_model(path, {k: arrays[k][c] for k in _ARRAYS}, meta)
                 for c in range(len(channels))), meta


def _checked_model(path, arrays: dict, meta: dict) -> FieldPSF:
    """The `FieldPSF` of one model's arrays from ``path``, checked to fit together and
    be finite."""
    k, c, p = arrays["kernels"], arrays["coefficients"], arrays["positions"]
    depth = k.shape[1:-2] if k.ndim in (3, 4) else None
    if (depth is None or c.shape[:-1] != (k.shape[0],) + depth
            or p.shape != depth + (c.shape[-1], 2) or meta.get("rank") != k.shape[0]):
        raise DiffcamError(f"{path}: its arrays do not fit together (kernels {k.shape}, "
                           f"coefficients {c.shape}, positions {p.shape}); the file is "
                           f"damaged.")
    for name in _ARRAYS:
        if not np.all(np.isfinite(arrays[name])):
            raise DiffcamError(f"{path}: {name} holds NaN/Inf; the file is damaged.")
    return FieldPSF(kernels=jnp.asarray(k), coefficients=jnp.asarray(c),
                    positions=jnp.asarray(p),
                    singular_values=jnp.asarray(arrays["singular_values"]))
