"""The wave model of a measured PSF stack: one band-limited diffuser-side field, seen
by every plane through the Fresnel scaling theorem (`StackModel`).

All lengths are in **pixels** and plane indices, since a real stack rarely records its
pitch or depths:

* one complex diffuser-side field g on a grid ``oversample`` (2) times finer than the
  sensor pixel of a virtual plane between the given ones (magnification
  m0 = √(s_min·s_max) relative to the reference), so every given plane is rendered
  through the same resampling. g is band-limited: a cubic B-spline with one complex
  coefficient every ``stride`` (2) fine samples, i.e. one per pixel (sampled by
  `diffcam.model.spline.spline_sample`), times a fixed raised-cosine taper at the
  grid edge (no energy can wrap around the FFT);
* plane t sees g propagated (Fresnel transfer function) by ζ(t) = ζ_ref·s(t)^(−κ) and
  magnified by s(t) = M(t)/M(ref) about a fitted centre, M linear in the plane index.
  κ = 1 is the Fresnel scaling theorem: a point at z1 is imaged with magnification
  M = 1 + z2/z1 from the effective distance z_eff = z1·z2/(z1 + z2) = z2/M. κ = 0 is
  the frozen-distance ablation;
* |·|², a Gaussian blur of σ fine samples (the source's size and bandwidth),
  ``oversample``×``oversample`` binning to pixels.

Forward, per plane: G = FFT(g) once; u_t = IFFT(G·e^{−jπζ(t)(fx² + fy²)}) (f in cycles
per fine sample, so ζ is in fine samples²: ζ = λ·z_eff/dx_fine²); u_t sampled at the
fine sensor grid magnified by s(t)/m0 by the engine's separable cubic B-spline
(`spline_sample`, its prefilter folded into the transfer
function, zero outside), as the scaling-theorem PSF samples its field; |·|²; blur (FFT,
zero-padded); bin.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.backend import fft2, ifft2, irfft2, rfft2
from diffcam.evaluate.registration import relative_magnification_at
from diffcam.model.sensor import bspline_prefilter
from diffcam.model.spline import spline_sample
from diffcam.optics.propagation import fresnel_number_factors

__all__ = ["StackModel", "render_planes", "identifiable", "coefficients_of",
           "coefficient_shape", "edge_taper", "fresnel_kernel"]


def edge_taper(n: int, pad: int) -> np.ndarray:
    """1 inside, a raised cosine to 0 over the outer ``pad // 2`` samples (≥ 2)."""
    x = np.ones(n)
    r = max(pad // 2, 2)
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(r) / r)
    x[:r] = ramp
    x[n - r:] = ramp[::-1]
    x[:2] = 0
    x[-2:] = 0
    return x


def _gauss_blur(img, sigma, margin: int = 8):
    """Gaussian blur of std ``sigma`` samples by FFT on a grid zero-padded by
    ``margin`` (nothing wraps around)."""
    p = jnp.pad(img, margin)
    fy = np.fft.fftfreq(p.shape[0])[:, None]
    fx = np.fft.rfftfreq(p.shape[1])[None, :]
    f2 = jnp.asarray((fy ** 2 + fx ** 2).astype(np.float32))
    out = irfft2(rfft2(p) * jnp.exp(-2 * np.pi ** 2 * sigma ** 2 * f2), s=p.shape)
    return out[margin:-margin, margin:-margin]


def fresnel_kernel(grid, zeta):
    """The Fresnel transfer function over ζ = λz/dx² (fine samples²) on the field grid."""
    hy, hx = fresnel_number_factors(grid, zeta)
    return hy * hx


def spline_kernel(grid, zeta):
    """`fresnel_kernel` times the cubic B-spline prefilter: its product with the
    field's spectrum has as inverse FFT the spline coefficients of the propagated field,
    which `spline_sample` then samples anywhere (the scaling
    theorem's path in `diffcam.model.point_spread`)."""
    hy, hx = fresnel_number_factors(grid, zeta)
    by, bx = bspline_prefilter(grid[0])[:, None], bspline_prefilter(grid[1])[None, :]
    return (hy * by) * (hx * bx)


