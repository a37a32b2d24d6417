"""Free-space propagation (paper Eqs. 1–2, 6).

Three propagators, all pure, jitted, differentiable in their array and physical
arguments, broadcasting over leading batch axes, complex64 unless given complex128:

- `fresnel_tf`       Fresnel transfer function  H = e^{jkz} e^{-jπλz(fx²+fy²)}
- `fresnel_ir`       Fresnel impulse response   h = e^{jkz}/(jλz) e^{jk(x²+y²)/(2z)}
- `angular_spectrum` exact scalar (Rayleigh–Sommerfeld) transfer function,
  band-limited after Matsushima & Shimobaba (2009), evanescent waves dropped

and `propagate`, which picks the method (and the padding) from the sampling
criterion: for a grid of width L = N·dx a transfer function is sampled while
|z| ≤ dx·L/λ, the impulse response beyond (docs/design.md, "Transfer function vs
impulse response").

Conventions. Fields are centred (index N//2 is the axis, `diffcam.core.grid`). Kernels
are built in FFT order and multiply ``fft2(field)`` directly: convolution is translation
invariant, so no ``fftshift`` is needed in the hot path. Kernels are separable where the
physics is (Fresnel TF and IR): two 1-D chirps whose outer product XLA fuses into the
multiply, so a step costs one FFT pair. The constant phase e^{jkz} is reduced modulo 2π
in float64 when z and λ are concrete (in float32, kz at z = 0.1 m has a step of 0.125
rad); when they are traced, it carries the precision of their dtype (it never affects an
intensity).

.. warning:: Without padding, the FFT makes every propagation circular: light leaving
   one edge of the grid re-enters at the other. The low-level functions default to
   ``pad=0`` (so that a step costs exactly one FFT pair on the given grid);
   `propagate` pads automatically by the spread it predicts.
"""

from __future__ import annotations

import math
from functools import lru_cache, partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jaxtyping import Complex, Num

from diffcam.core.errors import (DiffcamError, check_field, check_finite, check_positive,
                                 found_false, is_concrete, fmt_length, plain_numbers,
                                 sampling_problem)
from diffcam.core.grid import (check_grid_size, coord_at, crop_to, fft_freq_at, fft_freqs,
                               int_pair, pad_by, pitch_yx)
from diffcam.core.deprecation import renamed
from diffcam.core.backend import (fft2, fft_size, ifft2, separable_factor,
                                  transfer_step)
from diffcam.core.phasor import expj
from diffcam.optics.fields import complex_dtype, pack_geometry, piston
from diffcam.optics import lens

__all__ = [
    "fresnel_tf",
    "fresnel_tf_factors",
    "transfer_factors",
    "fresnel_ir",
    "angular_spectrum",
    "propagate",
    "PropagationChoice",
    "choose_propagation",
    "plan_propagation",
    "critical_distance",
    "transfer_pad",
    "transfer_function",
    "apply_transfer",
    "spherical_chirp",
    "magnification",
    "effective_distance",
    "fresnel_number_factors",
]

METHODS = ("fresnel_tf", "fresnel_ir", "angular_spectrum")


# --------------------------------------------------------------------------- helpers

def critical_distance(shape, dx, wavelength) -> tuple[float, float]:
    """z at which a transfer function stops being sampled, per axis (m): N·dx²/λ.

    A transfer function (Fresnel TF, angular spectrum) is sampled for |z| ≤ this
    distance, the impulse response for |z| ≥ it.
    """
    dy, dxx = (float(p) for p in pitch_yx(dx))
    ny, nx = shape[-2], shape[-1]
    lam = float(wavelength)
    return ny * dy * dy / lam, nx * dxx * dxx / lam


def transfer_pad(n: int, dx: float, wavelength: float, z: float) -> int:
    """Samples of pitch ``dx`` (m) to add on each side of an ``n``-sample axis so that a
    transfer function of distance ``z`` (m) is sampled at ``wavelength`` (m): the
    inverse of `critical_distance`, ⌈(λz/dx² − n)/2⌉, at least 0. For a grid ``k``×
    finer than ``dx`` (whose pad is ``k`` times this one), give ``k·wavelength``."""
    return max(0, math.ceil((float(wavelength) * float(z) / float(dx) ** 2 - n) / 2))


def _check_common(field, dx, wavelength, z):
    check_field(field)
    _check_lengths(dx, wavelength, z)


