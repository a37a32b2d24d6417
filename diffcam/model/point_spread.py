"""The diffuser-camera PSF at any depth (paper Eqs. 7–8).

A point source at ``(y1, x1, z1)`` lights a circular aperture C (or any mask) carrying
a thin diffuser of phase θd; the field travels ``z2`` to the sensor, which records the
intensity:

    PSF(u) = |P_z2{C · e^{jθd} · U1}(u)|²,   U1 = e^{jkz1}/(jλz1) e^{jk|x − ρ1|²/(2z1)}

with ρ1 = (x1, y1) and P_z the Fresnel transfer-function propagator.

Two ways to evaluate it (``Camera.method``):

``"scaling"`` (default) — the Fresnel scaling theorem (docs/design.md). Expanding the two
quadratic phases,

    P_z2{g·U1}(u) = (1/M) e^{jφ(u)} e^{jkz1}/(jλz1) · P_zeff{g}(u/M + ρ1·z2/(z1 + z2)),

    z_eff = z1·z2/(z1 + z2),   M = (z1 + z2)/z1,

where φ is a known quadratic phase that drops out of the intensity. The source's chirp
is never sampled, so any ``z1`` works at the diffuser's pitch, and ``FFT(g)`` is shared
by every depth and every lateral position: a depth costs one inverse FFT, a position one
interpolation. The magnified field is sampled at the sensor-grid points by separable
cubic B-spline interpolation (its prefilter folded into the transfer function) of the
*complex field* — band-limited at the grid's Nyquist — and squared afterwards: the
intensity has twice the field's bandwidth, so interpolating it would blur speckle. The
result is the irradiance at the sensor-grid points, like the direct path; integrating
over pixels of another pitch is `diffcam.model.sensor.bin_pixels`.

``"direct"`` — the literal Eq. 7 on the grid, for checking: the point-source chirp is
sampled at the aperture, which aliases for close sources (a `SamplingError`
unless ``accept_undersampling=True``).

Both propagate with the Fresnel transfer function on a grid zero-padded by
``Camera.pad`` per side (wrap-around otherwise) and return the centred ``Camera.crop``.

Each path is two steps, which `diffcam.model.stack` runs over many depths: the
fields the FFTs start from (`fields_for_fft`) and what the FFTs make of them
(`irradiance`); a PSF is ``irradiance(fields_for_fft(...))``.
"""

from __future__ import annotations

import weakref
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float
from jax import Array

from diffcam.core.backend import (fft2, ifft2, in_chunks, staged,
                                  transfer_step_with_spectrum)
from diffcam.core.errors import (DiffcamError, ShapeError, check_finite, check_positive,
                                 fmt_length, found_false, is_concrete, plain_numbers,
                                 sampling_problem)
from diffcam.core.grid import crop_to, pad_to
from diffcam.model.camera import (Camera, HeightMap, as_spectrum, diffuser_phase,
                                  real_dtype)
from diffcam.model import off_axis
from diffcam.model.sensor import bspline_prefilter
from diffcam.model.spline import spline_sample
from diffcam.optics.elements import apply_phase, spherical_wave
from diffcam.optics.propagation import (critical_distance, effective_distance,
                                        magnification, transfer_factors,
                                        transfer_function)
from diffcam.optics.sampling import check_point_source_sampling

__all__ = ["psf", "depth_list", "on_axis_arguments", "source_psfs", "diffuser_fields",
           "fields_for_fft", "fields_per_depth", "irradiance", "zeff_factors",
           "sample_points", "check_inputs"]


# --------------------------------------------------------------- Eq. 7, step by step

def diffuser_fields(phase, camera: Camera, wavelengths) -> Array:
    """C · e^{jθd(λ)} (paper Eqs. 4–5) on the padded grid, one per wavelength:
    (nλ, ny, nx) complex; on the scaling path its FFT, which every depth shares. With a
    stop away from the diffuser (`diffcam.model.off_axis`) e^{jθd} alone: each source
    has its own shadow C."""
    thetas = jax.vmap(lambda lam: diffuser_phase(phase, lam, camera.wavelength))(wavelengths)
    if camera.aperture_distance is not None:
        return pad_to(apply_phase(jnp.ones(camera.shape, thetas.dtype), thetas),
                      camera.padded_shape)
    fields = pad_to(apply_phase(camera.aperture(), thetas), camera.padded_shape)
    return fft2(fields) if camera.method == "scaling" else fields