class StackModel(eqx.Module):
    """The wave model of a PSF stack (see the module docstring), as a pytree.

    Array leaves (fitted): ``field_real``, ``field_imag`` the cubic B-spline coefficients
    of the diffuser-side field g, one per ``stride`` fine samples; ``log_zeta`` log ζ_ref
    (ζ in fine samples²); ``log_s`` log M(anchor)/M(reference); ``centre`` the
    magnification centre (y, x), pixels; ``log_sigma`` log of the blur's std, fine
    samples; ``kappa`` the depth-law exponent ζ(t) = ζ_ref·s(t)^(−κ) (1: the Fresnel
    scaling theorem, z_eff = z2/M).

    Static fields (hashable: changing one recompiles): ``frame`` (H, W) pixels, ``pad``
    fine samples added before the frame on each axis, ``grid`` (ny, nx) the fine field
    grid, ``stride`` fine samples per field coefficient, ``reference`` and ``anchor``
    plane indices (the magnification law runs through them), ``oversample`` fine
    samples per pixel, ``frozen`` (κ ≡ 0: the frozen-distance ablation),
    ``grid_magnification`` m0: the field grid is the fine sensor grid of a virtual plane
    at s = m0.

    Field sample n ↔ pixel coordinate (n − pad − (o − 1)/2)/o of that virtual plane,
    o = ``oversample`` (pixel k's centre at k); plane t sees it magnified by s(t)/m0
    about ``centre``.
    """

    field_real: Float[Array, "cy cx"]
    field_imag: Float[Array, "cy cx"]
    log_zeta: Float[Array, ""]
    log_s: Float[Array, ""]
    centre: Float[Array, "2"]
    log_sigma: Float[Array, ""]
    kappa: Float[Array, ""]
    frame: tuple[int, int] = eqx.field(static=True)
    pad: int = eqx.field(static=True)
    grid: tuple[int, int] = eqx.field(static=True)
    stride: int = eqx.field(static=True)
    reference: int = eqx.field(static=True)
    anchor: int = eqx.field(static=True)
    oversample: int = eqx.field(static=True, default=2)
    frozen: bool = eqx.field(static=True, default=False)
    grid_magnification: float = eqx.field(static=True, default=1.0)

    # -- geometry
    def magnification(self, t) -> Array:
        """s(t) = M(t)/M(reference), dimensionless (``t`` plane indices)."""
        return relative_magnification_at(jnp.asarray(t, jnp.float32), jnp.exp(self.log_s),
                                         self.reference, self.anchor)

    def distance(self, t) -> Array:
        """ζ(t) = λ·z_eff(t)/dx_fine², fine samples² (ζ_ref·s(t)^(−κ); κ = 0 if frozen)."""
        kappa = 0.0 if self.frozen else self.kappa
        return jnp.exp(self.log_zeta) * self.magnification(t) ** (-kappa)

    def field(self) -> Array:
        """g on the fine grid: the cubic B-spline of the coefficients (band-limited at one
        coefficient per ``stride`` samples) times the edge taper."""
        taper = np.outer(edge_taper(self.grid[0], self.pad), edge_taper(self.grid[1], self.pad))
        ty, tx = coefficient_points(self.grid, self.stride)
        c = self.field_real + 1j * self.field_imag
        g = spline_sample(spline_sample(c, ty, -2), tx, -1)
        return g * jnp.asarray(taper, jnp.float32)

    def spectrum(self) -> Array:
        """FFT of the field g (shared by all planes)."""
        return fft2(self.field())

    def _sample(self, u, s):
        """Spline coefficients ``u`` on the field grid → the field on the fine sensor grid
        of a plane at s (magnified by s/m0 relative to the field grid; zero outside)."""
        o, (h, w) = self.oversample, self.frame
        half = (o - 1) / 2.0
        ay = (jnp.arange(o * h) - half) / o
        ax = (jnp.arange(o * w) - half) / o
        cy, cx = self.centre[0], self.centre[1]
        s = s / self.grid_magnification
        qy = o * (cy + (ay - cy) / s) + half + self.pad
        qx = o * (cx + (ax - cx) / s) + half + self.pad
        return spline_sample(spline_sample(u, qy, -2), qx, -1)

    def render_plane(self, spec, t) -> Float[Array, "h w"]:
        """Pixel image of plane ``t`` (arbitrary gain) from ``spec`` =
        [`spectrum`][diffcam.calibrate.stack.model.StackModel.spectrum]."""
        o, (h, w) = self.oversample, self.frame
        u = ifft2(spec * spline_kernel(self.grid, self.distance(t)))
        v = self._sample(u, self.magnification(t))
        inten = jnp.real(v) ** 2 + jnp.imag(v) ** 2
        inten = _gauss_blur(inten, jnp.exp(self.log_sigma))
        return inten.reshape(h, o, w, o).mean(axis=(1, 3))

    def render(self, planes) -> Float[Array, "k h w"]:
        """Pixel images of ``planes`` (plane indices, any real values), arbitrary gain;
        one plane at a time (bounded memory)."""
        spec = self.spectrum()
        return jax.lax.map(lambda t: self.render_plane(spec, t),
                           jnp.asarray(planes, jnp.float32).reshape(-1))

    @property
    def zeta_pixels(self) -> float:
        """ζ_ref in pixel units, λ·z_eff/pixel² (dimensionless)."""
        return float(np.exp(float(self.log_zeta))) / self.oversample ** 2


# ------------------------------------------------------------------- field basis

