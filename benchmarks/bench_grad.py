"""Reverse mode against the forward pass: ``value_and_grad`` ÷ forward, both PSF paths.

    python -m benchmarks.bench_grad --sizes 512 1024 2048 4096

For each N and each PSF path (``direct``: Eq. 7 propagated by z2; ``scaling``: the
scaling theorem, the default), the loss Σ w·PSF(phase) at one depth (w a fixed random
weight, the shape of a data term), compiled once as ``jax.jit(loss)`` and once as
``jax.jit(jax.value_and_grad(loss))`` with respect to the phase. Times are medians of
interleaved repeats (``benchmarks.harness``; at least ``--repeats``, and at least 2 s
of forward calls at small sizes), and the ratio is the median over the rounds of each
round's value_and_grad ÷ forward (the two calls side by side); memory is XLA's own
figure for each compiled program (``memory_analysis()``: temporaries, and temporaries
plus arguments and outputs), and the page faults of one call (``getrusage``): XLA
allocates a call's temporaries afresh, and glibc maps a block of 32 MiB or more anew on
every call, so the kernel zero-fills it page by page (:mod:`diffcam.core.memory`; run
with ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` for huge pages). The issue's targets:
ratio ≤ 2 and a gradient step's memory ≤ 3× the forward's, at 512²–4096².

Where the ratio can go: the gradient with respect to the phase carries the cotangent
back through the propagation to the diffuser, so every reverse pass contains at least
one transfer step (FFT, product, inverse FFT) on the padded grid, the forward's own
FFT work. Each round also times that step alone (input donated), giving
``floor`` = 1 + step ÷ forward (paired per round): no implementation of this gradient
has a ratio below it. ``forward_over_step`` and ``reverse_over_step`` =
(value_and_grad − forward) ÷ step put both passes in units of that step: the reverse
pass is the forward's chain transposed (the same FFTs, a product for each product, the
spline's transpose for the spline), so it costs what the forward costs less the
forward's own non-linear work, and the ratio sits near 2 when that work is small.

A reference written by hand is timed after, in rounds of its own beside the forward
(``hand_ratio``: its value_and_grad ÷ diffcam's forward): the same forward, then the
adjoint chain with this loss folded in, which a library cannot do (it does not know the
loss), so the normalisation's transpose costs no reduction of its own. On the scaling
path it uses diffcam's spline transpose: it shows what the chain costs, not what
another transpose would. ``hand_grad_error`` is its largest difference from diffcam's
gradient, relative to the largest entry. ``plain_ratio`` is JAX's own value_and_grad
of the reference's forward chain, written as plain JAX (÷ diffcam's forward, in the
same rounds): what reverse mode makes of the chain without diffcam's ``psf`` around
it. The JSON is ``grad_<backend>.json`` (``grad_<backend>_huge_pages.json`` with huge
pages).
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.harness import markdown_table, time_interleaved, write_json
from diffcam.core import memory
from diffcam.core.backend import fft_backend, transfer_step
from diffcam.core.grid import crop_to, pad_to
from diffcam.core.phasor import expj
from diffcam.model import Camera, psf
from diffcam.model.point_spread import sample_points, zeff_factors
from diffcam.model.spline import spline_sample
from diffcam.optics.elements import apply_phase, spherical_wave
from diffcam.optics.propagation import apply_transfer, transfer_function

LAM, DX, Z2, Z1 = 532e-9, 5e-6, 1e-3, 25e-3
MIN_SECONDS = 2.0


def _camera(n, method):
    return Camera(wavelength=LAM, z2=Z2, dx=DX, aperture_radius=0.3 * n * DX, shape=(n, n),
                  method=method)


def _memory_mb(compiled):
    """(temporaries, temporaries + arguments + outputs) in MB, or (None, None)."""
    try:
        m = compiled.memory_analysis()
    except Exception:  # optional in XLA backends
        return None, None
    total = m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes
    return m.temp_size_in_bytes / 2 ** 20, total / 2 ** 20


def _transfer_step(camera):
    """One Fresnel transfer step (FFT, product, inverse FFT) on the camera's padded grid,
    its input donated: the least work any reverse pass of either path must do (the
    cotangent goes back through the propagation to the diffuser), so no gradient can
    cost less than forward + step."""
    kernel = transfer_function(camera.padded_shape, camera.dx, camera.wavelength, camera.z2,
                               "fresnel_tf")
    step = jax.jit(apply_transfer, donate_argnums=0)
    field = [jnp.ones(camera.padded_shape, jnp.complex64)]

    def call():
        field[0] = step(field[0], kernel)
        return field[0]
    return call


def _hand_written(camera, w):
    """value_and_grad of Σ w·PSF, by hand. The PSF is |c|²/Σ|c|², so the cotangent of c
    is 2(w − L)c/S (L the loss, S = Σ|c|²), and the gradient C·Im(e^{−jθ}·b), with b that
    cotangent carried back to the diffuser's field C·e^{jθ}.

    Direct path: c is the crop of P·(C·e^{jθ}·U1), P the transfer step by z2, so
    b = U1*·P^H(c's cotangent, padded), P^H the step with H* (the Fresnel kernel is
    unitary up to its scale). Scaling path: c = S·P'(C·e^{jθ}), P' the step with the z_eff
    kernel times the spline prefilter (formed from its vectors in each step) and S the magnifying
    spline sampling, so b = P'^H·Sᵀ(c's cotangent), Sᵀ the library's spline transpose
    (``jax.linear_transpose``): the chain is written out, the transposes are diffcam's."""
    forward, back = _chain(camera)
    loss = _loss(camera, w, forward)

    def value_and_grad(phase):
        value, (c, state, total) = loss(phase)
        b = crop_to(back(2 * (w - value) / total * c, state), camera.shape)
        return value, camera.aperture() * jnp.imag(jnp.conj(expj(phase)) * b)
    return value_and_grad


