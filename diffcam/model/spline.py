"""Cubic B-spline sampling along one axis, with a transpose at the cost of the forward.

``spline_sample(f, t, axis)`` evaluates the cubic B-spline whose coefficients are ``f``
along ``axis`` (−2 or −1) at the fractional indices ``t`` (coefficients beyond the grid
are zero): four gathers of near-consecutive rows or columns. Its derivative with respect
to ``f`` is the same sampling; in reverse mode JAX transposes it, and the transpose of a
gather is a scatter-add, which XLA's CPU backend runs serially (the scaling-theorem
PSF's reverse pass at 1024²: 42 ms of sampling transposes against 3.8 ms of sampling).

Here the sampling is a linear JAX primitive whose transpose is a primitive too, written
as gathers: grid row ``j`` receives ``Σᵢ β₃(tᵢ − j)·ctᵢ`` over the points within two
samples of it, ``a_j ≤ i < b_j`` (found by ``searchsorted``, as the points do not
decrease), so the transpose gathers rows (columns) of the cotangent as the sampling
gathers rows (columns) of the grid: five gathers where the points step by less than one
sample but more than 0.8, more passes of five for denser points. Decreasing points
would break the search: the transpose then returns NaN rather than a wrong gradient
(``jax_debug_nans`` points at it). Forward mode applies a primitive to the tangent;
the derivative with respect to ``t`` samples (spreads) with the weights' derivative
(orders up to 3; the cubic's 4th derivative is 0), so geometry gradients and higher
orders work.

Memory: along −2 whole rows are gathered in one fused operation, along −1 blocks of
rows in a loop (`_by_row_blocks`), which overwrite their own rows when the length
is kept. A 2-D sampling of a field the caller no longer needs (the scaling-theorem PSF,
and its transpose) then needs one N² buffer, not three: the scaling PSF's temporaries
at 1024² went from 32 to 16 MB, its gradient's from 48 to 24 MB, both bit for bit the
same.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

__all__ = ["spline_sample", "cubic_sample", "bspline"]

_LOOP = 4      # row blocks of the sampling along −1 and of its transpose (_by_row_blocks)
_PASS = 5      # gathers per pass of the transpose: one pass for points 0.8–1 sample apart
# the cubic B-spline β₃(x) = p(|x|), as polynomial coefficients of 1, a, a², a³:
# p = 2/3 − a² + a³/2 on [0, 1) and (2 − a)³/6 on [1, 2)
_COMPARE_ALL = 2 ** 18   # searches of up to this many (sorted × queries) pairs compare all


def _search(sorted_values, queries, side):
    """``jnp.searchsorted``: on small grids by comparing every pair, one fused operation
    (an eager 128² PSF: 30 µs less than the binary search's while loop, which a PSF
    jitted with a constant camera folds away); on large ones by binary search."""
    small = sorted_values.size * queries.size <= _COMPARE_ALL
    return jnp.searchsorted(sorted_values, queries, side=side,
                            method="compare_all" if small else "scan")


_INNER = np.array([2 / 3, 0, -1, 1 / 2])
_OUTER = np.array([4 / 3, -2, 1, -1 / 6])


def bspline(x, order: int = 0):
    """The cubic B-spline β₃ (its ``order``-th derivative) at ``x``; zero for |x| ≥ 2.
    A NumPy array in gives a NumPy array out (host-side resampling), anything else JAX.

    The piece is chosen by |x|, and β₃ is continuous with two derivatives: two roundings
    of one ``x`` give two nearby values (see `_taps`)."""
    xp = np if isinstance(x, np.ndarray) else jnp
    a = xp.abs(x)

    def piece(c):
        for _ in range(order):
            c = c[1:] * np.arange(1, c.size)
        out = xp.zeros_like(a)
        for coef in reversed(c):       # Horner
            out = out * a + coef
        return out
    value = xp.where(a < 1, piece(_INNER), xp.where(a < 2, piece(_OUTER), 0))
    return value * xp.sign(x) if order % 2 else value


def _taps(t, n, order, dtype):
    """The four grid indices each point gathers, clipped to the grid, and their weights
    β₃(t − index) (zero for taps off the grid): (m, 4) each.

    The first tap is floor(t) − 1, floor(t) found by a search of the grid: one integer
    array for the gathers and the weights. Written as ``jnp.floor``, XLA may compute t
    once per consumer, and two roundings of a t at an integer put the weights on the
    wrong taps (a user's jit with constant geometry did: PSFs off by 5%); a weight
    computed from another rounding of t differs only in its last bits (`bspline`
    is continuous). Beyond the grid the search stops at −1 or n − 1, whose taps still
    cover every grid sample within reach."""
    i0 = _search(jnp.arange(n, dtype=t.dtype), t, "right").astype(jnp.int32)
    idx = (i0 - 2)[:, None] + jnp.arange(4)
    w = jnp.where((idx >= 0) & (idx < n), bspline(t[:, None] - idx, order), 0.0)
    return jnp.clip(idx, 0, n - 1), w.astype(dtype)


def cubic_sample(f, t, axis: int, order: int = 0):
    """The sampling itself, as plain JAX (JAX's own derivatives: its transpose is a
    scatter-add): four gathers along ``axis``, cache-friendly either way; ``order`` > 0
    samples the spline's derivative in ``t``."""
    return _gathered(f, *_taps(t, f.shape[axis], order, f.real.dtype), axis)


def _gathered(x, index, weight, axis):
    """Σ_q x[index[:, q]]·weight[:, q], gathering along ``axis``: (k, q) → k outputs."""
    out = 0
    for q in range(index.shape[1]):
        w = weight[:, q, None] if axis == -2 else weight[:, q]
        out = out + jnp.take(x, index[:, q], axis=axis, mode="clip") * w
    return out


def _by_row_blocks(term, x, length, terms=1):
    """Σ_p ``term(rows, p)`` over ``p < terms`` (a static 1 or traced), ``term`` taking
    rows of ``x`` (…, k, nx) to rows (…, k, ``length``), on ``_LOOP`` blocks of rows
    inside a loop. A loop's result is one buffer: XLA cannot fuse a loop's body into its
    consumers, and fused, it copied the 16 gathers of a 2-D sampling into every consumer
    (the real and the imaginary part of |s|² each: the scaling-theorem PSF at 1024² took
    80–117 ms instead of 25–35 ms).

    When the rows keep their length, each block overwrites itself in ``x``'s buffer,
    which XLA reuses when ``x`` is not needed after: no second N² buffer, and none to
    fill with zeros first (a loop's output is one: at 2048² the sampling took 24 ms
    instead of 40). The first term is written in place, the others added to it; a loop
    over the terms that carried the block's sum cost a transposed copy of it (at 4096²
    the transpose took 136 ms instead of 87). Otherwise the blocks go to a new buffer,
    one term at a time."""
    n_rows = x.shape[-2]
    nb = min(_LOOP, n_rows)
    one = isinstance(terms, int) and terms == 1
    if length == x.shape[-1]:
        def block(start, size, out):
            rows = lax.dynamic_slice_in_dim(out, start, size, axis=-2)
            out = lax.dynamic_update_slice_in_dim(out, term(rows, 0), start, axis=-2)

            def add(p, out):
                total = lax.dynamic_slice_in_dim(out, start, size, axis=-2) + term(rows, p)
                return lax.dynamic_update_slice_in_dim(out, total, start, axis=-2)
            return out if one else lax.fori_loop(1, terms, add, out)
        bs = n_rows // nb
        out = lax.fori_loop(0, nb, lambda k, out: block(k * bs, bs, out), x)
        if nb * bs < n_rows:   # the rows left over, one block of fewer rows
            out = block(nb * bs, n_rows - nb * bs, out)
        return out
    bs = -(-n_rows // nb)
    xb = jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(0, nb * bs - n_rows), (0, 0)])
    xb = jnp.moveaxis(xb.reshape(x.shape[:-2] + (nb, bs, x.shape[-1])), -3, 0)

    def every_block(p):
        out = jnp.moveaxis(lax.map(lambda rows: term(rows, p), xb), 0, -3)
        return out.reshape(out.shape[:-3] + (nb * bs, length))[..., :n_rows, :]
    first = every_block(0)
    return first if one else lax.fori_loop(1, terms, lambda p, acc: acc + every_block(p),
                                           first)


