"""Diffuser surfaces a fabricator can make, as height maps in metres.

Two parametrisations, each an equinox module whose array leaves are what the optimiser
moves and whose static fields are the fabrication limits:

- `SmoothSurface` — a random-looking smooth surface: cubic B-spline coefficients on a
  coarse grid whose spacing is the minimum feature size s, squashed into the height range
  by a logistic function,

      h(x, y) = h_max · σ(Σ_kl c_kl β₃((y − Y_k)/s) β₃((x − X_l)/s)),   σ(u) = 1/(1 + e^{−u}),

  so 0 < h < h_max by construction and the surface has no detail finer than s (β₃'s
  spectrum is sinc⁴(f·s): zero at f = 1/s);
- `LensletArray` — a microlens array (Miniscope3D's kind): spherical caps of sag
  t_k ∈ (0, h_max) and aperture radius a_k ∈ [s/2, a_max] (the rim's slope ≈ 2t_k/a_k
  bounded too), at centres inside the clear
  aperture; radius of curvature R_k = (a_k² + t_k²)/(2 t_k), focal length
  f_k = R_k/(n − 1). Where caps overlap the higher one is the surface.

Either becomes a `diffcam.model.camera.HeightMap` (θd = 2π(n − 1)h/λ) through
`height_map`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.errors import DiffcamError, check_positive
from diffcam.core.grid import coord_at, int_pair, radius2
from diffcam.model.camera import HeightMap
from diffcam.model.spline import bspline

__all__ = ["SmoothSurface", "LensletArray", "Surface", "height_map", "spline_basis",
           "lenslet_table"]


def spline_basis(n: int, dx: float, feature_size: float) -> np.ndarray:
    """The cubic B-spline basis (n, m) that maps m coarse coefficients of spacing
    ``feature_size`` (m) onto n samples of pitch ``dx`` (m): the coarse knots cover the
    grid with one knot to spare on each side, centred like it."""
    m = int(np.ceil(n * dx / feature_size)) + 3
    knots = (np.arange(m) - (m - 1) / 2) * feature_size
    return bspline((coord_at(np.arange(n), n, dx)[:, None] - knots[None, :]) / feature_size)


class SmoothSurface(eqx.Module):
    """A smooth random surface with height range (0, ``height_max``) and minimum feature
    size ``feature_size``.

    Attributes:
        coefficients: B-spline coefficients on the coarse grid (my, mx), unitless
            (before the logistic squash).
        shape: ``(ny, nx)`` samples of the diffuser grid.
        dx: grid pitch, metres per sample.
        feature_size: spacing of the coarse grid (the minimum feature size), metres.
        height_max: the largest height the fabricator can make, metres.
    """

    coefficients: Float[Array, "my mx"]
    shape: tuple[int, int] = eqx.field(static=True)
    dx: float = eqx.field(static=True)
    feature_size: float = eqx.field(static=True)
    height_max: float = eqx.field(static=True)

    @eqx.filter_jit
    def height(self) -> Float[Array, "ny nx"]:
        """h on the diffuser grid, metres, in (0, ``height_max``)."""
        by = spline_basis(self.shape[0], self.dx, self.feature_size)
        bx = spline_basis(self.shape[1], self.dx, self.feature_size)
        c = self.coefficients
        u = jnp.asarray(by, c.dtype) @ c @ jnp.asarray(bx.T, c.dtype)
        return self.height_max * jax.nn.sigmoid(u)

    @staticmethod
    def random(key: Array, shape, dx: float, feature_size: float,
               height_max: float, spread: float = 2.0) -> "SmoothSurface":
        """A random start: independent normal coefficients of standard deviation
        ``spread`` (unitless; 2 spreads the heights over the whole range). ``key`` is a
        ``jax.random`` key or an int seed; ``dx``, ``feature_size`` and ``height_max``
        in metres."""
        shape = _check_limits(shape, dx, feature_size, height_max)
        key = _key(key)
        my = spline_basis(shape[0], dx, feature_size).shape[1]
        mx = spline_basis(shape[1], dx, feature_size).shape[1]
        return SmoothSurface(spread * jax.random.normal(key, (my, mx)), shape, float(dx),
                             float(feature_size), float(height_max))


class LensletArray(eqx.Module):
    """Spherical microlenses on a flat substrate, heights in (0, ``height_max``).

    Each lens has three unconstrained parameters per row of ``params`` (k, 4): its centre
    (two values: the centre lies within ``region`` of the axis, by a tanh), its sag (a
    logit: t = t_max·σ, t_max = min(height_max, slope_max·a/2)) and its aperture radius
    (a logit: a = a_min + (a_max − a_min)·σ, a_min = feature_size/2).

    Attributes:
        params: (k, 4) unconstrained lens parameters (y, x, sag, aperture logits).
        shape: ``(ny, nx)`` samples of the diffuser grid.
        dx: grid pitch, metres per sample.
        feature_size: the smallest lens diameter, metres.
        height_max: the largest sag, metres.
        aperture_max: the largest lens aperture radius, metres.
        region: lens centres lie within ±region of the axis in y and x, metres.
        slope_max: the steepest surface slope (at a cap's rim, ≈ 2t/a), unitless: it
            bounds the sag of small lenses (and the phase's bandwidth).
    """

    params: Float[Array, "k 4"]
    shape: tuple[int, int] = eqx.field(static=True)
    dx: float = eqx.field(static=True)
    feature_size: float = eqx.field(static=True)
    height_max: float = eqx.field(static=True)
    aperture_max: float = eqx.field(static=True)
    region: float = eqx.field(static=True)
    slope_max: float = eqx.field(static=True, default=0.1)

    def lenses(self) -> tuple[Array, Array, Array, Array]:
        """(y, x, sag, aperture radius) of every lens, each (k,), metres."""
        p = self.params
        centre = self.region * jnp.tanh(p[:, :2])
        a_min = self.feature_size / 2
        aperture = a_min + (self.aperture_max - a_min) * jax.nn.sigmoid(p[:, 3])
        sag_max = jnp.minimum(self.height_max, self.slope_max * aperture / 2)
        sag = sag_max * jax.nn.sigmoid(p[:, 2])
        return centre[:, 0], centre[:, 1], sag, aperture

    @eqx.filter_jit
    def height(self) -> Float[Array, "ny nx"]:
        """h on the diffuser grid, metres: the highest cap at each point (0 outside
        every lens)."""
        y, x, sag, a = self.lenses()
        radius = (a ** 2 + sag ** 2) / (2 * sag)
        dx = jnp.asarray(self.dx, self.params.dtype)

        def cap(yk, xk, tk, ak, rk):
            r2 = radius2(self.shape, dx, centre=(yk, xk))
            inside = r2 < ak ** 2
            # safe where: the square root's argument stays positive outside the cap
            h = jnp.sqrt(jnp.where(inside, rk ** 2 - r2, rk ** 2)) - (rk - tk)
            return jnp.where(inside, h, 0.0)
        return jnp.max(jax.vmap(cap)(y, x, sag, a, radius), axis=0)

    @staticmethod
    def random(key: Array, shape, dx: float, feature_size: float, height_max: float,
               count: int, region: float, regular: bool = False) -> "LensletArray":
        """``count`` lenses with random centres within ±``region`` (m), sags and
        apertures; ``regular`` puts them on a square lattice instead, all alike (the
        baseline a regular microlens array gives). ``key`` is a ``jax.random`` key or an
        int seed; lengths in metres."""
        shape = _check_limits(shape, dx, feature_size, height_max)
        key = _key(key)
        check_positive("region", region, "m")
        if not isinstance(count, (int, np.integer)) or count < 1:
            raise DiffcamError(f"count must be a positive number of lenses, got {count!r}.")
        side = int(np.ceil(np.sqrt(count)))
        aperture_max = max(region / side, feature_size)
        kc, ks, ka = jax.random.split(key, 3)
        if regular:
            lattice = (np.arange(side) + 0.5) / side * 2 - 1
            yy, xx = np.meshgrid(lattice, lattice, indexing="ij")
            centre = np.arctanh(np.stack([yy.ravel(), xx.ravel()], -1)[:count] * 0.999)
            shape_logits = np.zeros((count, 2))
            params = jnp.asarray(np.concatenate([centre, shape_logits], -1), jnp.float32)
        else:
            centre = jax.random.uniform(kc, (count, 2), minval=-1.5, maxval=1.5)
            sag = jax.random.normal(ks, (count, 1))
            aperture = jax.random.normal(ka, (count, 1))
            params = jnp.concatenate([centre, sag, aperture], -1)
        return LensletArray(params, shape, float(dx), float(feature_size), float(height_max),
                            float(aperture_max), float(region))


Surface = SmoothSurface | LensletArray
"""The parametrisations `design` optimises."""


def height_map(surface: Surface, refractive_index) -> HeightMap:
    """The `diffcam.model.camera.HeightMap` of ``surface`` with refractive index
    ``refractive_index`` (unitless): what `diffcam.model.point_spread.psf` takes."""
    return HeightMap(surface.height(), refractive_index)


def lenslet_table(surface: LensletArray, refractive_index: float) -> dict[str, list]:
    """The lenses as a fabricator's table: centres, sags, aperture radii, radii of
    curvature and focal lengths f = R/(n − 1), each a list in metres."""
    y, x, sag, a = (np.asarray(v, np.float64) for v in surface.lenses())
    radius = (a ** 2 + sag ** 2) / (2 * sag)
    return {"y": y.tolist(), "x": x.tolist(), "sag": sag.tolist(),
            "aperture_radius": a.tolist(), "radius_of_curvature": radius.tolist(),
            "focal_length": (radius / (refractive_index - 1)).tolist()}


def _key(key) -> Array:
    """A ``jax.random`` key from a key or an int seed."""
    return jax.random.key(key) if isinstance(key, (int, np.integer)) else key


def _check_limits(shape, dx, feature_size, height_max) -> tuple[int, int]:
    """The grid and fabrication limits, checked: a feature spans at least two samples."""
    shape = int_pair(tuple(shape) if np.ndim(shape) else shape, "shape")
    if min(shape) < 2:
        raise DiffcamError(f"shape must be at least 2×2 samples, got {shape}.")
    for name, value in (("dx", dx), ("feature_size", feature_size),
                        ("height_max", height_max)):
        check_positive(name, value, "m")
    if feature_size < 2 * dx:
        raise DiffcamError(f"feature_size {feature_size:.3g} m is below two samples of the "
                           f"grid (dx = {dx:.3g} m); use a finer grid or larger features.")
    return shape