def _check_lengths(dx, wavelength, z):
    for p in pitch_yx(dx):
        check_positive("dx (pixel pitch)", p, "m")
    check_positive("wavelength", wavelength, "m")
    check_positive("z (propagation distance)", z, "m", allow_negative=True)


def _padded_shape(shape, pad):
    py, px = int_pair(pad, "pad")
    return shape[-2] + 2 * py, shape[-1] + 2 * px


def _check_kernel_sampling(method, shape, dx, wavelength, z, pad, accept_undersampling):
    """Concrete sampling check of the TF / IR chirp (docs/design.md, "Validation")."""
    if not is_concrete(dx, wavelength, z) or method == "angular_spectrum":
        return  # the band-limited angular spectrum never aliases its kernel
    zc = min(critical_distance(_padded_shape(shape, pad), dx, wavelength))
    az = abs(float(z))
    if az == 0:
        return
    if method == "fresnel_tf" and az > zc:
        sampling_problem(
            f"Fresnel transfer function is undersampled: |z| = {fmt_length(az)} exceeds "
            f"N·dx²/λ = {fmt_length(zc)} on this (padded) grid, so its chirp aliases; use "
            f"method='fresnel_ir' (or propagate(..., method='auto')), or pad the grid",
            accept_undersampling)
    if method == "fresnel_ir" and az < zc:
        sampling_problem(
            f"Fresnel impulse response is undersampled: |z| = {fmt_length(az)} is below "
            f"N·dx²/λ = {fmt_length(zc)}, so its chirp aliases at the grid edge; use "
            f"method='fresnel_tf' or 'angular_spectrum' (or method='auto')",
            accept_undersampling)


# ---------------------------------------------------------------- transfer functions

def spherical_chirp(n: int, dx, wavelength, z, centre=0.0):
    """exp(jπ(t − centre)²/(λz)) on the centred axis t of ``n`` samples at pitch ``dx``:
    the 1-D factor of a paraxial spherical wave (metres). Computed on its own, not once
    per sample of the N² product that consumes it
    (`diffcam.core.backend.separable_factor`)."""
    def chirp(i):
        t = coord_at(i, n, dx) - centre
        return expj(jnp.pi * (t * t) / (wavelength * z))
    return separable_factor(chirp, n)


def fresnel_tf_factors(shape, dy, dx, wavelength, z):
    """The Fresnel transfer function exp(−jπλz(fy² + fx²)), piston left out, as its two
    1-D factors in FFT order, ``(ny, 1)`` and ``(1, nx)`` (each computed on its own:
    `diffcam.core.backend.separable_factor`); pitches, wavelength and z in metres."""
    return _chirp_factors(shape, dy, dx, wavelength * z)


def fresnel_number_factors(shape, zeta):
    """The Fresnel transfer function of a field in sample units (pitch 1): the factors
    of exp(−jπζ(fy² + fx²)), f in cycles per sample, ζ = λz/dx² the Fresnel number —
    the one distance a sampled field without a known pitch can identify."""
    return _chirp_factors(shape, 1.0, 1.0, zeta)


def _chirp_factors(shape, dy, dx, lambda_z):
    """The factors of exp(−jπ·λz·(fy² + fx²)) in FFT order (``lambda_z`` = λ·z)."""
    def factor(n, d):
        return separable_factor(
            lambda i: expj(-jnp.pi * lambda_z * fft_freq_at(i, n, d) ** 2), n)
    return factor(shape[-2], dy)[:, None], factor(shape[-1], dx)[None, :]


def _fresnel_ir_kernel(shape, dy, dx, wavelength, z):
    """FFT of the sampled, centred impulse response: separable, two 1-D FFTs."""
    def factor(n, d):
        return jnp.fft.fft(jnp.fft.ifftshift(spherical_chirp(n, d, wavelength, z))) * d
    Hy = factor(shape[-2], dy) / (1j * wavelength * z)
    return Hy[:, None], factor(shape[-1], dx)[None, :]


