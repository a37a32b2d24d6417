"""Cubic B-spline sampling along one axis, with a transpose at the cost of the forward.

``spline_sample(f, t, axis)`` evaluates the cubic B-spline whose coefficients are ``f``
along ``axis`` (−2 or −1) at the fractional indices ``t`` (coefficients beyond the grid
are zero): four gathers of near-consecutive rows or columns. Its derivative with respect
to ``f`` is the same sampling; in reverse mode JAX transposes it, and the transpose of a
gather is a scatter-add, which XLA's CPU backend runs serially (the scaling-theorem
PSF's reverse pass at 1024²: 42 ms of sampling transposes against 3.8 ms of sampling).

Here the sampling is a linear JAX primitive whose transpose is written out: the
outputs are taken in blocks of 32; a block's sample points span at most
``31·max_step + 5`` consecutive grid rows when the points increase by at most
``max_step`` samples each, so the block's contribution is one small dense product (its
32 × R spline weights, transposed, times the block's cotangent rows) added into those
rows in place. No scatter. Points that decrease, or steps beyond ``max_step``, would
fall outside a block's window: the transpose then returns NaN rather than a wrong
gradient (``jax_debug_nans`` points at it). Forward mode applies the primitive to the
tangent; the derivative with respect to ``t`` samples with the weights' derivative
(orders up to 3; the cubic's 4th derivative is 0), so geometry gradients and higher
orders work.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

__all__ = ["spline_sample", "cubic_sample", "bspline_weights"]

_BLOCK = 32
_LOOP = 4      # loop iterations of the forward (see _in_blocks)
# 6 × the cubic B-spline's four weights at offset u ∈ [0, 1), taps −1, 0, 1, 2, as
# polynomial coefficients of 1, u, u², u³
_COEFFS = np.array([[1, -3, 3, -1], [4, 0, -6, 3], [1, 3, 3, -3], [0, 0, 0, 1]], float) / 6


def bspline_weights(frac, order: int = 0):
    """The ``order``-th derivative (in ``frac``) of the cubic B-spline weights of taps
    −1, 0, 1, 2 at offset ``frac`` ∈ [0, 1): shape ``frac.shape + (4,)``."""
    c = _COEFFS
    for _ in range(order):
        c = c[:, 1:] * np.arange(1, c.shape[1])
    if c.shape[1] == 0:
        return jnp.zeros(frac.shape + (4,), frac.dtype)
    out = 0
    for p in reversed(range(c.shape[1])):          # Horner, one polynomial per tap
        out = out * frac[..., None] + jnp.asarray(c[:, p], frac.dtype)
    return out


def _taps(t, n, order, dtype):
    """First tap index, and the weights (zero for taps off the grid): (m,), (m, 4)."""
    i0 = jnp.floor(t)
    w = bspline_weights(t - i0, order)
    i0 = i0.astype(jnp.int32)
    idx = i0[:, None] - 1 + jnp.arange(4)
    return i0, jnp.where((idx >= 0) & (idx < n), w, 0.0).astype(dtype)


def cubic_sample(f, t, axis: int, order: int = 0):
    """The sampling itself, as plain JAX (JAX's own derivatives: its transpose is a
    scatter-add): four gathers along ``axis``, cache-friendly either way; ``order`` > 0
    samples the spline's derivative in ``t``."""
    n = f.shape[axis]
    i0, w = _taps(t, n, order, f.real.dtype)
    out = 0
    for k in range(4):
        wk = w[:, k, None] if axis == -2 else w[:, k]
        out = out + jnp.take(f, jnp.clip(i0 - 1 + k, 0, n - 1), axis=axis, mode="clip") * wk
    return out


def _real_matmul(m, x, axis):
    """``m`` (r × i, real) applied along ``axis`` (−2 or −1) of ``x``, real or complex:
    (..., i, nx) → (..., r, nx), or (..., ny, i) → (..., ny, r)."""
    if jnp.iscomplexobj(x):
        return lax.complex(_real_matmul(m, x.real, axis), _real_matmul(m, x.imag, axis))
    return jnp.einsum("ri,...ix->...rx" if axis == -2 else "ri,...xi->...xr", m, x)