def coefficient_shape(grid, stride: int) -> tuple[int, int]:
    """Field coefficients per axis: one every ``stride`` fine samples, one more before
    the grid and two after (the cubic's support)."""
    return tuple(-(-n // stride) + 3 for n in grid)


def coefficient_points(grid, stride: int):
    """Where the fine samples fall on the coefficient grid (fractional indices)."""
    return tuple(jnp.asarray(np.arange(n) / stride + 1.0, jnp.float32) for n in grid)


@partial(jax.jit, static_argnums=(1, 2, 3))
def coefficients_of(g, grid, stride: int, iterations: int = 40):
    """Least-squares spline coefficients of the fine field ``g`` (conjugate gradients on
    the normal equations; the sampling's transpose is its vjp)."""
    ty, tx = coefficient_points(grid, stride)

    def upsample(c):
        return spline_sample(spline_sample(c, ty, -2), tx, -1)

    _, transpose = jax.vjp(upsample, jnp.zeros(coefficient_shape(grid, stride), g.dtype))
    normal = lambda c: transpose(upsample(c))[0]  # noqa: E731
    return jax.scipy.sparse.linalg.cg(normal, transpose(g)[0], maxiter=iterations)[0]


# --------------------------------------------------------------------------- render

CHUNK = 4     # planes per call of the compiled renderer


@eqx.filter_jit
def _render_chunk(model: StackModel, planes):
    return model.render(planes)


def render_planes(model: StackModel, planes) -> np.ndarray:
    """Rendered ``planes`` (float64, arbitrary gain), ``CHUNK`` planes per call: one
    compiled function per model geometry (compiled inside the fit) serves every
    prediction."""
    ts = np.asarray(planes, np.float32).reshape(-1)
    padded = np.concatenate([ts, np.full((-len(ts)) % CHUNK, ts[-1], np.float32)])
    out = [np.asarray(_render_chunk(model, jnp.asarray(padded[k:k + CHUNK])), np.float64)
           for k in range(0, len(padded), CHUNK)]
    return np.concatenate(out)[:len(ts)]


def identifiable(phys: dict, model: StackModel, n_planes: int | None,
                 light_magnification: float | None = None) -> dict:
    """What the planes fix, in physical units as far as ``phys`` allows.

    ζ_ref = λ·z_eff/d² with d the diffuser-side sample pitch, (pitch/o)/M_virtual; with
    z_eff = z2/M this is λ·z2·M(ref)·m0²/(pitch/o)²: the planes fix z2·M(t) =
    z2 + z2²/z1(t), not z2 and z1 apart (module docstring). Given z2 too,
    M(t) = z2·M(t)/z2 and z1(t) = z2/(M(t) − 1).

    ``light_magnification``, M(reference) from the given planes' light
    (`magnification_from_light`), fixes M(t) and
    z1(t)/z2 = 1/(M(t) − 1) over the stack without any physical input; with z2, z1(t).
    """
    zeta_px = model.zeta_pixels
    ident = {"zeta_reference_px2": zeta_px,
             "note": "the planes can fix at most ζ = λ·z2·M/pixel², i.e. z2·M(t) = z2 + "
                     "z2²/z1(t) given the pixel pitch and wavelength; z1 needs z2 as well. "
                     "Where the planes change little with the distance the fit ends near "
                     "its start (docs/stack_fit.md). The planes' light (inverse-square "
                     "law) fixes M(t) and z1(t)/z2 when one source power and exposure "
                     "served every plane."}
    pitch, lam, z2 = phys["pixel_pitch"], phys["wavelength"], phys["z2"]
    ends = [0, n_planes - 1] if n_planes else sorted({model.reference, model.anchor})
    s = [float(model.magnification(t)) for t in ends]
    if light_magnification is not None:
        ident["magnification_reference_from_light"] = light_magnification
        m = [light_magnification * v for v in s]
        ident["magnification_range_from_light"] = m
        ident["z1_over_z2_range_from_light"] = [1.0 / (v - 1.0) for v in m]
        if z2 is not None:
            ident["z1_range_from_light_m"] = [z2 / (v - 1.0) for v in m]
    if pitch is None:
        return ident
    m0 = model.grid_magnification
    ident["lambda_z2_M_reference_m2"] = zeta_px * pitch ** 2 / m0 ** 2
    if lam is None:
        return ident
    z2m_ref = ident["lambda_z2_M_reference_m2"] / lam
    ident["z2_M_reference_m"] = z2m_ref
    ident["z2_M_range_m"] = [z2m_ref * v for v in s]
    if z2 is not None:
        m = [z2m_ref * v / z2 for v in s]
        ident["magnification_range"] = m
        ident["z1_range_m"] = [z2 / (v - 1) if v > 1 else None for v in m]
    return ident


# ------------------------------------------------------------------------ entry point