def _plain_autodiff(camera, w):
    """JAX's own value_and_grad of the hand-written reference's forward chain: what
    reverse mode makes of the same chain written as plain JAX, without diffcam's
    ``psf`` around it."""
    loss = _loss(camera, w, _chain(camera)[0])
    return jax.value_and_grad(lambda phase: loss(phase)[0])


def _loss(camera, w, forward):
    """phase → (Σ w·|c|²/Σ|c|², (c, the chain's state, Σ|c|²)), c = forward(C·e^{jθ})."""
    def loss(phase):
        c, state = forward(pad_to(apply_phase(camera.aperture(), phase), camera.padded_shape))
        intensity = c.real ** 2 + c.imag ** 2
        total = jnp.sum(intensity)
        return jnp.sum(w * intensity) / total, (c, state, total)
    return loss


def _chain(camera):
    return _scaling_chain(camera) if camera.method == "scaling" else _direct_chain(camera)


def _direct_chain(camera):
    kernel = transfer_function(camera.padded_shape, camera.dx, camera.wavelength, camera.z2,
                               "fresnel_tf")
    cy, cx = spherical_wave(camera.padded_shape, camera.dx, camera.wavelength, Z1)

    def forward(f):
        return crop_to(transfer_step(f * (cy * cx), kernel), camera.out_shape), None

    def back(ct, _):
        return transfer_step(pad_to(ct, camera.padded_shape), jnp.conj(kernel)) \
            * jnp.conj(cy * cx)
    return forward, back


def _scaling_chain(camera):
    """P' and S from diffcam's own geometry (``zeff_factors``, ``sample_points``)."""
    shape = camera.padded_shape
    factors = zeff_factors(camera, camera.wavelength, Z1)
    ty, tx = sample_points(shape, camera, Z1)

    def sample(field):
        return spline_sample(spline_sample(field, ty, -2), tx, -1)

    def kernel():   # formed where it is used: XLA fuses it into the product
        hy, hx, by, bx = factors
        return (hy * hx) * (by * bx)

    def forward(f):
        field = transfer_step(f, kernel())
        return sample(field), field

    def back(ct, field):
        (ct_field,) = jax.linear_transpose(sample, field)(ct)
        return transfer_step(ct_field, jnp.conj(kernel()))
    return forward, back


def _hand_reference(camera, w, phase, fwd, vag, rounds):
    """The references' figures (the hand-written gradient, and JAX's gradient of the same
    chain), measured after diffcam's rounds, in rounds of their own beside the forward,
    so that diffcam's rounds are those of a run without them."""
    by_hand = jax.jit(_hand_written(camera, w)).lower(phase).compile()
    plain = jax.jit(_plain_autodiff(camera, w)).lower(phase).compile()
    ours, theirs = vag(phase)[1], by_hand(phase)[1]
    error = float(jnp.max(jnp.abs(theirs - ours)) / jnp.max(jnp.abs(ours)))
    del ours, theirs
    t = time_interleaved({"forward": lambda: fwd(phase), "hand": lambda: by_hand(phase),
                          "plain": lambda: plain(phase)}, repeats=rounds, budget_s=150)
    forward_s = np.asarray(t["forward"]["times_s"])
    return {"hand_ratio": float(np.median(np.asarray(t["hand"]["times_s"]) / forward_s)),
            "plain_ratio": float(np.median(np.asarray(t["plain"]["times_s"]) / forward_s)),
            "hand_grad_error": error, "hand_temp_mb": _memory_mb(by_hand)[0],
            "plain_temp_mb": _memory_mb(plain)[0],
            "hand_faults": _faults_per_call(lambda: by_hand(phase))}


