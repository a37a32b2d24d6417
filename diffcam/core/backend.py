"""The one seam between the physics and the FFT backend.

Every transform in diffcam goes through [`fft2`][diffcam.core.backend.fft2],
[`ifft2`][diffcam.core.backend.ifft2], [`rfft2`][diffcam.core.backend.rfft2] and
[`irfft2`][diffcam.core.backend.irfft2] (over the last two axes, batched over leading ones,
numpy's conventions), and every propagation step through
[`transfer_step`][diffcam.core.backend.transfer_step]. Two backends stand behind them:

- ``"xla"``: ``jnp.fft``; the default, and the only one on GPU/TPU;
- ``"fftw"`` (CPU): FFTW on its own threads through XLA FFI custom calls
  ([`diffcam.core.fftw`][diffcam.core.fftw]; needs FFTW, e.g.
  ``pip install 'diffcam[fftw]'``, and a C++ compiler once).

``"auto"`` takes FFTW on CPU when it loads, else XLA. Choose with
[`set_fft`][diffcam.core.backend.set_fft] or the environment (``DIFFCAM_FFT=xla|auto|fftw``,
``DIFFCAM_FFT_THREADS=n``); [`fft_backend`][diffcam.core.backend.fft_backend] says which one
runs. The choice is made when a function is traced:
[`set_fft`][diffcam.core.backend.set_fft] clears JAX's caches so that jitted functions trace
again. FFTW is not the default: it is GPL and measures a plan for every new shape
(``docs/fft.md``; ``python -m benchmarks.bench_fft`` times both).

Also here, and only here, are the CPU scheduling aids for XLA's FFT. XLA splits a large
elementwise fusion over its thread pool and continues on whichever pool thread finishes
last, where a following FFT runs at one core's speed (the FFT rule, ``docs/design.md``,
"The backend seam"). None of the aids changes a result; each is differentiable and
``vmap``-able, and with FFTW or off the CPU each reduces to the plain expression
([`separable_factor`][diffcam.core.backend.separable_factor] stays on CPU: it is not about
the FFT):

- [`transfer_step`][diffcam.core.backend.transfer_step] writes the product between the two
  FFTs in place, in row blocks, which XLA never splits; it is a linear primitive whose
  reverse rule runs the same program on the conjugated cotangent;
- [`separable_factor`][diffcam.core.backend.separable_factor] computes the 1-D factors of
  separable kernels in a loop, which XLA neither splits nor fuses into the N² product that
  consumes them;
- [`staged`][diffcam.core.backend.staged] runs a computation whose FFT follows a large
  product as two jitted calls, so the FFT starts a call of its own.

What each aid saves: ``python -m benchmarks.bench_propagate`` and
``python -m benchmarks.bench_psf``.
"""

from __future__ import annotations

import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, custom_batching, custom_derivatives, lax
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from diffcam.core import fftw
from diffcam.core.deprecation import renamed
from diffcam.core.errors import DiffcamError

__all__ = ["fft2", "ifft2", "rfft2", "irfft2", "fft_size", "transfer_step",
           "transfer_step_with_spectrum", "separable_factor", "staged", "on_cpu",
           "set_fft", "fft_backend", "fft_status", "in_chunks"]

_AXES = (-2, -1)
BACKENDS = ("auto", "fftw", "xla")
_setting = {"backend": None, "why_not_fftw": None}


def on_cpu() -> bool:
    """True when JAX's default backend is the CPU."""
    return jax.default_backend() == "cpu"


def set_fft(backend: str = "xla", *, threads: int | None = None,
            planning: str = "measure") -> str:
    """Choose the FFT behind every transform; returns the one that will run.

    Args:
        backend: ``"xla"`` (the default), ``"fftw"`` (an error if it cannot load)
            or ``"auto"`` (FFTW on CPU when it loads, else XLA).
        threads: FFTW's threads (default ``$DIFFCAM_FFT_THREADS``, else every CPU this
            process may use).
        planning: FFTW's planning effort, ``"measure"``, ``"patient"`` or
            ``"estimate"`` ([`diffcam.core.fftw.configure`][diffcam.core.fftw.configure]).

    Clears JAX's compilation caches, so that jitted functions trace again with this
    choice.
    """
    _choose(backend, threads, planning)
    jax.clear_caches()
    return fft_backend()


