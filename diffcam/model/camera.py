"""The diffuser camera as data: fixed geometry and the physical numbers users fit.

- `Camera` — grid, padding, crop and method (static: they fix shapes and code
  paths) beside wavelength, z2, pitch and aperture (array leaves: differentiable,
  ``vmap``-able, changed without recompiling);
- `HeightMap` — a diffuser given by its surface height (θd scales with 1/λ);
- `Spectrum` — broadband light;
- `random_diffuser` — a random phase screen like the paper's Fig. 6.

The PSF these describe is `diffcam.model.point_spread.psf` (paper Eq. 7).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.backend import fft2, ifft2

from diffcam.core.errors import (DiffcamError, ShapeError, check_field, check_finite,
                                 check_positive, fmt_length, is_concrete)
from diffcam.core.grid import check_grid_size, int_pair
from diffcam.optics.elements import circular_aperture

__all__ = ["Camera", "HeightMap", "Spectrum", "as_spectrum", "diffuser_phase", "random_diffuser",
           "real_dtype", "with_method", "oversampled", "finer_diffuser", "METHODS"]

METHODS = ("scaling", "direct")
OFF_AXIS_TERMS = ("aperture_distance", "acceptance_exponent", "vignetting_exponent")
"""The Camera fields of the terms that change across the field (`diffcam.model.off_axis`)."""


def _scalar(x):
    """A strongly typed real scalar: float32, or float64 when given or when x64 is on.

    Text (``"532nm"``: units are read only on the command line), complex or non-numeric
    values are a DiffcamError here, before JAX sees them; the number of values is
    checked by ``Camera.__check_init__``."""
    if not isinstance(x, jax.core.Tracer):
        kind = np.asarray(x).dtype.kind if not isinstance(x, jax.Array) else x.dtype.kind
        if kind not in "biuf":
            raise DiffcamError(
                f"Camera lengths are numbers in metres (e.g. wavelength=532e-9), got "
                f"{x!r:.60}; units such as '532nm' are read only on the command line.")
    x = jnp.asarray(x)
    return x.astype(jnp.promote_types(x.dtype, jnp.float32))


def real_dtype(camera) -> jnp.dtype:
    """The real dtype the camera computes in (its pitch's)."""
    return jnp.promote_types(camera.dx.dtype, jnp.float32)


def _optional_array(x):
    return None if x is None else jnp.asarray(x)


def _optional_scalar(x):
    return None if x is None else _scalar(x)


class Camera(eqx.Module):
    """A diffuser camera: static geometry plus traced physical numbers.

    Static (hashable; changing one recompiles): ``shape``, ``pad``, ``crop``, ``method``,
    ``edge``. Traced (array leaves: differentiable, ``vmap``-able, new values reuse the
    compiled code): ``wavelength``, ``z2``, ``dx``, ``aperture_radius`` or
    ``aperture_mask``, and the off-axis terms ``aperture_distance``,
    ``acceptance_exponent`` and ``vignetting_exponent`` (`diffcam.model.off_axis`; each
    ``None``, the default, leaves it out). Change a field with
    ``dataclasses.replace(camera, z2=2e-3)`` (which re-validates) or ``eqx.tree_at``
    (which does not, for use under transforms).

    Attributes:
        wavelength: metres (the wavelength a phase-array diffuser is given at).
        z2: diffuser-to-sensor distance, metres (> 0).
        dx: sample pitch of the diffuser and sensor grids, metres per sample.
        aperture_radius: radius of the circular aperture centred on the axis, metres;
            or ``None`` when ``aperture_mask`` is given.
        aperture_mask: transmission of the aperture on the ``shape`` grid (0…1); or
            ``None`` for the circular aperture.
        shape: ``(ny, nx)`` samples of the diffuser grid.
        pad: zero samples added per side before propagating (int or ``(py, px)``);
            the padded grid holds at most ``diffcam.core.grid.MAX_GRID_SAMPLES``.
        crop: ``(ny, nx)`` of the returned PSF, centred (default: ``shape``).
        method: ``"scaling"`` (Fresnel scaling theorem, default) or ``"direct"``.
        edge: ``"hard"`` (as in the paper) or ``"soft"`` (one-pixel ramp,
            differentiable in ``aperture_radius``) circular-aperture edge.
        aperture_distance: distance d of the circular aperture (the stop) in front of the
            diffuser, metres (≥ 0); its shadow on the diffuser moves with the source.
            ``None``: the aperture lies on the diffuser.
        acceptance_exponent: p of the sensor's angular response: a pixel records the
            fraction cos^p θ of the power of a plane wave at incidence θ (≥ 0, unitless).
        vignetting_exponent: n of the irradiance's fall-off cos^n of the source's field
            angle (≥ 0, unitless; 4 is the classic cos⁴ law). Only an unnormalised PSF
            shows it.
    """

    wavelength: Float[Array, ""] = eqx.field(converter=_scalar)
    z2: Float[Array, ""] = eqx.field(converter=_scalar)
    dx: Float[Array, ""] = eqx.field(converter=_scalar)
    aperture_radius: Float[Array, ""] | None = eqx.field(default=None,
                                                         converter=_optional_array)
    aperture_mask: Float[Array, "ny nx"] | None = eqx.field(default=None,
                                                            converter=_optional_array)
    aperture_distance: Float[Array, ""] | None = eqx.field(default=None,
                                                           converter=_optional_scalar)
    acceptance_exponent: Float[Array, ""] | None = eqx.field(default=None,
                                                             converter=_optional_scalar)
    vignetting_exponent: Float[Array, ""] | None = eqx.field(default=None,
                                                             converter=_optional_scalar)
    shape: tuple[int, int] = eqx.field(default=(1024, 1024), static=True)
    pad: tuple[int, int] = eqx.field(default=(0, 0), static=True,
                                     converter=lambda v: int_pair(v, "pad"))
    crop: tuple[int, int] | None = eqx.field(default=None, static=True)
    method: str = eqx.field(default="scaling", static=True)
    edge: str = eqx.field(default="hard", static=True)

    def __check_init__(self):
        shape = int_pair(tuple(self.shape), "shape")
        if min(shape) <= 0:
            raise ShapeError(f"camera shape must be positive (ny, nx), got {self.shape}.")
        check_grid_size(shape, self.pad)
        if self.crop is not None:
            cy, cx = int_pair(tuple(self.crop), "crop")
            if not (0 < cy <= shape[0] and 0 < cx <= shape[1]):
                raise ShapeError(f"crop {self.crop} must be positive and fit in the grid "
                                 f"{shape}; crop to at most the camera shape.")
        if self.method not in METHODS:
            raise DiffcamError(f"method must be one of {METHODS}, got {self.method!r}.")
        if self.edge not in ("hard", "soft"):
            raise DiffcamError(f"edge must be 'hard' or 'soft', got {self.edge!r}.")
        for name in ("wavelength", "z2", "dx", "aperture_radius", *OFF_AXIS_TERMS):
            value = getattr(self, name)
            if value is not None and not isinstance(value, jax.core.Tracer) \
                    and np.ndim(value) != 0:
                raise DiffcamError(
                    f"Camera.{name} must be one number, got {np.size(value)} values; for "
                    f"broadband light pass psf(..., spectrum=(wavelengths, weights)), and "
                    f"for several cameras build one Camera each (or jax.vmap over one).")
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
            if self.aperture_distance is not None:
                raise DiffcamError("aperture_distance moves a circular aperture's shadow; "
                                   "give aperture_radius (metres) instead of a mask.")
        else:
            check_positive("aperture_radius", self.aperture_radius, "m")
            if is_concrete(self.aperture_radius, self.dx):
                half = min(shape) // 2 * float(self.dx)
                if float(self.aperture_radius) > half:
                    raise DiffcamError(
                        f"aperture radius {fmt_length(float(self.aperture_radius))} is larger "
                        f"than the grid's half-width {fmt_length(half)}; use more samples "
                        f"(shape) or a larger pitch dx.")

        for name, unit in zip(OFF_AXIS_TERMS, ("m", "", "")):
            if getattr(self, name) is not None:
                check_positive(name, getattr(self, name), unit, allow_zero=True)

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
    """θd at ``wavelength`` (m) from a `HeightMap` or a phase array (radians).

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
    theta = ifft2(fft2(noise) * lowpass).real
    gy, gx = jnp.gradient(theta, dx)
    slope = jnp.sqrt(jnp.mean(gy ** 2 + gx ** 2))
    return theta * (2 * jnp.pi * jnp.sin(deflection) / wavelength / slope)


def as_spectrum(spectrum, camera):
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


def with_method(camera: Camera, method: str) -> Camera:
    """The same camera evaluated by ``method`` ("scaling" or "direct")."""
    return dataclasses.replace(camera, method=method)


def oversampled(camera: Camera, factor: int) -> Camera:
    """``camera`` on a grid ``factor``× finer over the same field: pitch dx/factor, and
    shape, pad and PSF crop ``factor``× (a circular aperture is drawn on the finer
    grid). Bin its PSFs to ``camera``'s pixels with
    `diffcam.model.sensor.bin_pixels`."""
    k = int(factor)
    if k == factor == 1:
        return camera    # as it is, whatever its aperture
    if k != factor or k < 1 or camera.aperture_mask is not None:
        raise DiffcamError(f"oversampling needs a whole factor ≥ 1 and a circular aperture "
                           f"(aperture_radius), got factor {factor!r}"
                           f"{'' if camera.aperture_mask is None else ' and a mask'}.")
    return dataclasses.replace(camera, dx=camera.dx / k,
                               shape=tuple(k * n for n in camera.shape),
                               pad=tuple(k * n for n in camera.pad),
                               crop=tuple(k * n for n in camera.out_shape))


def finer_diffuser(diffuser, factor: int):
    """A `HeightMap` (heights) or a phase array cubic-interpolated onto a grid
    ``factor``× finer, the grid of `oversampled`: the surface is continuous, the model
    samples it at the camera's pitch. Differentiable; ``factor`` 1 returns it as it is."""
    if factor == 1:
        return diffuser

    def finer(values):
        ny, nx = np.shape(values)[-2:]
        return jax.image.resize(jnp.asarray(values), (ny * factor, nx * factor), "cubic")
    if isinstance(diffuser, HeightMap):
        return HeightMap(finer(diffuser.height), diffuser.refractive_index)
    return finer(diffuser)