def _angular_spectrum_kernel(shape, dy, dx, wavelength, z, band_limit):
    """exp(j2πz(√(1/λ² − f²) − 1/λ)), evanescent waves set to zero.

    The exponent is written −f²/(1/λ + √(1/λ² − f²)) so it stays accurate in float32
    (no cancellation between two numbers near 1/λ); the e^{jkz} piston is separate.
    The square root is guarded with a double ``where`` so gradients are finite.
    """
    fy, fx = fft_freqs(shape, (dy, dx))
    f2 = fy ** 2 + fx ** 2
    inv_l2 = 1.0 / wavelength ** 2
    propagating = f2 < inv_l2
    root = jnp.sqrt(jnp.where(propagating, inv_l2 - f2, 1.0))
    excess = -f2 / (1.0 / wavelength + root)
    H = jnp.where(propagating, jnp.exp(2j * jnp.pi * z * excess), 0.0)
    if band_limit:
        ny, nx = shape[-2], shape[-1]
        # Matsushima & Shimobaba (2009): |f| ≤ 1/(λ√((2zΔf)² + 1)), Δf = 1/L per axis
        fy_lim = 1.0 / (wavelength * jnp.sqrt((2 * z / (ny * dy)) ** 2 + 1))
        fx_lim = 1.0 / (wavelength * jnp.sqrt((2 * z / (nx * dx)) ** 2 + 1))
        H = H * ((jnp.abs(fy) <= fy_lim) & (jnp.abs(fx) <= fx_lim))
    return H


def transfer_function(shape, dx, wavelength, z, method: str = "angular_spectrum",
                      *, band_limit: bool = True) -> Complex[Array, "ny nx"]:
    """The kernel that multiplies ``fft2(field)`` (FFT order, piston included).

    For loops that propagate the same distance many times (phase retrieval): build it
    once with this, then call `apply_transfer` inside the loop.

    Args:
        shape: ``(..., ny, nx)`` of the (already padded) field.
        dx: sample pitch, metres (scalar or ``(dy, dx)``).
        wavelength: metres.
        z: propagation distance, metres (negative propagates backwards).
        method: ``"fresnel_tf"``, ``"fresnel_ir"`` or ``"angular_spectrum"``.
    """
    if method not in METHODS:
        raise DiffcamError(f"method must be one of {METHODS}, got {method!r}.")
    dy, dxx = pitch_yx(dx)
    return _kernel(shape, dy, dxx, wavelength, z, piston(wavelength, z), method, band_limit)


def _kernel(shape, dy, dx, wavelength, z, p, method, band_limit):
    """The transfer function with piston ``p``: for the Fresnel methods the product of
    two 1-D factors, which fuses into the multiply that consumes it."""
    if method == "angular_spectrum":
        return p * _angular_spectrum_kernel(shape, dy, dx, wavelength, z, band_limit)
    kernel = fresnel_tf_factors if method == "fresnel_tf" else _fresnel_ir_kernel
    hy, hx = kernel(shape, dy, dx, wavelength, z)
    return (p * hy) * hx


def transfer_factors(shape, dx, wavelength, z):
    """The Fresnel transfer function of `transfer_function` (``"fresnel_tf"``) as
    its two 1-D factors, ``(ny, 1)`` with the piston and ``(1, nx)``, for a caller that
    forms their product itself (the scaling-theorem PSF, under ``jax.checkpoint``, so
    that reverse mode keeps the vectors rather than the N² kernel)."""
    dy, dxx = pitch_yx(dx)
    hy, hx = fresnel_tf_factors(shape, dy, dxx, wavelength, z)
    return piston(wavelength, z) * hy, hx


@jax.jit
def apply_transfer(field: Complex[Array, "... ny nx"],
                   H: Complex[Array, "ny nx"]) -> Complex[Array, "... ny nx"]:
    """``ifft2(fft2(field) · H)``: one propagation step with a prebuilt kernel."""
    return transfer_step(field, H)


def _step(u, H, in_place=True):
    """``ifft2(fft2(u) · H)``. For a prebuilt or separable H through
    `diffcam.core.backend.transfer_step`; a kernel computed per sample (the angular
    spectrum's square root and exponential) costs more computed serially than the inverse
    FFT loses, so it is multiplied as one plain product."""
    return transfer_step(u, H) if in_place else ifft2(fft2(u) * H)


@partial(jax.jit, static_argnames=("method", "pad", "band_limit"))
def _propagate_core(field, geometry, *, method, pad, band_limit):
    shape = field.shape
    u = field.astype(complex_dtype(field))
    dy, dx, wavelength, z = geometry[0], geometry[1], geometry[2], geometry[3]
    p = lax.complex(geometry[4], geometry[5]).astype(u.dtype)
    if pad != (0, 0):
        u = pad_by(u, pad)
    H = _kernel(u.shape, dy, dx, wavelength, z, p, method, band_limit)
    out = _step(u, H, in_place=method != "angular_spectrum").astype(u.dtype)
    if pad != (0, 0):
        out = crop_to(out, shape)
    return out, jnp.isfinite(field).all()