def _choose(backend: str, threads: int | None = None, planning: str = "measure") -> None:
    """Record the choice once FFTW, if asked for, is loaded; nothing changes on error."""
    if backend not in BACKENDS:
        raise DiffcamError(f"the FFT backend is one of {', '.join(BACKENDS)}, not {backend!r}.")
    why_not_fftw = None
    if backend != "xla" and (backend == "fftw" or on_cpu()):
        try:
            fftw.configure(threads=threads, planning=planning)
        except DiffcamError as e:
            if backend == "fftw":
                raise
            why_not_fftw = str(e)
    _setting["backend"], _setting["why_not_fftw"] = backend, why_not_fftw


def fft_backend() -> str:
    """The FFT the next traced function uses: ``"fftw"`` or ``"xla"``."""
    backend = _setting["backend"]
    if backend is None:  # first use: the environment's choice
        backend = os.environ.get("DIFFCAM_FFT", "xla").strip().lower() or "xla"
        if backend not in BACKENDS:
            raise DiffcamError(f"DIFFCAM_FFT is one of {', '.join(BACKENDS)}, not {backend!r}.")
        _choose(backend)  # nothing was traced with another choice: no cache to clear
    if backend == "xla" or not on_cpu() or _setting["why_not_fftw"] is not None:
        return "xla"
    return "fftw"


def fft_status() -> str:
    """One line for logs and reports: the FFT in use and, if FFTW was asked for and
    is not used, why."""
    if fft_backend() == "fftw":
        return f"FFT: FFTW, {fftw.threads()} threads"
    if not on_cpu():
        return f"FFT: XLA on {jax.default_backend()}"
    why = _setting["why_not_fftw"]
    return "FFT: XLA" + (f" (FFTW unavailable: {why.splitlines()[0]})" if why else "")


def _fftw_in_use() -> bool:
    return fft_backend() == "fftw"


def _xla_fft_on_cpu() -> bool:
    """Whether the FFT rule applies (XLA's FFT on CPU): the aids below are needed."""
    return on_cpu() and not _fftw_in_use()


def _norm_scale(norm: str | None, n: int, inverse: bool):
    """The factor numpy's ``norm`` puts on an unnormalised transform of ``n`` samples."""
    if norm == "ortho":
        return 1 / np.sqrt(n)
    if norm not in (None, "backward", "forward"):
        raise DiffcamError(f"norm is None, 'backward', 'ortho' or 'forward', not {norm!r}.")
    return 1 / n if (norm == "forward") != inverse else None


def _scaled(x: Array, scale) -> Array:
    """``x · scale``; the FFTW path scales a transform's input, not its output, so that
    XLA fuses the product into whatever computed the input (a product with a transfer
    function, say) instead of a pass of its own over the result."""
    return x if scale is None else x * jnp.asarray(scale, x.real.dtype)


def _as_complex(u) -> Array:
    u = jnp.asarray(u)
    return u.astype(jnp.promote_types(u.dtype, jnp.complex64))


def _fit(u: Array, shape) -> Array:
    """``u`` cropped or zero-padded at the end of its last two axes to ``shape``."""
    u = u[..., :shape[0], :shape[1]]
    pad = [(0, 0)] * (u.ndim - 2) + [(0, shape[0] - u.shape[-2]), (0, shape[1] - u.shape[-1])]
    return jnp.pad(u, pad) if any(p for _, p in pad) else u


def fft2(u: Array, norm: str | None = None) -> Array:
    """2-D DFT over the last two axes (``numpy.fft.fft2`` conventions)."""
    if not _fftw_in_use():
        return jnp.fft.fft2(u, axes=_AXES, norm=norm)
    u = _as_complex(u)
    return fftw.c2c(_scaled(u, _norm_scale(norm, u.shape[-2] * u.shape[-1], False)), -1)


