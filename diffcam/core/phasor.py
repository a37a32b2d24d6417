"""e^{jθ} at the cost of a few products: the diffuser's phase factor (paper Eq. 5).

XLA's CPU backend evaluates ``jnp.exp(1j * θ)`` as ``exp(0)``, ``cos θ`` and ``sin θ``,
each with its own argument reduction: at 1024² (float32, 2 cores) 5.4 ms, about a
third of a PSF with FFTW. [`expj`][diffcam.core.phasor.expj] reduces θ once, by the nearest
multiple of π/2 (Cody–Waite: π/2 split into parts short enough that their products with the
quadrant are exact), evaluates one polynomial for sin and one for cos on [−π/4, π/4] and
swaps and negates them by quadrant: 0.4 ms at 1024², every step a vectorised product.

Accuracy (float32, θ taken as the float32 it is): within 1.3e-7 of e^{jθ} for
|θ| ≤ 1e6 rad (XLA's: 4.4e-8), measured by ``tests/test_phasor.py``. The reduction is
exact while the quadrant is below 2^13 (|θ| < 12868 rad); beyond, it degrades slowly
as compiled at XLA's default optimisation level, which fuses each product and
subtraction into one multiply-add (with ``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` the error
at 1e6 rad is 3e-2). From 2^22 rad on, where float32 phases are 0.5 rad apart and
carry no phase at all, the value stays on the unit circle within 1e-3 but is not
e^{jθ}. float64 phases take XLA's own
``jnp.exp(1j * θ)``: float64 is diffcam's precision for checking, not for speed. The
derivative is exact: d e^{jθ} = j·e^{jθ}·dθ (a custom JVP, so reverse mode keeps only
the result).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = ["expj"]


def _split(x: float, parts: int, bits: int) -> list[np.float32]:
    """``x`` as a sum of float32 parts with ``bits`` significant bits each (the last
    part full): products of the parts with integers below 2^(24 − bits) are exact."""
    out = []
    for i in range(parts):
        if i == parts - 1:
            out.append(np.float32(x))
            break
        e = np.floor(np.log2(abs(x)))
        part = np.round(x / 2.0 ** (e - bits + 1)) * 2.0 ** (e - bits + 1)
        out.append(np.float32(part))
        x -= part
    return out


def _fit(target, powers) -> list[np.float32]:
    """Least-squares coefficients of ``r**powers`` for ``target(r)`` on Chebyshev nodes
    of [0, π/4]: a near-minimax fit of the absolute error, computed once at import."""
    r = np.pi / 8 * (1 + np.cos(np.pi * (np.arange(512) + 0.5) / 512))
    a = np.stack([r ** p for p in powers], axis=1)
    return [np.float32(c) for c in np.linalg.lstsq(a, target(r), rcond=None)[0]]


_HALF_PI = _split(np.pi / 2, 3, 11)   # quadrants up to 2^13 are exact
_REACH = np.float32(np.pi / 2)        # |r| ≤ π/4 + rounding of n; beyond: θ > 2^22 rad
# sin r = r + r³·S(r²), cos r = 1 − r²/2 + r⁴·C(r²); errors 2e-9 and 5e-11 in float64
_S = _fit(lambda r: np.sin(r) - r, (3, 5, 7))
_C = _fit(lambda r: np.cos(r) - 1 + r ** 2 / 2, (4, 6, 8))


def _horner(coefficients, x):
    out = coefficients[-1]
    for c in reversed(coefficients[:-1]):
        out = out * x + c
    return out


def _sincos(theta):
    """(sin θ, cos θ) of a float32 array."""
    n = jnp.round(theta * np.float32(2 / np.pi))
    r = theta
    for part in _HALF_PI:
        r = r - n * part
    r = jnp.clip(r, -_REACH, _REACH)   # only beyond 2^22 rad (module docstring)
    r2 = r * r
    s = r + r * r2 * _horner(_S, r2)
    c = 1 - np.float32(0.5) * r2 + r2 * r2 * _horner(_C, r2)
    quadrant = n.astype(jnp.int32) & 3        # θ ≈ r + quadrant·π/2
    odd = (quadrant & 1) == 1
    sin = jnp.where(odd, c, s)
    cos = jnp.where(odd, s, c)
    return (jnp.where(quadrant >= 2, -sin, sin),
            jnp.where((quadrant == 1) | (quadrant == 2), -cos, cos))


@jax.custom_jvp
def expj(theta):
    """e^{jθ} for a real array θ (radians): complex64 for float32 (and narrower or
    integer) θ, complex128 for float64."""
    theta = jnp.asarray(theta)
    if theta.dtype == jnp.float64:
        return jnp.exp(1j * theta)
    if theta.dtype != jnp.float32:
        theta = theta.astype(jnp.float32)
    sin, cos = _sincos(theta)
    return lax.complex(cos, sin)


@expj.defjvp
def _expj_jvp(primals, tangents):
    out = expj(primals[0])
    return out, out * (1j * jnp.asarray(tangents[0])).astype(out.dtype)