def _sample(f, t, *, axis, order):
    """Along −2, whole rows gathered in one fused operation, whose result the PSF's
    sampling along −1 takes over as its buffer; along −1, in row blocks."""
    index, weight = _taps(t, f.shape[axis], order, f.real.dtype)
    if axis == -2:
        return _gathered(f, index, weight, axis)
    return _by_row_blocks(lambda rows, _: _gathered(rows, index, weight, axis), f, t.shape[0])


def _spread(ct, t, *, n, axis, order):
    """The transpose of `_sample` onto ``n`` grid indices, as gathers (module): grid
    index j gathers the points ``a ≤ i < b`` within two samples of it, in passes of
    ``_PASS`` gathers, as many as the most crowded index needs."""
    m = t.shape[0]
    j = jnp.arange(n, dtype=t.dtype)[:, None]
    a = _search(t, j[:, 0] - 2, "right")[:, None]   # first tᵢ > j − 2
    b = _search(t, j[:, 0] + 2, "left")[:, None]    # first tᵢ ≥ j + 2
    broken = jnp.where(jnp.all(jnp.diff(t) >= 0), 1.0, jnp.nan).astype(t.dtype)
    passes = -(-jnp.max(b - a) // _PASS)

    def one_pass(x, p):
        i = a + p * _PASS + jnp.arange(_PASS)
        index = jnp.minimum(i, m - 1)
        w = jnp.where(i < b, bspline(t[index] - j, order) * broken, 0).astype(ct.real.dtype)
        return _gathered(x, index, w, axis)
    if axis == -1:
        return _by_row_blocks(one_pass, ct, n, passes)
    return lax.fori_loop(1, passes, lambda p, acc: acc + one_pass(ct, p), one_pass(ct, 0))


def _with_length(x, axis, length):
    shape = list(x.shape)
    shape[axis] = length
    return jax.core.ShapedArray(tuple(shape), x.dtype)


def _along(dt, axis):
    return dt[:, None] if axis == -2 else dt


sample_p = Primitive("diffcam_spline_sample")
spread_p = Primitive("diffcam_spline_spread")   # the two are each other's transpose
sample_p.def_abstract_eval(lambda f, t, *, axis, order: _with_length(f, axis, t.shape[0]))
spread_p.def_abstract_eval(lambda ct, t, *, n, axis, order: _with_length(ct, axis, n))
for _p, _rule in ((sample_p, _sample), (spread_p, _spread)):
    _p.def_impl(lambda *a, _p=_p, **k: jax.jit(partial(_p.bind, **k))(*a))
    mlir.register_lowering(_p, mlir.lower_fun(_rule, multiple_results=False))


def _sample_jvp_t(dt, f, t, *, axis, order):
    slope = sample_p.bind(f, t, axis=axis, order=order + 1)
    return slope * _along(dt, axis).astype(slope.dtype)


def _spread_jvp_t(dt, ct, t, *, n, axis, order):
    return spread_p.bind(ct * _along(dt, axis).astype(ct.dtype), t, n=n, axis=axis,
                         order=order + 1)


def _sample_transpose(ct, f, t, *, axis, order):
    if type(ct) is ad.Zero:
        return ad.Zero(f.aval), None
    return spread_p.bind(ct, t, n=f.aval.shape[axis], axis=axis, order=order), None


def _spread_transpose(g, ct, t, *, n, axis, order):
    if type(g) is ad.Zero:
        return ad.Zero(ct.aval), None
    return sample_p.bind(g, t, axis=axis, order=order), None


ad.defjvp(sample_p, lambda df, f, t, **k: sample_p.bind(df, t, **k), _sample_jvp_t)
ad.defjvp(spread_p, lambda dct, ct, t, **k: spread_p.bind(dct, t, **k), _spread_jvp_t)
ad.primitive_transposes[sample_p] = _sample_transpose
ad.primitive_transposes[spread_p] = _spread_transpose


def _batcher(prim):
    def batch(args, dims, **k):
        x, t = args
        bx, bt = dims
        if bt is None:
            return prim.bind(jnp.moveaxis(x, bx, 0), t, **k), 0
        t = jnp.moveaxis(t, bt, 0)
        if bx is None:
            return lax.map(lambda ti: prim.bind(x, ti, **k), t), 0
        return lax.map(lambda a: prim.bind(a[0], a[1], **k), (jnp.moveaxis(x, bx, 0), t)), 0
    return batch


batching.primitive_batchers[sample_p] = _batcher(sample_p)
batching.primitive_batchers[spread_p] = _batcher(spread_p)


def spline_sample(f, t, axis: int):
    """The cubic spline with coefficients ``f`` along ``axis`` (−2 or −1), at the
    fractional indices ``t`` (m,), which must not decrease: shape of ``f`` with ``axis``
    of length m. The gradient with respect to ``f`` is NaN where ``t`` decreases."""
    if axis not in (-2, -1):
        raise ValueError(f"axis must be -2 or -1, got {axis}")
    f = jnp.asarray(f)
    t = jnp.asarray(t, f.real.dtype)
    return sample_p.bind(f, t, axis=axis, order=0)