def _run(method, field, dx, wavelength, z, pad, accept_undersampling, band_limit=True):
    # the NaN/Inf check of a device field is computed inside the jitted call (one
    # dispatch instead of two: 130 µs of a 128² step's 440) and raised after it
    check_field(field, finite="host")
    args = (method, np.shape(field), complex_dtype(field), dx, wavelength, z, pad,
            accept_undersampling)
    plain = not accept_undersampling and plain_numbers(dx, wavelength, z, pad)
    eager = isinstance(field, jax.Array) and not isinstance(field, jax.core.Tracer)
    prepared = (_prepare if not plain else _prepare_on_device if eager else
                _prepare_plain)(*args)
    if prepared is None:
        return jnp.asarray(field).astype(args[2])  # z = 0 is the identity
    pad, geometry = prepared
    out, finite = _propagate_core(field, geometry, method=method, pad=pad,
                                  band_limit=band_limit)
    if found_false(finite):
        check_finite("field", field)    # raises, with the count of bad samples
    return out


def _prepare(method, shape, cdt, dx, wavelength, z, pad, accept_undersampling):
    """The geometry's checks, then ``(pad as (py, px), geometry vector)`` for
    `_propagate_core`, or None for z = 0 (the identity)."""
    _check_lengths(dx, wavelength, z)
    check_grid_size(shape, pad)
    pad = int_pair(pad, "pad")
    _check_kernel_sampling(method, shape, dx, wavelength, z, pad, accept_undersampling)
    if is_concrete(z) and float(np.max(np.abs(np.asarray(z)))) == 0.0:
        return None
    rdt = jnp.float64 if cdt == jnp.complex128 else jnp.float32
    return pad, pack_geometry((*pitch_yx(dx), wavelength, z), piston(wavelength, z), rdt)


@lru_cache(maxsize=256)
def _prepare_plain(*args):
    """`_prepare` remembered for plain-number geometry: an eager call with a
    geometry that passed before skips the checks (35 µs of Python against 150 µs of
    device work for a 128² step). Not used with ``accept_undersampling``, whose warnings
    must repeat; a geometry that fails raises every time (errors are not remembered).
    The vector stays a NumPy array: a device array kept here and reused inside someone's
    trace becomes an argument of their program that its ahead-of-time compiled form
    does not pass (jax 0.10: "compiled for 2 inputs but called with 1")."""
    return _prepare(*args)


@lru_cache(maxsize=256)
def _prepare_on_device(*args):
    """`_prepare_plain` with the geometry vector on the device, for an eager call
    on a device array: no host-to-device copy per call (17 µs of a 128² step's 200).
    Only then: inside someone's trace a device array kept here would become an argument
    of their program (above), which a field that is itself a device array does anyway."""
    prepared = _prepare_plain(*args)
    return None if prepared is None else (prepared[0], jax.device_put(prepared[1]))


def fresnel_tf(field: Num[Array, "... ny nx"], dx, wavelength, z, *, pad=0,
               accept_undersampling: bool = False) -> Complex[Array, "... ny nx"]:
    """Fresnel propagation by the transfer function (paraxial), paper Eq. 6.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly to validate, or check the geometry alone
    (no field) with `choose_propagation` or `critical_distance`.

    Args:
        field: complex field, last two axes space (centred grid).
        dx: sample pitch, metres per sample (scalar or ``(dy, dx)``).
        wavelength: metres.
        z: distance, metres; negative propagates backwards, 0 is the identity.
        pad: zero samples added on each side before the FFT and cropped after (int
            or ``(py, px)``); 0 means circular propagation (wrap-around). The padded
            grid holds at most ``diffcam.core.grid.MAX_GRID_SAMPLES``.
        accept_undersampling: turn the aliasing error into a warning.

    Raises:
        SamplingError: ``|z| > N·dx²/λ`` on the padded grid (the chirp aliases).
        DiffcamError: a pad that is not whole and ≥ 0, or a padded grid above the
            limit (checked before anything is allocated).
    """
    return _run("fresnel_tf", field, dx, wavelength, z, pad, accept_undersampling)