def _transpose_blocks(ct, t, n, order, max_step, axis):
    """Σ over outputs of weight × cotangent row (column), into the ``n`` grid rows
    (columns) along ``axis`` (see module): in place along either axis, so the
    columns' transpose needs no transposed copies of the field."""
    m = t.shape[0]
    nb = -(-m // _BLOCK)
    r = int(math.ceil((_BLOCK - 1) * max_step)) + 5        # grid rows a block can touch
    t = jnp.pad(t, (0, nb * _BLOCK - m), mode="edge")
    pad = [(0, 0)] * ct.ndim
    pad[axis] = (0, nb * _BLOCK - m)
    ct = jnp.pad(ct, pad)
    i0, w = _taps(t, n, order, ct.real.dtype)
    first, last = i0[::_BLOCK], i0[_BLOCK - 1::_BLOCK]
    fits = jnp.all(jnp.diff(i0) >= 0) & jnp.all(last - first + 4 <= r)
    w = w * jnp.where(fits, 1.0, jnp.nan).astype(w.dtype)    # NaN weights: NaN gradient
    # the accumulator is the grid itself: a window that would cross an edge is moved
    # inside, which only drops taps off the grid, whose weights are zero. Grids smaller
    # than a window get a margin of r rows on each side instead.
    off = 0 if n >= r else r
    size = n + 2 * off
    shape = list(ct.shape)
    shape[axis] = size
    acc = jnp.zeros(shape, ct.dtype)

    def block(b, acc):
        s = b * _BLOCK
        i0b = lax.dynamic_slice_in_dim(i0, s, _BLOCK)
        wb = lax.dynamic_slice_in_dim(w, s, _BLOCK)
        start = jnp.clip(i0b[0] - 1 + off, 0, size - r)     # window's first row in acc
        rows = i0b[:, None] - 1 + jnp.arange(4) + off - start   # (block, 4); off-window: 0
        weights = jnp.einsum("ik,ikr->ri", wb, jax.nn.one_hot(rows, r, dtype=wb.dtype))
        add = _real_matmul(weights, lax.dynamic_slice_in_dim(ct, s, _BLOCK, axis=axis), axis)
        cur = lax.dynamic_slice_in_dim(acc, start, r, axis=axis)
        return lax.dynamic_update_slice_in_dim(acc, cur + add, start, axis=axis)

    acc = lax.fori_loop(0, nb, block, acc)
    return acc if off == 0 else lax.slice_in_dim(acc, off, off + n, axis=axis)


def _transpose(ct, f, t, *, axis, order, max_step):
    if type(ct) is ad.Zero:
        return ad.Zero(f.aval), None
    return _transpose_blocks(ct, t, f.aval.shape[axis], order, max_step, axis), None


def _shape(f, t, *, axis, order, max_step):
    shape = list(f.shape)
    shape[axis] = t.shape[0]
    return jax.core.ShapedArray(tuple(shape), f.dtype)


sample_p = Primitive("diffcam_spline_sample")
sample_p.def_abstract_eval(_shape)
sample_p.def_impl(lambda f, t, **k: jax.jit(partial(sample_p.bind, **k))(f, t))


def _in_blocks(f, t, *, axis, order, max_step):
    """:func:`cubic_sample` computed in ``_LOOP`` blocks of output rows inside a loop, so
    that its result is one buffer: XLA cannot fuse a loop's body into the loop's
    consumers. Fused, XLA copied the 16 gathers of a 2-D sampling into every consumer
    (the real and the imaginary part of |s|² each): the scaling-theorem PSF at 1024²
    took 80–117 ms instead of 25–35 ms, depending on which inputs were constants."""
    del max_step
    rows = f.shape[-2] if axis == -1 else t.shape[0]
    nb = min(_LOOP, rows)
    bs = -(-rows // nb)
    if axis == -2:
        tb = jnp.pad(t, (0, nb * bs - rows), mode="edge").reshape(nb, bs)
        out = lax.map(lambda tb: cubic_sample(f, tb, -2, order), tb)
    else:
        fb = jnp.pad(f, [(0, 0)] * (f.ndim - 2) + [(0, nb * bs - rows), (0, 0)])
        fb = jnp.moveaxis(fb.reshape(f.shape[:-2] + (nb, bs, f.shape[-1])), -3, 0)
        out = lax.map(lambda fb: cubic_sample(fb, t, -1, order), fb)
    out = jnp.moveaxis(out, 0, -3)
    return out.reshape(out.shape[:-3] + (nb * bs, out.shape[-1]))[..., :rows, :]


mlir.register_lowering(sample_p, mlir.lower_fun(_in_blocks, multiple_results=False))


def _jvp_t(dt, f, t, *, axis, order, max_step):
    slope = sample_p.bind(f, t, axis=axis, order=order + 1, max_step=max_step)
    return slope * (dt[:, None] if axis == -2 else dt).astype(slope.dtype)


ad.defjvp(sample_p, lambda df, f, t, **k: sample_p.bind(df, t, **k), _jvp_t)
ad.primitive_transposes[sample_p] = _transpose


def _batch(args, dims, **k):
    f, t = args
    bf, bt = dims
    if bt is None:
        return sample_p.bind(jnp.moveaxis(f, bf, 0), t, **k), 0
    t = jnp.moveaxis(t, bt, 0)
    if bf is None:
        return lax.map(lambda ti: sample_p.bind(f, ti, **k), t), 0
    return lax.map(lambda a: sample_p.bind(a[0], a[1], **k), (jnp.moveaxis(f, bf, 0), t)), 0


batching.primitive_batchers[sample_p] = _batch


def spline_sample(f, t, axis: int, *, max_step: float = 1.0):
    """The cubic spline with coefficients ``f`` along ``axis`` (−2 or −1), at the
    fractional indices ``t`` (m,), increasing by at most ``max_step`` samples per point
    (a magnification ≥ 1/max_step): shape of ``f`` with ``axis`` of length m. The
    gradient with respect to ``f`` is NaN where ``t`` breaks that promise."""
    if axis not in (-2, -1):
        raise ValueError(f"axis must be -2 or -1, got {axis}")
    f = jnp.asarray(f)
    t = jnp.asarray(t, f.real.dtype)
    return sample_p.bind(f, t, axis=axis, order=0, max_step=float(max_step))