def _sensor_kernel(camera, wavelength):
    """The Fresnel transfer function over z2, times the sensor's angular response."""
    kernel = transfer_function(camera.padded_shape, camera.dx, wavelength, camera.z2,
                               "fresnel_tf")
    if camera.acceptance_exponent is None:
        return kernel
    return kernel * off_axis.response_amplitude(camera.padded_shape, camera.dx, wavelength,
                                                camera.acceptance_exponent)


def _source_fields(diffuser, camera, wavelength, z1, positions):
    """C·e^{jθd}·U1 for each source offset (y1, x1) (Eq. 2 times Eqs. 4–5): (npos, ny,
    nx); U1's constant 1/(jλz1) is applied to the intensity."""
    def one(offset):
        cy, cx = spherical_wave(diffuser.shape, camera.dx, wavelength, z1, y1=offset[0],
                                x1=offset[1])
        return _through_stop(diffuser, camera, z1, offset) * (cy * cx)
    return jax.vmap(one)(positions)


def _through_stop(diffuser, camera, z1, offset):
    """The diffuser field in the stop's shadow for the source at ``offset`` (itself when
    the aperture is on the diffuser and already applied)."""
    if camera.aperture_distance is None:
        return diffuser
    return diffuser * off_axis.stop_shadow(camera, z1, offset)


def zeff_factors(camera, wavelength, z1):
    """The scaling theorem's transfer function on the camera's padded grid, times the
    separable spline prefilter, as four vectors (hy, hx, by, bx): the product
    (hy·hx)·(by·bx) multiplies the diffuser's spectrum (`_zeff_spectrum`)."""
    ny, nx = camera.padded_shape
    hy, hx = transfer_factors((ny, nx), camera.dx, wavelength,
                              effective_distance(z1, camera.z2))
    return hy, hx, bspline_prefilter(ny)[:, None], bspline_prefilter(nx)[None, :]


def _zeff_spectrum(diffuser_hat, camera, wavelength, z1):
    """Spectrum of the cubic B-spline coefficients of P_zeff{C·e^{jθd}}: its inverse FFT is
    the field the scaling theorem magnifies (the separable spline prefilter rides on the
    transfer function). (n, ny, nx) for n spectra: one (the positions only move the
    sampling), or one per position in a moving stop's shadow."""
    # Under jax.checkpoint, reverse mode keeps the four vectors and forms the N² product
    # again inside the multiply's transpose; without it, XLA kept the product as an
    # array (8 MB and 3 ms of a 1024² gradient). Multiplying by the vectors one after
    # another would do as well, but rounds differently, and the demo's Fig. 6
    # calibration then landed in another basin (bench_fig6_seeds: 0.875 for 0.930).
    @jax.checkpoint
    def filtered(d, hy, hx, by, bx):
        return d * ((hy * hx) * (by * bx))
    factors = zeff_factors(camera, wavelength, z1)
    return filtered(diffuser_hat, *factors)