def fresnel_ir(field: Num[Array, "... ny nx"], dx, wavelength, z, *, pad=0,
               accept_undersampling: bool = False) -> Complex[Array, "... ny nx"]:
    """Fresnel propagation by the impulse response (paraxial), paper Eqs. 1–2.

    Convolution with h = e^{jkz}/(jλz) e^{jk(x²+y²)/(2z)} sampled on the grid. Accurate
    for ``|z| ≥ N·dx²/λ``; not exactly invertible (the sampled kernel is not unitary).
    Arguments as in [`fresnel_tf`][diffcam.optics.propagation.fresnel_tf].

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly to validate, or check the geometry alone
    (no field) with `choose_propagation` or `critical_distance`.
    """
    return _run("fresnel_ir", field, dx, wavelength, z, pad, accept_undersampling)


def angular_spectrum(field: Num[Array, "... ny nx"], dx, wavelength, z, *, pad=0,
                     band_limit: bool = True) -> Complex[Array, "... ny nx"]:
    """Exact scalar propagation by the angular spectrum (Rayleigh–Sommerfeld).

    H = exp(j2πz√(1/λ² − fx² − fy²)); evanescent components (f > 1/λ) are dropped.
    With ``band_limit=True`` frequencies beyond 1/(λ√((2z/L)² + 1)) are also dropped
    (Matsushima & Shimobaba 2009), which removes the aliasing of the kernel at long
    distances; for short distances the limit lies beyond the grid's Nyquist and changes
    nothing. Arguments as in [`fresnel_tf`][diffcam.optics.propagation.fresnel_tf].

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly to validate.
    """
    return _run("angular_spectrum", field, dx, wavelength, z, pad, False, band_limit)


# ---------------------------------------------------------------------- Fourier lens

# --------------------------------------------------------------- Fresnel scaling theorem

def magnification(z1, z2):
    """M = (z1 + z2)/z1: how much the Fresnel scaling theorem magnifies the diffuser's
    plane-wave field for a point source at ``z1`` and a sensor at ``z2`` (metres).

    A field g times a spherical wave diverging from distance z1, propagated by z2, is
    g propagated by `effective_distance` and magnified by M, scaled in amplitude by
    1/M, times a known quadratic phase (docs/design.md, "Fresnel scaling theorem").
    """
    return (z1 + z2) / z1


def effective_distance(z1, z2):
    """z_eff = z1·z2/(z1 + z2) (metres): the plane-wave propagation distance of the
    scaling theorem (see `magnification`)."""
    return z1 * z2 / (z1 + z2)


# ------------------------------------------------------------------------ the chooser

class PropagationChoice(NamedTuple):
    """What `propagate` ran, and why."""

    method: str
    pad: tuple[int, int]
    critical_distance: float  # N·dx²/λ on the padded grid, metres (smaller axis)
    reason: str

    def __str__(self) -> str:
        return f"{self.method} (pad {self.pad[0]}×{self.pad[1]}): {self.reason}"


def _energy_bounds(weights: np.ndarray, keep: float) -> tuple[int, int]:
    c = np.cumsum(weights)
    total = c[-1]
    lo = int(np.searchsorted(c, (1 - keep) / 2 * total))
    hi = int(np.searchsorted(c, (1 + keep) / 2 * total))
    return lo, min(hi, len(weights) - 1)