def _faults_per_call(fn, calls=3):
    """Minor page faults of one call (the process's count, so other threads' too)."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(calls):
        jax.block_until_ready(fn())
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / calls


def run(sizes=(512, 1024, 2048, 4096), repeats=7) -> list[dict]:
    rows = []
    for n in sizes:
        rng = np.random.default_rng(0)
        phase = jnp.asarray(rng.uniform(-np.pi, np.pi, (n, n)), jnp.float32)
        for method in ("direct", "scaling"):
            cam = _camera(n, method)
            w = jnp.asarray(rng.random(cam.out_shape), jnp.float32)

            def loss(ph):
                return jnp.sum(w * psf(ph, cam, Z1, accept_undersampling=True))

            fwd = jax.jit(loss).lower(phase).compile()
            vag = jax.jit(jax.value_and_grad(loss)).lower(phase).compile()
            # small grids run in milliseconds and swing with the machine: at least
            # MIN_SECONDS of forward calls, so that their medians settle
            start = time.perf_counter()
            jax.block_until_ready(fwd(phase))
            once = time.perf_counter() - start
            step = _transfer_step(cam)
            calls = {"forward": lambda: fwd(phase), "value_and_grad": lambda: vag(phase),
                     "step": step}
            rounds = max(repeats, int(MIN_SECONDS / once))
            t = time_interleaved(calls, repeats=rounds, budget_s=180)
            hand = _hand_reference(cam, w, phase, fwd, vag, rounds)
            (ft, fa), (gt, ga) = _memory_mb(fwd), _memory_mb(vag)
            f_ms, g_ms = 1e3 * t["forward"]["median_s"], 1e3 * t["value_and_grad"]["median_s"]
            # the median of each round's ratio (a forward and a gradient call side by
            # side): the machine's drift cancels, which a ratio of medians keeps
            fwd_s, vag_s, step_s = (np.asarray(t[k]["times_s"]) for k in
                                    ("forward", "value_and_grad", "step"))
            paired = float(np.median(vag_s / fwd_s))
            floor = float(np.median(1 + step_s / fwd_s))
            rows.append({"N": n, "path": method, "forward_ms": f_ms, "value_and_grad_ms": g_ms,
                         "ratio": paired, "ratio_of_medians": g_ms / f_ms,
                         "step_ms": 1e3 * t["step"]["median_s"], "floor": floor,
                         "forward_over_step": float(np.median(fwd_s / step_s)),
                         "reverse_over_step": float(np.median((vag_s - fwd_s) / step_s)),
                         "forward_faults": _faults_per_call(lambda: fwd(phase)),
                         "grad_faults": _faults_per_call(lambda: vag(phase)),
                         "forward_temp_mb": ft, "grad_temp_mb": gt,
                         "forward_total_mb": fa, "grad_total_mb": ga,
                         "memory_ratio": None if fa is None else ga / fa,
                         **hand, "repeats": t["forward"]["repeats"],
                         "loadavg": os.getloadavg()[0]})
            print(markdown_table(rows[-1:], COLUMNS), flush=True)
    return rows


COLUMNS = ["N", "path", "forward_ms", "value_and_grad_ms", "ratio", "hand_ratio", "plain_ratio",
           "step_ms", "floor", "forward_over_step", "reverse_over_step", "ratio_of_medians",
           "forward_faults", "grad_faults", "forward_temp_mb", "grad_temp_mb",
           "forward_total_mb", "grad_total_mb", "memory_ratio", "hand_temp_mb", "plain_temp_mb",
           "hand_faults", "hand_grad_error", "loadavg"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048, 4096])
    p.add_argument("--repeats", type=int, default=7)
    args = p.parse_args(argv)
    rows = run(args.sizes, args.repeats)
    print(markdown_table(rows, COLUMNS))
    name = f"grad_{fft_backend()}" + ("_huge_pages" if memory.huge_pages() == "on" else "")
    extra = {"loss": "sum(w * psf(phase, camera, 25 mm))", "memory": memory.status()}
    print(f"{memory.status()}\nwrote {write_json(name, rows, extra)}")


if __name__ == "__main__":
    main()