def sample_points(shape, camera, z1, y1=0.0, x1=0.0, margin: int = 0):
    """Where the scaling theorem samples the z_eff field on a grid of ``shape``: the
    sensor-grid points (the crop and ``margin`` samples per side), magnified by M about
    the image of the source (y1, x1), in fractional sample indices (ty, tx); both
    increase (spline_sample's promise)."""
    z2 = camera.z2
    mag = magnification(z1, z2)
    ny, nx = shape
    cy, cx = camera.out_shape
    shift = z2 / (z1 + z2) / camera.dx  # source offset → sample offset, per metre
    ty = (jnp.arange(cy + 2 * margin) - margin - cy // 2) / mag + y1 * shift + ny // 2
    tx = (jnp.arange(cx + 2 * margin) - margin - cx // 2) / mag + x1 * shift + nx // 2
    return ty, tx


def _magnified(field, camera, wavelength, z1, y1, x1):
    """|·|² of the z_eff field magnified by M about the image of the source, at the
    sensor-grid points (as the pixels record it, with an angular response): the
    irradiance but for the constant 1/(Mλz1)² of the scaling theorem
    (`_source_constant`)."""
    accepting = camera.acceptance_exponent is not None
    margin = off_axis.MARGIN if accepting else 0
    ty, tx = sample_points(field.shape[-2:], camera, z1, y1, x1, margin)
    s = spline_sample(spline_sample(field, ty, -2), tx, -1)
    if accepting:
        s = off_axis.accepted_on_sensor(s, camera, wavelength, z1, y1, x1)
    return s.real ** 2 + s.imag ** 2


def _source_constant(camera, wavelength, z1):
    """The factor between |·|² of what the FFTs make and the irradiance (per m², of a unit
    point source): the source's 1/(λz1)², times the scaling theorem's 1/M² (M·λ·z1 =
    λ(z1 + z2))."""
    if camera.method == "scaling":
        return 1 / (wavelength * (z1 + camera.z2)) ** 2
    return 1 / (wavelength * z1) ** 2


def fields_for_fft(prepared, camera: Camera, wavelengths, z1, positions) -> Array:
    """What the FFTs of one depth start from, (nλ, n, ny, nx) complex: the source fields
    C·e^{jθd}·U1 (direct, n = npos) or the spectra of the z_eff fields (scaling, n = 1).

    ``prepared`` is `diffuser_fields`; ``positions`` (npos, 2) of (y1, x1), metres.
    """
    def per_wavelength(prep, lam):
        if camera.method == "direct":
            return _source_fields(prep, camera, lam, z1, positions)
        if camera.aperture_distance is None:
            return _zeff_spectrum(prep[None], camera, lam, z1)
        shadowed = jax.vmap(lambda offset: fft2(_through_stop(prep, camera, z1, offset)))
        return _zeff_spectrum(shadowed(positions), camera, lam, z1)
    return jax.vmap(per_wavelength)(prepared, wavelengths)


def irradiance_and_fields(fields, camera, wavelengths, weights, z1, positions, normalise):
    """`irradiance`, and the two field-sized arrays its FFTs wrote (the executor in
    `diffcam.model.stack` hands them back as the next call's buffers)."""
    def per_wavelength(u, lam):
        constant = _source_constant(camera, lam, z1) * off_axis.vignetting(camera, z1,
                                                                           positions)
        if camera.method == "scaling":
            field = ifft2(u)   # one z_eff field, or one per position's stop shadow
            psfs = jax.vmap(lambda f, p: _magnified(f, camera, lam, z1, p[0], p[1]),
                            in_axes=(0 if u.shape[0] > 1 else None, 0))(
                field if u.shape[0] > 1 else field[0], positions)
            return _normalised(psfs, normalise, constant), (u, field)
        kernel = _sensor_kernel(camera, lam)
        field, spectrum = transfer_step_with_spectrum(u, kernel)
        out = crop_to(field, camera.out_shape)
        psfs = out.real ** 2 + out.imag ** 2
        return _normalised(psfs, normalise, constant), (field, spectrum)
    psfs, written = jax.vmap(per_wavelength)(fields, wavelengths)
    return jnp.tensordot(weights, psfs, axes=1) / jnp.sum(weights), written


def irradiance(fields, camera: Camera, wavelengths, weights, z1, positions,
               normalise: bool = True) -> Array:
    """PSFs of one depth, (npos, ny, nx) on the crop, from `fields_for_fft`:
    |P_z2{·}|² (direct) or the magnified z_eff field (scaling), normalised per wavelength
    if asked, then averaged with the spectrum's ``weights``."""
    return irradiance_and_fields(fields, camera, wavelengths, weights, z1, positions,
                                  normalise)[0]


def _normalised(intensity, normalise, constant):
    """Unit sum over the last two axes, or the irradiance (times ``constant``).

    The constant, which drops out of the unit sum, is never applied before it: for a
    close source it is ~10¹⁶ m⁻², the sum S of the irradiance 10²² and more, and S²,
    which JAX's quotient rule divides by in reverse mode, overflows float32 (> 3.4·10³⁸).
    The rule's second term then turned 0, silently: float32 gradients of the
    scaling-theorem PSF were 50–60 % off (``test_float32_gradient_agrees_with_float64``).
    """
    if not normalise:
        return intensity * constant
    return intensity / jnp.sum(intensity, axis=(-2, -1), keepdims=True)


def _spectrum_or_camera(camera, wavelengths, weights):
    """The spectrum, or (``None``) the camera's one wavelength at weight 1."""
    if wavelengths is None:
        dtype = real_dtype(camera)
        return jnp.reshape(camera.wavelength, (1,)).astype(dtype), jnp.ones((1,), dtype)
    return wavelengths, weights


def _fields_of_phase(phase, camera, wavelengths, weights, z1, positions):
    """First stage of `psf`: the fields its FFTs start from, and whether the
    diffuser is finite (checked here rather than in a dispatch of its own)."""
    wavelengths, _ = _spectrum_or_camera(camera, wavelengths, weights)
    arr = phase.height if isinstance(phase, HeightMap) else phase
    fields = fields_for_fft(diffuser_fields(phase, camera, wavelengths), camera, wavelengths,
                            z1, positions)
    return fields, jnp.isfinite(arr).all()


def _irradiance_of_fields(first, phase, camera, wavelengths, weights, z1, positions, *,
                          normalise):
    fields, finite = first
    wavelengths, weights = _spectrum_or_camera(camera, wavelengths, weights)
    return irradiance(fields, camera, wavelengths, weights, z1, positions, normalise)[0], finite


_psf = staged(_fields_of_phase, _irradiance_of_fields, static_argnames=("normalise",))


FIELD_SAMPLES_PER_CHUNK = 2 ** 20
"""Field samples computed together when PSFs are computed many at a time (a chunk of
`diffcam.model.stack.psf_stack`, a ``vmap`` of `psf`): one depth at 1024²."""


def items_per_chunk(camera: Camera, fields_per_item: int) -> int:
    """PSFs (depths, or any batched item) per chunk when each needs ``fields_per_item``
    fields on the padded grid: about `FIELD_SAMPLES_PER_CHUNK` samples, at least 1."""
    ny, nx = camera.padded_shape
    return max(1, FIELD_SAMPLES_PER_CHUNK // (ny * nx * max(1, fields_per_item)))


def fields_per_depth(camera: Camera, npos: int) -> int:
    """Fields one depth's ``npos`` sources need per wavelength: one each on the direct
    path or in a moving stop's shadow, else one z_eff field for all."""
    return npos if camera.method == "direct" or camera.aperture_distance is not None else 1


def source_psfs(prepared, camera, wavelengths, weights, z1, positions, normalise):
    """PSFs of one source depth from `diffuser_fields`' output: (npos, ny, nx)
    (``wavelengths`` and ``weights`` as `on_axis_arguments` gives them)."""
    return irradiance(fields_for_fft(prepared, camera, wavelengths, z1, positions), camera,
                      wavelengths, weights, z1, positions, normalise)


def _chunk_rule(in_batched, prepared, camera, wavelengths, weights, z1, positions):
    """Chunks for a ``vmap`` of `psf`: a batch of lateral positions alone on the
    scaling path is JAX's own batching (the z_eff field is shared, each position is a
    resampling of it); anything else (depths, wavelengths, diffusers, cameras) is
    computed a chunk at a time, each item its own fields."""
    shared = [b for i, b in enumerate(in_batched) if i != 5]
    if camera.method == "scaling" and not any(jax.tree_util.tree_leaves(shared)):
        return None
    return items_per_chunk(camera, prepared.shape[-3] * fields_per_depth(camera,
                                                                         positions.shape[-2]))


_depth_psfs = {normalise: in_chunks(lambda p, c, w, g, z, x, n=normalise:
                                    source_psfs(p, c, w, g, z, x, n), _chunk_rule)
               for normalise in (True, False)}


def _traced_psf(phase, camera, wavelengths, weights, z1, positions, normalise):
    """`psf` under a JAX transformation: the depth-independent diffuser fields,
    then the source's PSFs, which a ``vmap`` computes a chunk at a time
    (`diffcam.core.backend.in_chunks`)."""
    wavelengths, weights = _spectrum_or_camera(camera, wavelengths, weights)
    prepared = diffuser_fields(phase, camera, wavelengths)
    return _depth_psfs[normalise](prepared, camera, wavelengths, weights, z1, positions)[0]


# ------------------------------------------------------------------------- validation

def check_inputs(phase, camera, z1, offsets, wavelengths, accept_undersampling,
                 finite: bool = True):
    """Concrete checks before tracing: shapes, NaN, signs, and sampling at the extremes.

    ``z1`` and ``offsets`` (lateral distances |ρ1|, metres) may be arrays; the smallest
    z1 and largest offset are checked. ``finite=False`` leaves the NaN/Inf check of a
    device-array diffuser to the caller (`psf` computes it inside its jitted call);
    a NumPy one is checked here, before anything else can fail.
    """
    _check_phase(phase, camera, finite)
    check_positive("z1 (source distance)", z1, "m")
    check_positive("lateral source offset |(y1, x1)|", offsets, "m", allow_zero=True)
    if not is_concrete(z1, offsets, camera, wavelengths):
        return
    z1, offsets = np.asarray(z1), np.asarray(offsets)
    _check_geometry(camera, float(np.min(z1)), float(np.max(z1)),
                    float(np.max(np.abs(offsets))) if offsets.size else 0.0,
                    np.atleast_1d(np.asarray(wavelengths, dtype=np.float64)).tolist(),
                    accept_undersampling)


def _check_phase(phase, camera, finite):
    """The camera, the diffuser's shape, and (``finite``, or a NumPy diffuser) its NaN."""
    if not isinstance(camera, Camera):
        raise DiffcamError(f"camera must be a diffcam.model.camera.Camera, got {type(camera)}.")
    arr = phase.height if isinstance(phase, HeightMap) else phase
    what = "height map" if isinstance(phase, HeightMap) else "phase"
    if np.shape(arr) != tuple(camera.shape):
        raise ShapeError(f"diffuser {what} has shape {np.shape(arr)} but the camera grid is "
                         f"{tuple(camera.shape)}; embed it with diffcam.core.grid.pad_to or "
                         f"build the Camera with shape={np.shape(arr)[-2:]}.")
    if np.iscomplexobj(arr):
        raise DiffcamError(
            f"diffuser {what} is complex ({np.asarray(arr).dtype}); θd is a real phase in "
            f"radians: pass np.angle(t) for a complex transmission t, or np.real(phase) if "
            f"the imaginary part is rounding.")
    if finite or not isinstance(arr, jax.Array):
        check_finite(f"diffuser {what}", arr)


def _check_geometry(camera, z_min, z_max, rho, wavelengths, accept_undersampling):
    """The frame and the sampling, for sources from ``z_min`` to ``z_max`` (metres) up to
    ``rho`` off axis."""
    dx, z2 = float(camera.dx), float(camera.z2)
    half_diagonal = 0.5 * float(np.hypot(*camera.out_shape)) * dx
    if rho * z2 / z_min > half_diagonal:
        raise DiffcamError(
            f"a source {fmt_length(rho)} off axis at z1 = {fmt_length(z_min)} is imaged "
            f"{fmt_length(rho * z2 / z_min)} from the sensor centre, outside the "
            f"{camera.out_shape[0]}×{camera.out_shape[1]} frame (half-diagonal "
            f"{fmt_length(half_diagonal)}): its PSF would miss the frame. Move the source "
            f"towards the axis or enlarge the camera's crop.")
    if camera.method == "scaling":
        _check_magnified_sampling(camera, z_min, accept_undersampling)
    off_axis.check_off_axis(camera, z_min, rho, wavelengths, accept_undersampling)
    for lam in wavelengths:
        # transfer-function sampling of the longest propagation on the padded grid
        z_prop = z2 if camera.method == "direct" else effective_distance(z_max, z2)
        zc = min(critical_distance(camera.padded_shape, dx, lam))
        if z_prop > zc:
            sampling_problem(
                f"the Fresnel transfer function for {fmt_length(z_prop)} aliases on this "
                f"grid (critical distance N·dx²/λ = {fmt_length(zc)}); increase Camera.pad "
                f"or the grid", accept_undersampling)
        if camera.method == "direct":
            check_point_source_sampling(lam, z_min, off_axis.lit_radius(camera, z_min, rho),
                                        rho, dx, "at the aperture edge", accept_undersampling)


MIN_SAMPLES_ACROSS = 4
"""Fewest diffuser-grid samples the sensor frame may span on the scaling path (where
the z_eff field is magnified by M, the frame spans ``min(out_shape)/M`` of them)."""


def _check_magnified_sampling(camera, z_min, accept_undersampling):
    """The scaling path reads the z_eff field magnified by M = (z1 + z2)/z1 about the
    image of the source, so the sensor frame spans ``n/M`` samples of the diffuser grid.
    For a very close source (M of tens) that is one or two samples: the PSF is then a
    spline interpolation between them, nearly flat, whatever the diffuser (the direct
    path refuses the same geometry for its undersampled chirp). The light spreads over
    M times the aperture, far beyond the frame; ``n/M`` does not depend on the pitch,
    only on the frame's pixel count and on z1."""
    n = min(camera.out_shape)
    m = float(magnification(z_min, float(camera.z2)))
    if n / m >= MIN_SAMPLES_ACROSS:
        return
    need = (f"z1 ≥ {fmt_length(float(camera.z2) / (n / MIN_SAMPLES_ACROSS - 1))}, "
            if n > MIN_SAMPLES_ACROSS else "")
    sampling_problem(
        f"at z1 = {fmt_length(z_min)} the scaling theorem magnifies the field M = {m:.3g}×, "
        f"so the {n}-pixel-wide frame spans {n / m:.2g} diffuser samples (fewer than "
        f"{MIN_SAMPLES_ACROSS}) and the PSF is an interpolation between them, nearly flat; "
        f"use {need}or a frame of more pixels (Camera shape and crop)", accept_undersampling)


def psf(phase, camera: Camera, z1, *, y1=0.0, x1=0.0, spectrum=None, normalise: bool = True,
        accept_undersampling: bool = False) -> Float[Array, "ny nx"]:
    """The camera's PSF for a point source at ``(x1, y1, z1)`` (paper Eq. 7).

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (one PSF is cheap) to validate;
    [`diffcam.optics.sampling.plan_sampling`][diffcam.optics.sampling.plan_sampling] checks
    the sampling of the geometry alone, without a phase.

    Args:
        phase: the diffuser: its phase θd on the camera grid (radians, at
            ``camera.wavelength``), or a [`HeightMap`][diffcam.model.camera.HeightMap].
        camera: the [`Camera`][diffcam.model.camera.Camera] (its ``method`` picks scaling
            theorem or direct).
        z1: source-to-aperture distance, metres (> 0).
        y1, x1: lateral source position, metres (keywords); the PSF moves by
            −(y1, x1)·z2/z1.
        spectrum: ``(wavelengths, weights)`` (metres, relative power) for broadband
            light: the weight-averaged PSF; ``None`` is monochromatic at
            ``camera.wavelength``.
        normalise: unit sum over the returned crop (default: what the stop's shadow,
            the angular response and vignetting take off the power is divided out);
            ``False`` returns the physical irradiance of a unit point source (1/M² of
            the scaling theorem, 1/(λz1)² of the source and the camera's off-axis terms
            included), per m² of sensor. Its values reach
            10¹⁶ for close sources and their sum 10²²: a float32 loss that squares
            such a sum (a quotient's derivative does) overflows, so scale it first.
        accept_undersampling: turn sampling errors into warnings.

    Returns:
        ``camera.out_shape`` float array. Pure and jitted; differentiable in ``phase``,
        ``z1``, ``x1``, ``y1`` and the camera's traced fields.

    Raises:
        ShapeError: the phase does not match the camera grid.
        DiffcamError: z1 ≤ 0, NaN in the phase, a complex or non-numeric phase, bad
            spectrum.
        SamplingError: ``method="direct"`` with an undersampled source chirp, a
            transfer function that aliases, or (``"scaling"``) a source so close that
            the frame spans fewer than `MIN_SAMPLES_ACROSS` diffuser samples.
    """
    arguments = _arguments(phase, camera, z1, y1, x1, spectrum, accept_undersampling)
    if _traced(phase, camera, arguments):
        return _traced_psf(phase, camera, *arguments, normalise)
    out, finite = _psf(phase, camera, *arguments, normalise=normalise)
    if found_false(finite):
        check_finite("diffuser phase", phase.height if isinstance(phase, HeightMap) else phase)
    return out


def depth_list(z1) -> np.ndarray:
    """The depths ``z1`` (a number or a 1-D list, metres) as float64 ``(nz,)`` (traced:
    flattened, unchecked values).

    Raises:
        DiffcamError: no depth, more than one axis, or a value that is not a finite
            number > 0 (each checked by `check_positive`).
    """
    if np.ndim(z1) > 1:
        raise ShapeError(f"z1 must be one depth or a 1-D list of depths (nz,), got shape "
                         f"{np.shape(z1)}; flatten it (np.ravel) if the order is meant.")
    check_positive("z1", z1, "m")
    if not is_concrete(z1):   # under a transformation (psf_map's depths)
        return jnp.reshape(z1, (-1,))
    return np.asarray(z1, dtype=np.float64).reshape(-1)


def on_axis_arguments(phase, camera: Camera, z1, spectrum):
    """The checks of `psf` for on-axis sources at the depths ``z1`` (metres, (nz,)), then
    ``(wavelengths, weights, z1, positions)``: the spectrum (the camera's wavelength at
    weight 1 if ``None``), the depths in the camera's dtype, one on-axis position."""
    wavelengths, weights, z1, positions = _arguments(phase, camera, z1, 0.0, 0.0, spectrum,
                                                     False)
    _check_phase(phase, camera, finite=True)
    wavelengths, weights = _spectrum_or_camera(camera, wavelengths, weights)
    return wavelengths, weights, z1, positions


def _traced(phase, camera, arguments) -> bool:
    """Whether `psf` runs under a JAX transformation: a tracer among the diffuser,
    the camera's fields or the source. The fields are read from the camera's
    ``__dict__`` past equinox's attribute hook (2.5 µs an attribute; a tree walk cost
    an eager PSF 30 µs)."""
    if isinstance(phase, HeightMap):
        return not is_concrete(phase, camera, arguments)
    fields = object.__getattribute__(camera, "__dict__").values()
    return any(isinstance(v, jax.core.Tracer) for v in (phase, *fields, *arguments))


def _arguments(phase, camera, z1, y1, x1, spectrum, accept_undersampling):
    """The checks, then what `psf` passes to ``_psf`` after the phase and the
    camera: ``(wavelengths, weights, z1, positions)``. Remembered for a camera and a
    plain-number source that passed (`_PASSED`)."""
    remember = spectrum is None and not accept_undersampling and plain_numbers(z1, y1, x1)
    if remember:
        key = (id(camera), z1, y1, x1)
        passed = _PASSED.get(key)
        if passed is not None and passed[0]() is camera:
            _check_phase(phase, camera, finite=False)
            return passed[1]
    dtype = real_dtype(camera)
    if spectrum is None:   # the camera's wavelength, taken inside the jitted call
        wavelengths = weights = None
    else:
        wavelengths, weights = (a.astype(dtype) for a in as_spectrum(spectrum, camera))
    concrete = is_concrete(z1, y1, x1)
    offset = np.hypot(x1, y1) if concrete else jnp.hypot(x1, y1)
    check_inputs(phase, camera, z1, offset,
                 camera.wavelength if wavelengths is None else wavelengths,
                 accept_undersampling, finite=False)
    # host values go to the jitted calls as NumPy arrays: no eager dispatch per argument
    xp = np if concrete else jnp
    z1 = xp.asarray(z1, dtype)
    positions = xp.stack([xp.asarray(y1, dtype), xp.asarray(x1, dtype)])[None]
    if not remember:
        return wavelengths, weights, z1, positions
    arguments = (None, None, z1, positions)   # NumPy, as the propagators' (AOT-safe)
    if len(_PASSED) >= 256:
        _PASSED.clear()
    _PASSED[key] = (weakref.ref(camera), arguments)
    return arguments


# sources that passed the checks: (id(camera), z1, y1, x1) → (a weak reference to the
# camera, psf's arguments); an id is reused only after its object is gone, and a changed
# camera is a new object (equinox modules are immutable). An eager 128² PSF then skips
# 70 µs of checks and conversions (of ~0.45 ms)
_PASSED: dict = {}