def ifft2(u: Array, norm: str | None = None) -> Array:
    """Inverse of [`fft2`][diffcam.core.backend.fft2] (``1/(ny·nx)`` unless ``norm`` says
    otherwise)."""
    if not _fftw_in_use():
        return jnp.fft.ifft2(u, axes=_AXES, norm=norm)
    u = _as_complex(u)
    return fftw.c2c(_scaled(u, _norm_scale(norm, u.shape[-2] * u.shape[-1], True)), +1)


def rfft2(u: Array, s=None) -> Array:
    """2-D DFT of a real array over the last two axes, half spectrum along the last;
    ``s`` crops or zero-pads the input first."""
    if not _fftw_in_use() or jnp.iscomplexobj(u):
        return jnp.fft.rfft2(u, s=s, axes=_AXES)
    u = jnp.asarray(u)
    u = u.astype(jnp.promote_types(u.dtype, jnp.float32))
    return fftw.r2c(u if s is None else _fit(u, tuple(s)))


def irfft2(u: Array, s=None) -> Array:
    """Inverse of [`rfft2`][diffcam.core.backend.rfft2] onto the real shape ``s`` (default:
    an even width)."""
    if not _fftw_in_use():
        return jnp.fft.irfft2(u, s=s, axes=_AXES)
    u = _as_complex(u)
    ny, nx = (u.shape[-2], 2 * (u.shape[-1] - 1)) if s is None else tuple(s)
    return fftw.c2r(_scaled(_fit(u, (ny, nx // 2 + 1)), 1 / (ny * nx)), nx)


def fft_size(n: int) -> int:
    """Smallest even length ``>= n`` whose factors are 2, 3 and at most one 5: the one
    rule for every padded FFT grid in diffcam.

    XLA's CPU FFT is fast on 2^a·3^b and 2^a·3^b·5 lengths; lengths with 5² or larger
    primes measured up to 2x slower here (1600 and 2000 against 1536 and 2048).
    """
    m = max(2, int(n) + (int(n) % 2))
    while True:
        k = m
        for p in (2, 3):
            while k % p == 0:
                k //= p
        if k in (1, 5):
            return m
        m += 2


def transfer_step(u: Array, H: Array) -> Array:
    """``ifft2(fft2(u) · H)``: one propagation step with a transfer function ``H`` that
    broadcasts against the spectrum (prebuilt, or the outer product of two 1-D factors).

    With XLA's FFT on CPU the product is written over the spectrum in two row blocks as
    in-place dynamic-update-slices, which keeps the inverse FFT multi-threaded (module
    docstring); a linear primitive there, whose reverse rule runs the same program.
    """
    return transfer_step_with_spectrum(u, H)[0]


def transfer_step_with_spectrum(u: Array, H: Array) -> tuple[Array, Array]:
    """[`transfer_step`][diffcam.core.backend.transfer_step] and the spectrum
    ``fft2(u) · H`` it went through: for a caller that donates both field-sized arrays back
    as the next call's buffers, so that no fresh, page-faulted buffer is allocated per call
    (`diffcam.model.stack`)."""
    if not _xla_fft_on_cpu():
        spectrum = fft2(u) * H
        return ifft2(spectrum), spectrum
    u = _as_complex(u)
    H = jnp.asarray(H).astype(u.dtype)
    return tuple(_rows_step_p.bind(*jnp.broadcast_arrays(u, H)))


def _in_row_blocks(u: Array, H: Array) -> tuple[Array, Array]:
    """ifft2(fft2(u)·H) with the product written over the spectrum in two row blocks as
    in-place dynamic-update-slices (the FFT rule), and the spectrum."""
    u_hat = jnp.fft.fft2(u, axes=_AXES)
    ny = u_hat.shape[-2]
    start = (0,) * (u_hat.ndim - 2)
    for a, b in ((0, ny // 2), (ny // 2, ny)):
        block = u_hat[..., a:b, :] * H[..., a:b, :]
        u_hat = lax.dynamic_update_slice(u_hat, block.astype(u_hat.dtype), start + (a, 0))
    return jnp.fft.ifft2(u_hat, axes=_AXES), u_hat


def _rows_step_transpose(cts, u, H):
    """Reverse mode of the step in ``u``: the adjoint of ifft2(fft2(·)·H) is
    conj(step(conj(ct), conj(H))), the same row-block program, so the reverse pass keeps
    the FFT rule too (a plain transpose put both reverse FFTs after products: 1143 vs
    1000 ms for a 4096² gradient); the spectrum's cotangent adds fft2(H·ct)."""
    ct_field, ct_spectrum = cts
    assert ad.is_undefined_primal(u) and not ad.is_undefined_primal(H)
    ct_u = None
    if type(ct_field) is not ad.Zero:
        ct_u = jnp.conj(_rows_step_p.bind(jnp.conj(ct_field), jnp.conj(H))[0])
    if type(ct_spectrum) is not ad.Zero:
        extra = jnp.fft.fft2(H * ct_spectrum, axes=_AXES)
        ct_u = extra if ct_u is None else ct_u + extra
    return [ad.Zero(u.aval) if ct_u is None else ct_u, None]


def _rows_step_jvp(primals, tangents):
    u, H = primals
    du, dH = tangents
    field, spectrum = _rows_step_p.bind(u, H)
    d_field = d_spectrum = None
    if type(du) is not ad.Zero:
        d_field, d_spectrum = _rows_step_p.bind(du, H)
    if type(dH) is not ad.Zero:   # geometry tangents: the plain expression
        dS = jnp.fft.fft2(u, axes=_AXES) * dH
        d_field = jnp.fft.ifft2(dS, axes=_AXES) + (0 if d_field is None else d_field)
        d_spectrum = dS + (0 if d_spectrum is None else d_spectrum)
    if d_field is None:
        return (field, spectrum), (ad.Zero.from_primal_value(field),
                                   ad.Zero.from_primal_value(spectrum))
    return (field, spectrum), (d_field, d_spectrum)


def _rows_step_batch(args, dims):
    u, H = (jnp.moveaxis(a, d, 0) if d is not None else a for a, d in zip(args, dims))
    size = u.shape[0] if dims[0] is not None else H.shape[0]
    u = u if dims[0] is not None else jnp.broadcast_to(u, (size,) + u.shape)
    H = H if dims[1] is not None else jnp.broadcast_to(H, (size,) + H.shape)
    return _rows_step_p.bind(u, H), (0, 0)


_rows_step_p = Primitive("diffcam_transfer_step_rows")
_rows_step_p.multiple_results = True
_rows_step_p.def_abstract_eval(lambda u, H: (jax.core.ShapedArray(u.shape, u.dtype),) * 2)
_rows_step_p.def_impl(lambda u, H: jax.jit(_rows_step_p.bind)(u, H))
mlir.register_lowering(_rows_step_p, mlir.lower_fun(_in_row_blocks, multiple_results=True))
ad.primitive_jvps[_rows_step_p] = _rows_step_jvp
ad.primitive_transposes[_rows_step_p] = _rows_step_transpose
batching.primitive_batchers[_rows_step_p] = _rows_step_batch


def separable_factor(f: Callable[[Array], Array], n: int, block: int = 512) -> Array:
    """``f(i)`` for the int32 indices ``i = 0 … n − 1``, ``f`` elementwise: shape ``(n,)``.

    For the 1-D factors of separable kernels (chirps). On CPU they are computed block by
    block inside a loop, which XLA neither fuses into the N² product that consumes them
    (it would evaluate the sin/cos once per sample: a Fresnel step 1.3× an FFT pair
    instead of 1.03×) nor splits over threads (module docstring).
    """
    if not on_cpu():
        return f(lax.iota(jnp.int32, n))

    block = min(block, n)

    def one_block(b):
        return f(b * block + lax.iota(jnp.int32, block))
    return lax.map(one_block, jnp.arange(-(-n // block), dtype=jnp.int32)).reshape(-1)[:n]


vector = renamed(separable_factor, "diffcam.core.backend.vector")


STAGED_FROM = 192 * 192  # samples of the first argument from which staged() splits


def staged(first: Callable, second: Callable, static_argnames=()) -> Callable:
    """``second(first(*args), *args)`` as one callable that is jitted once per shape.

    With XLA's FFT on CPU, and a first argument of at least
    [`STAGED_FROM`][diffcam.core.backend.STAGED_FROM] samples, the two halves run as two
    jitted calls, so that ``second``'s FFTs start a program of their own (the FFT rule);
    elsewhere as one. Below that size a second dispatch costs more than the rule (one PSF at
    128²: 0.72 ms split, 0.41 fused; ``benchmarks/bench_overhead.py``). ``static_argnames``
    name keyword arguments of ``second`` that fix shapes or code paths.
    """
    fused = jax.jit(lambda *a, **k: second(first(*a), *a, **k),
                    static_argnames=static_argnames)
    first_j = jax.jit(first)
    second_j = jax.jit(second, static_argnames=static_argnames)

    def call(*a, **k):  # decided per call: the backend may be chosen after import
        if _xla_fft_on_cpu() and max(map(np.size, jax.tree_util.tree_leaves(a[0])),
                                     default=0) >= STAGED_FROM:
            return second_j(first_j(*a), *a, **k)
        return fused(*a, **k)
    return call


def in_chunks(fn: Callable, items_per_chunk: Callable[..., int | None]) -> Callable:
    """``fn`` (a function of arrays and pytrees of arrays) whose ``jax.vmap`` computes
    the batch a chunk at a time, one chunk after another (``lax.map``), not all at once.

    A vmapped PSF otherwise holds every item's fields at once and runs
    one batched FFT over them: 32 PSFs at 1024² took 3.7× the time and 2.8× the memory
    of the same PSFs one after another (``python -m benchmarks.bench_peers``). Here a
    ``vmap`` — a user's ``jax.jit(jax.vmap(psf))`` — becomes the loop
    `diffcam.model.stack.psf_stack` runs: working memory is one chunk's.

    ``items_per_chunk(in_batched, *args)`` gives the chunk (items computed together,
    vmapped inside the loop), or ``None`` for JAX's own batching of ``fn`` where that
    is cheaper; ``in_batched`` is a tuple of one pytree of bools per argument, and
    ``args`` carry the batch axis first where batched.

    Derivatives are ``fn``'s own (forward and reverse mode, JAX's batching of them:
    a ``lax.map`` cannot be linearised): the primal alone runs in chunks. Tangents
    that are symbolically zero (the camera's fields when only the phase is
    differentiated) are left out of ``fn``'s JVP, so no work is spent on them.
    """
    @custom_batching.custom_vmap
    def chunked(*args):
        return fn(*args)

    @chunked.def_vmap
    def _rule(axis_size, in_batched, *args):
        size = items_per_chunk(tuple(in_batched), *args)
        leaves, tree = jax.tree_util.tree_flatten(args)
        flags = jax.tree_util.tree_leaves(tuple(in_batched))
        mapped = [i for i, b in enumerate(flags) if b]

        def items(*batched):
            full = list(leaves)
            for i, leaf in zip(mapped, batched):
                full[i] = leaf
            return fn(*jax.tree_util.tree_unflatten(tree, full))
        batched = [leaves[i] for i in mapped]
        if size is None:
            out = jax.vmap(items)(*batched)
        else:
            out = lax.map(lambda xs: items(*xs), batched,
                          batch_size=min(int(size), axis_size))
        return out, jax.tree_util.tree_map(lambda _: True, out)

    @jax.custom_jvp
    def call(*args):
        return chunked(*args)

    def _jvp(primals, tangents):
        leaves, tree = jax.tree_util.tree_flatten(primals)
        dots = jax.tree_util.tree_leaves(
            tangents, is_leaf=lambda t: isinstance(t, custom_derivatives.SymbolicZero))
        live = [i for i, t in enumerate(dots)
                if not isinstance(t, custom_derivatives.SymbolicZero)]

        def of_live(*values):
            full = list(leaves)
            for i, v in zip(live, values):
                full[i] = v
            return fn(*jax.tree_util.tree_unflatten(tree, full))
        return jax.jvp(of_live, [leaves[i] for i in live], [dots[i] for i in live])
    call.defjvp(_jvp, symbolic_zeros=True)
    return call