def _auto_pad(field, dx, wavelength, z, keep=0.999) -> tuple[int, int]:
    """Zero padding per side that keeps the field's spread inside the grid.

    The field's 99.9 % energy support and 99.9 % spectral bandwidth are measured; light
    at the band edge travels |z|·tanθ sideways (sin θ = λ·f); the pad covers what that
    spread takes beyond the room left between the support and the grid edge.
    """
    u = np.asarray(field)
    intensity = np.abs(u.reshape((-1,) + u.shape[-2:])) ** 2
    intensity = intensity.sum(axis=0)
    spectrum = np.abs(np.fft.fftshift(np.fft.fft2(u.reshape((-1,) + u.shape[-2:])),
                                      axes=(-2, -1))) ** 2
    spectrum = spectrum.sum(axis=0)
    pads = []
    for axis, (n, p) in enumerate(zip(u.shape[-2:], pitch_yx(dx))):
        other = 1 - axis
        lo, hi = _energy_bounds(intensity.sum(axis=other), keep)
        room = min(lo, n - 1 - hi)
        flo, fhi = _energy_bounds(spectrum.sum(axis=other), keep)
        f_edge = max(abs(flo - n // 2), abs(fhi - n // 2)) / (n * float(p))
        sin_t = min(float(wavelength) * f_edge, 0.999)
        spread = abs(float(z)) * sin_t / math.sqrt(1 - sin_t ** 2)
        need = max(0, math.ceil(spread / float(p)) - room)
        if need:
            need = (fft_size(n + 2 * need) - n + 1) // 2
        pads.append(need)
    return pads[0], pads[1]


def choose_propagation(shape, dx, wavelength, z, pad=(0, 0)) -> PropagationChoice:
    """Pick the propagator for distance ``z`` on a grid padded by ``pad`` per side.

    The angular spectrum (exact, and identical to Fresnel TF where that is valid) while
    its transfer function is sampled, |z| ≤ N·dx²/λ; the Fresnel impulse response
    beyond, where the transfer function's chirp would alias.
    """
    pad = int_pair(pad, "pad")
    zc = min(critical_distance(_padded_shape(shape, pad), dx, wavelength))
    az = abs(float(z))
    if az <= zc:
        return PropagationChoice("angular_spectrum", pad, zc,
                                 f"|z| = {fmt_length(az)} ≤ N·dx²/λ = {fmt_length(zc)}: "
                                 f"transfer function sampled")
    return PropagationChoice("fresnel_ir", pad, zc,
                             f"|z| = {fmt_length(az)} > N·dx²/λ = {fmt_length(zc)}: "
                             f"impulse response sampled, transfer function would alias")


def plan_propagation(field: Num[Array, "... ny nx"], dx, wavelength, z, *,
                     method: str = "auto", pad="auto") -> PropagationChoice:
    """The method and padding `propagate` runs for these arguments, and why.

    Args:
        field: complex field (concrete when ``pad="auto"``: its support and bandwidth
            set the padding).
        dx, wavelength, z: metres.
        method: ``"auto"`` (see `choose_propagation`) or one of the methods.
        pad: ``"auto"`` (the spread predicted from the field's support and bandwidth,
            rounded up to an FFT-friendly size) or an int / ``(py, px)``.
    """
    check_field(field, finite=True if pad == "auto" else "host")  # else in the propagation
    if pad == "auto":
        if not is_concrete(field, z, dx, wavelength):
            raise DiffcamError("pad='auto' inspects the field and z, which are traced here; "
                               "pass pad=<int> (zero samples per side) inside jit/grad/vmap.")
        _check_common(field, dx, wavelength, z)
        pad = _auto_pad(field, dx, wavelength, z)
    pad = int_pair(pad, "pad")
    if method == "auto":
        if not is_concrete(z, dx, wavelength):
            raise DiffcamError("method='auto' compares z with N·dx²/λ, which needs concrete "
                               "values; pass method='angular_spectrum', 'fresnel_tf' or "
                               "'fresnel_ir' inside jit/grad/vmap.")
        return choose_propagation(np.shape(field), dx, wavelength, z, pad)
    if method in METHODS:
        zc = min(critical_distance(_padded_shape(np.shape(field), pad), dx, wavelength)) \
            if is_concrete(dx, wavelength) else float("nan")
        return PropagationChoice(method, pad, zc, "chosen by the caller")
    raise DiffcamError(f"method must be 'auto' or one of {METHODS}, got {method!r}.")


def propagate(field: Num[Array, "... ny nx"], dx, wavelength, z, *, method: str = "auto",
              pad="auto", accept_undersampling: bool = False, verbose: bool = False
              ) -> Complex[Array, "... ny nx"]:
    """Propagate ``field`` by ``z`` with the method and padding the sampling calls for
    (`plan_propagation` says which, and why).

    Args:
        field: complex field, last two axes space (centred grid), concrete when
            ``pad="auto"``.
        dx: pitch, metres per sample (scalar or ``(dy, dx)``).
        wavelength: metres.
        z: metres.
        method, pad: as for `plan_propagation`.
        accept_undersampling: warn instead of raising on an aliased kernel.
        verbose: print the choice.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly to validate, or `plan_propagation`
    with the concrete arguments.

    Under an outer ``jit`` the automatic choices need concrete values: pass ``method``
    and an integer ``pad`` explicitly there.
    """
    choice = plan_propagation(field, dx, wavelength, z, method=method, pad=pad)
    if verbose:
        print(f"diffcam.optics.propagate: {choice}")
    if choice.method == "angular_spectrum":
        return angular_spectrum(field, dx, wavelength, z, pad=choice.pad)
    return _run(choice.method, field, dx, wavelength, z, choice.pad, accept_undersampling)


fourier_lens = renamed(lens.fourier_lens, "diffcam.optics.propagation.fourier_lens")
inverse_fourier_lens = renamed(lens.inverse_fourier_lens,
                               "diffcam.optics.propagation.inverse_fourier_lens")
