"""The diffuser-camera PSF at any depth (paper Eqs. 7–8).

A point source at ``(x1, y1, z1)`` lights a circular aperture C (or any mask) carrying
a thin diffuser of phase θd; the field travels ``z2`` to the sensor, which records the
intensity:

    PSF(u) = |P_z2{C · e^{jθd} · U1}(u)|²,   U1 = e^{jkz1}/(jλz1) e^{jk|x − ρ1|²/(2z1)}

with ρ1 = (x1, y1) and P_z the Fresnel transfer-function propagator.

Two ways to evaluate it (``Camera.method``):

``"scaling"`` (default) — the Fresnel scaling theorem (DESIGN.md). Expanding the two
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
over pixels of another pitch is :func:`diffcam.sensor.bin_pixels`.

``"direct"`` — the literal Eq. 7 on the grid, for checking: the point-source chirp is
sampled at the aperture, which aliases for close sources (a :class:`SamplingError`
unless ``accept_undersampling=True``).

Both propagate with the Fresnel transfer function on a grid zero-padded by
``Camera.pad`` per side (wrap-around otherwise) and return the centred ``Camera.crop``.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from .errors import (DiffcamError, ShapeError, check_field, check_finite, check_positive,
                     fmt_length, is_concrete, sampling_problem)
from .grid import crop_to, pad_to
from .optics import circular_aperture, point_source_max_frequency
from .propagate import critical_distance, spherical_chirp, transfer_function
from .xla_cpu import fusion_barrier, update_rows_for_fft
from .sensor import bspline_prefilter, cubic_sample

__all__ = ["Camera", "HeightMap", "Spectrum", "psf", "diffuser_phase", "random_diffuser",
           "with_method", "METHODS"]

METHODS = ("scaling", "direct")


def _scalar(x):
    """A strongly typed real scalar: float32, or float64 when given or when x64 is on."""
    x = jnp.asarray(x)
    return x.astype(jnp.promote_types(x.dtype, jnp.float32))


def real_dtype(camera) -> jnp.dtype:
    """The real dtype the camera computes in (its pitch's)."""
    return jnp.promote_types(camera.dx.dtype, jnp.float32)


def _optional_array(x):
    return None if x is None else jnp.asarray(x)


def _pair(v, name):
    if isinstance(v, (int, np.integer)):
        return int(v), int(v)
    if isinstance(v, (tuple, list)) and len(v) == 2 and all(
            isinstance(a, (int, np.integer)) for a in v):
        return int(v[0]), int(v[1])
    raise DiffcamError(f"{name} must be an int or a pair of ints, got {v!r}.")


class Camera(eqx.Module):
    """A diffuser camera: static geometry plus traced physical numbers.

    Static (hashable; changing one recompiles): ``shape``, ``pad``, ``crop``, ``method``,
    ``edge``. Traced (array leaves: differentiable, ``vmap``-able, new values reuse the
    compiled code): ``wavelength``, ``z2``, ``dx``, ``aperture_radius`` or
    ``aperture_mask``. Change a field with ``dataclasses.replace(camera, z2=2e-3)`` (which
    re-validates) or ``eqx.tree_at`` (which does not, for use under transforms).

    Attributes:
        wavelength: metres (the wavelength a phase-array diffuser is given at).
        z2: diffuser-to-sensor distance, metres (> 0).
        dx: sample pitch of the diffuser and sensor grids, metres per sample.
        aperture_radius: radius of the circular aperture centred on the axis, metres;
            or ``None`` when ``aperture_mask`` is given.
        aperture_mask: transmission of the aperture on the ``shape`` grid (0…1); or
            ``None`` for the circular aperture.
        shape: ``(ny, nx)`` samples of the diffuser grid.
        pad: zero samples added per side before propagating (int or ``(py, px)``).
        crop: ``(ny, nx)`` of the returned PSF, centred (default: ``shape``).
        method: ``"scaling"`` (Fresnel scaling theorem, default) or ``"direct"``.
        edge: ``"hard"`` (as in the paper) or ``"soft"`` (one-pixel ramp,
            differentiable in ``aperture_radius``) circular-aperture edge.
    """

    wavelength: Float[Array, ""] = eqx.field(converter=_scalar)
    z2: Float[Array, ""] = eqx.field(converter=_scalar)
    dx: Float[Array, ""] = eqx.field(converter=_scalar)
    aperture_radius: Float[Array, ""] | None = eqx.field(default=None,
                                                         converter=_optional_array)
    aperture_mask: Float[Array, "ny nx"] | None = eqx.field(default=None,
                                                            converter=_optional_array)
    shape: tuple[int, int] = eqx.field(default=(1024, 1024), static=True)
    pad: tuple[int, int] = eqx.field(default=(0, 0), static=True,
                                     converter=lambda v: _pair(v, "pad"))
    crop: tuple[int, int] | None = eqx.field(default=None, static=True)
    method: str = eqx.field(default="scaling", static=True)
    edge: str = eqx.field(default="hard", static=True)

    def __check_init__(self):
        shape = _pair(tuple(self.shape), "shape")
        if min(shape) <= 0:
            raise ShapeError(f"camera shape must be positive (ny, nx), got {self.shape}.")
        if min(self.pad) < 0:
            raise DiffcamError(f"pad must be ≥ 0 samples per side, got {self.pad}.")
        if self.crop is not None:
            cy, cx = _pair(tuple(self.crop), "crop")
            if not (0 < cy <= shape[0] and 0 < cx <= shape[1]):
                raise ShapeError(f"crop {self.crop} must be positive and fit in the grid "
                                 f"{shape}; crop to at most the camera shape.")
        if self.method not in METHODS:
            raise DiffcamError(f"method must be one of {METHODS}, got {self.method!r}.")
        if self.edge not in ("hard", "soft"):
            raise DiffcamError(f"edge must be 'hard' or 'soft', got {self.edge!r}.")
        check_positive("wavelength", self.wavelength, "m")
        check_positive("z2 (diffuser-to-sensor distance)", self.z2, "m")
        check_positive("dx (pixel pitch)", self.dx, "m")
        if (self.aperture_radius is None) == (self.aperture_mask is None):
            raise DiffcamError("give exactly one of aperture_radius (metres) and "
                               "aperture_mask (an array on the camera grid).")
        if self.aperture_mask is not None:
            if np.shape(self.aperture_mask) != shape:
                raise ShapeError(f"aperture_mask has shape {np.shape(self.aperture_mask)}, "
                                 f"the camera grid is {shape}; build it on that grid.")
            check_finite("aperture_mask", self.aperture_mask)
        else:
            check_positive("aperture_radius", self.aperture_radius, "m")
            if is_concrete(self.aperture_radius, self.dx):
                half = min(shape) // 2 * float(self.dx)
                if float(self.aperture_radius) > half:
                    raise DiffcamError(
                        f"aperture radius {fmt_length(float(self.aperture_radius))} is larger "
                        f"than the grid's half-width {fmt_length(half)}; use more samples "
                        f"(shape) or a larger pitch dx.")

    @property
    def out_shape(self) -> tuple[int, int]:
        """``(ny, nx)`` of the PSF this camera returns."""
        return tuple(self.crop) if self.crop is not None else tuple(self.shape)

    @property
    def padded_shape(self) -> tuple[int, int]:
        """``(ny, nx)`` of the propagation grid (``shape`` plus ``pad`` per side)."""
        return self.shape[0] + 2 * self.pad[0], self.shape[1] + 2 * self.pad[1]

    def aperture(self) -> Float[Array, "ny nx"]:
        """The aperture transmission C on the camera grid (paper Eq. 4)."""
        if self.aperture_mask is not None:
            return self.aperture_mask
        return circular_aperture(self.shape, self.dx, self.aperture_radius, edge=self.edge)

    def support_radius(self) -> float:
        """Largest distance from the axis at which the aperture transmits, metres."""
        if self.aperture_mask is None:
            return float(self.aperture_radius)
        ny, nx = self.shape
        yy, xx = np.nonzero(np.asarray(self.aperture_mask))
        if yy.size == 0:
            return 0.0
        r = np.hypot(yy - ny // 2, xx - nx // 2).max() + 0.5
        return float(r * float(self.dx))


class HeightMap(eqx.Module):
    """A thin diffuser described by its surface height: θd(λ) = 2π(n − 1)·h/λ.

    Attributes:
        height: surface height h on the camera grid, metres.
        refractive_index: n of the diffuser material (dispersion-free), unitless.
    """

    height: Float[Array, "ny nx"] = eqx.field(converter=jnp.asarray)
    refractive_index: Float[Array, ""] = eqx.field(converter=_scalar)

    def __check_init__(self):
        check_field(self.height, "height")
        check_positive("refractive_index", self.refractive_index, "")

    def phase(self, wavelength) -> Float[Array, "ny nx"]:
        """θd at ``wavelength`` (metres), radians."""
        return 2 * jnp.pi * (self.refractive_index - 1) * self.height / wavelength


class Spectrum(NamedTuple):
    """Broadband light: ``wavelengths`` (metres) and relative power ``weights`` (≥ 0)."""

    wavelengths: Float[Array, " n"]
    weights: Float[Array, " n"]


def diffuser_phase(diffuser, wavelength, reference_wavelength) -> Float[Array, "ny nx"]:
    """θd at ``wavelength`` (m) from a :class:`HeightMap` or a phase array (radians).

    A phase array is taken as given at ``reference_wavelength`` (m) and scaled by
    reference_wavelength/wavelength: a dispersion-free thin element.
    """
    if isinstance(diffuser, HeightMap):
        return diffuser.phase(wavelength)
    return jnp.asarray(diffuser) * (reference_wavelength / wavelength)


def random_diffuser(key: Array, shape, dx, wavelength, feature_size=30e-6,
                    deflection=np.deg2rad(1.0)) -> Float[Array, "ny nx"]:
    """A random-phase diffuser like the paper's Fig. 6 (radians at ``wavelength``).

    Gaussian-correlated noise whose Gaussian kernel has a 1/e² diameter of
    ``feature_size`` (m), scaled so the r.m.s. deflection λ|∇θ|/(2π) is
    sin(``deflection``) (radians). ``dx`` and ``wavelength`` in metres.
    """
    check_positive("feature_size", feature_size, "m")
    check_positive("deflection", deflection, "rad")
    ny, nx = shape
    noise = jax.random.normal(key, (ny, nx))
    sigma = feature_size / 4 / dx  # 1/e² radius = 2σ, in samples
    fy, fx = jnp.fft.fftfreq(ny)[:, None], jnp.fft.fftfreq(nx)[None, :]
    lowpass = jnp.exp(-2 * (jnp.pi * sigma) ** 2 * (fy ** 2 + fx ** 2))
    theta = jnp.fft.ifft2(jnp.fft.fft2(noise) * lowpass).real
    gy, gx = jnp.gradient(theta, dx)
    slope = jnp.sqrt(jnp.mean(gy ** 2 + gx ** 2))
    return theta * (2 * jnp.pi * jnp.sin(deflection) / wavelength / slope)


def _as_spectrum(spectrum, camera):
    """(wavelengths, weights) arrays, validated; the camera's wavelength if ``None``."""
    if spectrum is None:
        return jnp.reshape(camera.wavelength, (1,)), jnp.ones((1,), camera.wavelength.dtype)
    wl, w = (jnp.atleast_1d(jnp.asarray(a)) for a in spectrum)
    if wl.ndim != 1 or wl.shape != w.shape or wl.size == 0:
        raise ShapeError(f"spectrum needs two 1-D arrays of equal, non-zero length "
                         f"(wavelengths in m, weights); got shapes {wl.shape}, {w.shape}.")
    check_positive("spectrum wavelengths", wl, "m")
    check_positive("spectrum weights", w, "relative power", allow_zero=True)
    if is_concrete(w) and float(np.sum(np.asarray(w))) <= 0:
        raise DiffcamError("spectrum weights sum to zero; give at least one positive weight.")
    return wl, w


# ------------------------------------------------------------------------------ cores

def _base_fields(phase, camera, wavelengths):
    """C·e^{jθd(λ)} on the padded grid, one per wavelength: (nλ, ny, nx) complex."""
    aperture = camera.aperture()
    thetas = jax.vmap(lambda lam: diffuser_phase(phase, lam, camera.wavelength))(wavelengths)
    base = aperture * jnp.exp(1j * thetas)
    return pad_to(base, camera.padded_shape)


def _tf(camera, wavelength, z):
    return transfer_function(camera.padded_shape, camera.dx, wavelength, z, "fresnel_tf")


def _source_field(base, camera, wavelength, z1, x1, y1):
    """base · U1: the field behind the diffuser for a point source at (x1, y1, z1)
    (the spherical wave's 1/(λz1) is applied to the intensity)."""
    ny, nx = base.shape[-2:]
    cy = spherical_chirp(ny, camera.dx, wavelength, z1, y1)[:, None]
    cx = spherical_chirp(nx, camera.dx, wavelength, z1, x1)[None, :]
    return base * (cy * cx)


def _direct_intensity(fields, camera, wavelength, z1):
    """|P_z2{fields}|² on the crop (physical irradiance, unit point source), batched; and
    the arrays the two FFTs wrote, (field at the sensor, its spectrum), full grid."""
    h = _tf(camera, wavelength, camera.z2)
    spectrum = update_rows_for_fft(jnp.fft.fft2(fields), lambda b, s: b * h[s])
    field = jnp.fft.ifft2(spectrum)
    out = crop_to(field, camera.out_shape)
    return (out.real ** 2 + out.imag ** 2) / (wavelength * z1) ** 2, (field, spectrum)


def _magnified_spectrum(base_hat, camera, wavelength, z1):
    """Spectrum of the cubic B-spline coefficients of P_zeff{base}, z_eff = z1·z2/(z1 + z2):
    its inverse FFT is the field the scaling theorem magnifies.

    The spline prefilter is separable and rides on the transfer function for free.
    """
    z_eff = z1 * camera.z2 / (z1 + camera.z2)
    ny, nx = base_hat.shape[-2:]
    return base_hat * (_tf(camera, wavelength, z_eff) * (bspline_prefilter(ny)[:, None]
                                                         * bspline_prefilter(nx)[None, :]))


def _sample_magnified(field, camera, wavelength, z1, x1, y1):
    """Irradiance at the sensor-grid points from the z_eff field (scaling theorem)."""
    z2 = camera.z2
    mag = (z1 + z2) / z1
    ny, nx = field.shape[-2:]
    cy, cx = camera.out_shape
    shift = z2 / (z1 + z2) / camera.dx  # source offset → sample offset, per metre
    ty = (jnp.arange(cy) - cy // 2) / mag + y1 * shift + ny // 2
    tx = (jnp.arange(cx) - cx // 2) / mag + x1 * shift + nx // 2
    s = cubic_sample(cubic_sample(field, ty, -2), tx, -1) / (mag * wavelength * z1)
    return fusion_barrier(s.real ** 2 + s.imag ** 2, camera.dx)


def _normalised(intensity, normalise):
    if not normalise:
        return intensity
    return intensity / jnp.sum(intensity, axis=(-2, -1), keepdims=True)


def prepare(phase, camera, wavelengths):
    """What every depth shares: base fields (direct) or their FFTs (scaling), (nλ, ny, nx)."""
    base = _base_fields(phase, camera, wavelengths)
    return jnp.fft.fft2(base) if camera.method == "scaling" else base


def depth_inputs(prepared, camera, wavelengths, z1, positions):
    """What the FFTs of one depth start from, (nλ, n, ny, nx) complex: the source fields
    base·U1 (direct, n = npos) or the spectra of the z_eff fields (scaling, n = 1: the
    positions only move the sampling).

    ``positions`` is (npos, 2) of (x1, y1) in metres; ``prepared`` from :func:`prepare`.
    Computed apart from :func:`depth_outputs`: on CPU, an FFT that XLA schedules after
    an elementwise product of its own size runs about single-threaded (the FFT rule of
    :mod:`diffcam.xla_cpu`), so :mod:`diffcam.stack` and :func:`psf` run the two as
    separate jitted calls.
    """
    def per_wavelength(pre, lam):
        if camera.method == "scaling":
            return _magnified_spectrum(pre, camera, lam, z1)[None]
        return jax.vmap(lambda p: _source_field(pre, camera, lam, z1, p[0], p[1]))(positions)
    return jax.vmap(per_wavelength)(prepared, wavelengths)


def depth_outputs(inputs, camera, wavelengths, weights, z1, positions, normalise,
                  buffers=False):
    """PSFs at one depth, (npos, ny, nx) on the crop, from :func:`depth_inputs`: the
    FFTs, the intensities, normalisation and the weighted mean over wavelengths.

    With ``buffers=True`` also returns two arrays shaped like ``inputs`` that hold what
    the FFTs wrote (direct: the sensor field and its spectrum; scaling: ``inputs``
    itself and the z_eff field), for a caller that donates them back as the next
    depth's buffers instead of page-faulting fresh ones (:mod:`diffcam.stack`); the
    first can hold the next :func:`depth_inputs`.
    """
    def per_wavelength(u, lam):
        if camera.method == "scaling":
            field = jnp.fft.ifft2(u[0])
            psfs = jax.vmap(lambda p: _sample_magnified(field, camera, lam, z1, p[0], p[1])
                            )(positions)
            written = (u, field[None])
        else:
            psfs, written = _direct_intensity(u, camera, lam, z1)
        return _normalised(psfs, normalise), written
    psfs, written = jax.vmap(per_wavelength)(inputs, wavelengths)
    psfs = jnp.tensordot(weights, psfs, axes=1) / jnp.sum(weights)
    return (psfs, written) if buffers else psfs


@jax.jit
def _psf_inputs(phase, camera, wavelengths, z1, positions):
    return depth_inputs(prepare(phase, camera, wavelengths), camera, wavelengths, z1,
                        positions)


@partial(jax.jit, static_argnames=("normalise",))
def _psf_outputs(inputs, camera, wavelengths, weights, z1, positions, normalise):
    return depth_outputs(inputs, camera, wavelengths, weights, z1, positions, normalise)[0]


# ------------------------------------------------------------------------- validation

def check_inputs(phase, camera, z1, offsets, wavelengths, accept_undersampling):
    """Concrete checks before tracing: shapes, NaN, signs, and sampling at the extremes.

    ``z1`` and ``offsets`` (lateral distances |ρ1|, metres) may be arrays; the smallest
    z1 and largest offset are checked.
    """
    if not isinstance(camera, Camera):
        raise DiffcamError(f"camera must be a diffcam.camera.Camera, got {type(camera)}.")
    arr = phase.height if isinstance(phase, HeightMap) else phase
    what = "height map" if isinstance(phase, HeightMap) else "phase"
    if np.shape(arr) != tuple(camera.shape):
        raise ShapeError(f"diffuser {what} has shape {np.shape(arr)} but the camera grid is "
                         f"{tuple(camera.shape)}; embed it with diffcam.grid.pad_to or "
                         f"build the Camera with shape={np.shape(arr)[-2:]}.")
    check_finite(f"diffuser {what}", arr)
    check_positive("z1 (source distance)", z1, "m")
    if not is_concrete(z1, offsets, camera, wavelengths):
        return
    z_min = float(np.min(np.asarray(z1)))
    z_max = float(np.max(np.asarray(z1)))
    rho = float(np.max(np.abs(np.asarray(offsets)))) if np.size(offsets) else 0.0
    dx, z2 = float(camera.dx), float(camera.z2)
    for lam in np.atleast_1d(np.asarray(wavelengths, dtype=np.float64)):
        lam = float(lam)
        # transfer-function sampling of the longest propagation on the padded grid
        z_prop = z2 if camera.method == "direct" else z_max * z2 / (z_max + z2)
        zc = min(critical_distance(camera.padded_shape, dx, lam))
        if z_prop > zc:
            sampling_problem(
                f"the Fresnel transfer function for {fmt_length(z_prop)} aliases on this "
                f"grid (critical distance N·dx²/λ = {fmt_length(zc)}); increase Camera.pad "
                f"or the grid", accept_undersampling)
        if camera.method == "direct":
            radius = camera.support_radius()
            f_max = point_source_max_frequency(lam, z_min, radius, rho)
            nyquist = 1 / (2 * dx)
            if f_max > nyquist:
                sampling_problem(
                    f"point-source chirp is undersampled at the aperture edge for z1 = "
                    f"{fmt_length(z_min)}: local frequency {f_max / 1e3:.0f} cycles/mm > "
                    f"Nyquist {nyquist / 1e3:.0f} cycles/mm; use z1 ≥ "
                    f"{fmt_length(z_min * f_max / nyquist)}, dx ≤ "
                    f"{fmt_length(1 / (2 * f_max))}, or method='scaling' (the default), "
                    f"which never samples this chirp", accept_undersampling)


def psf(phase, camera: Camera, z1, x1=0.0, y1=0.0, *, spectrum=None, normalise: bool = True,
        accept_undersampling: bool = False) -> Float[Array, "ny nx"]:
    """The camera's PSF for a point source at ``(x1, y1, z1)`` (paper Eq. 7).

    Args:
        phase: the diffuser: its phase θd on the camera grid (radians, at
            ``camera.wavelength``), or a :class:`HeightMap`.
        camera: the :class:`Camera` (its ``method`` picks scaling theorem or direct).
        z1: source-to-aperture distance, metres (> 0).
        x1, y1: lateral source position, metres; the PSF moves by −(x1, y1)·z2/z1.
        spectrum: ``(wavelengths, weights)`` (metres, relative power) for broadband
            light: the weight-averaged PSF; ``None`` is monochromatic at
            ``camera.wavelength``.
        normalise: unit sum over the returned crop (default); ``False`` returns the
            physical irradiance of a unit point source (1/M² of the scaling theorem
            and 1/(λz1)² of the source included), per m² of sensor.
        accept_undersampling: turn sampling errors into warnings.

    Returns:
        ``camera.out_shape`` float array. Pure and jitted; differentiable in ``phase``,
        ``z1``, ``x1``, ``y1`` and the camera's traced fields.

    Raises:
        ShapeError: the phase does not match the camera grid.
        DiffcamError: z1 ≤ 0, NaN in the phase, bad spectrum.
        SamplingError: ``method="direct"`` with an undersampled source chirp, or a
            transfer function that aliases.
    """
    wavelengths, weights = _as_spectrum(spectrum, camera)
    check_inputs(phase, camera, z1, jnp.hypot(jnp.asarray(x1), jnp.asarray(y1)), wavelengths,
                 accept_undersampling)
    dtype = real_dtype(camera)
    wavelengths, weights, z1 = wavelengths.astype(dtype), weights.astype(dtype), \
        jnp.asarray(z1, dtype)
    positions = jnp.stack([jnp.asarray(x1, dtype), jnp.asarray(y1, dtype)])[None]
    inputs = _psf_inputs(phase, camera, wavelengths, z1, positions)
    return _psf_outputs(inputs, camera, wavelengths, weights, z1, positions, normalise)


def with_method(camera: Camera, method: str) -> Camera:
    """The same camera evaluated by ``method`` ("scaling" or "direct")."""
    return dataclasses.replace(camera, method=method)
