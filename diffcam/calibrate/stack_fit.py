"""Fit a wave model to a few measured planes of a PSF stack; predict every other plane.

A DiffuserCam PSF stack is a set of caustics of one diffuser for point sources at
depths equally spaced in 1/z1. Given a few of its planes (two or more), the model here
predicts the others better than the scaling baseline
(:func:`diffcam.evaluate.registration.scaling_baseline`), which magnifies the nearest
measured plane.

The model (:class:`StackModel`; all lengths in **pixels** and plane indices, since a
real stack rarely records its pitch or depths):

* one complex diffuser-side field g on a grid ``oversample`` (2) times finer than the
  sensor pixel of a virtual plane between the given ones (magnification
  m0 = √(s_min·s_max) relative to the reference), so every given plane is rendered
  through the same resampling. g is band-limited: a cubic B-spline with one complex
  coefficient every ``stride`` (2) fine samples, i.e. one per pixel (sampled by
  :func:`diffcam.model.spline.spline_sample`), times a fixed raised-cosine taper at the
  grid edge (no energy can wrap around the FFT);
* plane t sees g propagated (Fresnel transfer function) by ζ(t) = ζ_ref·s(t)^(−κ) and
  magnified by s(t) = M(t)/M(ref) about a fitted centre, M linear in the plane index
  (from the registered pair). κ = 1 is the Fresnel scaling theorem: a point at z1 is
  imaged with magnification M = 1 + z2/z1 from the effective distance
  z_eff = z1·z2/(z1 + z2) = z2/M, so the registered magnifications fix how the
  distance changes with depth and only ζ_ref is fitted. κ = 0 is the frozen-distance
  ablation;
* |·|², a Gaussian blur of σ fine samples (the source's size and bandwidth),
  ``oversample``×``oversample`` binning to pixels. Gain and offset are free: the loss
  is 1 − Pearson per plane.

Forward, per plane: G = FFT(g) once; u_t = IFFT(G·e^{−jπζ(t)(fx² + fy²)}) (f in cycles
per fine sample, so ζ is in fine samples²: ζ = λ·z_eff/dx_fine²); u_t sampled at the
fine sensor grid magnified by s(t)/m0 by separable Keys cubic convolution (zero
outside); |·|²; blur (FFT, zero-padded); bin.

Prediction (:meth:`StackFit.predict`) is the rendered plane plus the part of the
measured planes the model does not reproduce, carried along by the model's own
magnification law. For each given plane k, least squares gives raw_k = a_k·render(k) +
b_k + R_k; plane t is predicted as (Σ_k w_k a_k)·render(t) + Σ_k w_k·T_{k→t}(R_k), T
the magnification by s(t)/s(k) about the fitted centre (cubic B-splines, zero outside),
w_k linear in t between the two given planes that bracket t (1 at its own plane), and
the nearest given plane's weight 1 outside the given range
(:func:`diffcam.evaluate.registration.bracket_weights`). At a given plane this is the
measurement; elsewhere the model supplies the change between planes, the residual the
sub-pixel detail the per-sample phase cannot interpolate at unseen pixels.
``residual=False`` renders the model alone.

The fit (:func:`fit_stack`): register the reference plane (the first given one) with
the given plane farthest from it; for each candidate ζ_ref run Gerchberg–Saxton between
the given planes, take the least-squares spline coefficients of its field, and keep
the best start; then Adam with per-group step sizes on
Σ_k (1 − Pearson over the training pixels of plane k). A fraction of the pixels of every
given plane (fixed seed) is held out for validation; the parameters with the best
validation Pearson are kept, and the fit stops when validation has not improved for
``patience`` steps, at ``max_steps`` or at the time budget. Planes that are not given
never enter.

What is identifiable: ζ = λ·z_eff/dx² (and the magnification law, the centre, the
blur). z2 and the absolute magnification are not: under the Fresnel scaling theorem a
diffuser scaled by a, seen with magnification M·a from z2/a, gives the same PSFs at
every depth, so the planes fix z_eff(t) = z2/M(t) but not z2. With the pixel pitch the
result reports λ·z_eff; with the wavelength too, z_eff.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import warnings
from functools import partial
from pathlib import Path
from typing import Mapping, NamedTuple, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage as ndi
from jax import Array
from jaxtyping import Float

from diffcam.core.options import Options
from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.core.backend import fft2, ifft2, irfft2, rfft2, transfer_step
from diffcam.core.progress import new_bar
from diffcam.core.phasor import expj
from diffcam.model.spline import spline_sample
from diffcam.calibrate.projections import fit_amplitude
from diffcam.evaluate.metrics import pearson
from diffcam.optics.propagation import fresnel_tf_factors
from diffcam.evaluate.registration import (Registration, bracket_weights, magnify_about,
                                           register_magnification,
                                           relative_magnification_at)

__all__ = ["StackModel", "StackFitOptions", "StackFit", "StackFitWarning", "fit_stack",
           "load_stack_fit", "prepare_planes", "FORMAT", "FORMAT_VERSION"]

FORMAT = "diffcam-stack-fit"
FORMAT_VERSION = 3
_ARRAYS = ("field_real", "field_imag", "log_zeta", "log_s", "centre", "log_sigma", "kappa")


class StackFitWarning(UserWarning):
    """A stack fit that ended worse than the scaling baseline on its validation pixels."""


# ----------------------------------------------------------------------------- helpers

def _good_size(n: int) -> int:
    """Smallest m ≥ n whose prime factors are 2, 3, 5 and 7 (a fast FFT length)."""
    m = n
    while True:
        k = m
        for p in (2, 3, 5, 7):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def _taper(n: int, pad: int) -> np.ndarray:
    """1 inside, a raised cosine to 0 over the outer ``pad // 2`` samples (≥ 2)."""
    x = np.ones(n)
    r = max(pad // 2, 2)
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(r) / r)
    x[:r] = ramp
    x[n - r:] = ramp[::-1]
    x[:2] = 0
    x[-2:] = 0
    return x


def _keys_weights(u):
    """Keys cubic-convolution (a = −½) weights of taps −1, 0, 1, 2 at offset u ∈ [0, 1)."""
    a = -0.5

    def near(x):
        return (a + 2) * x ** 3 - (a + 3) * x ** 2 + 1

    def far(x):
        return a * x ** 3 - 5 * a * x ** 2 + 8 * a * x - 4 * a

    return jnp.stack([far(1 + u), near(u), near(1 - u), far(2 - u)])


def _interp_rows(f, q):
    """``f`` (n, m) sampled at fractional rows ``q`` (k,) → (k, m): cubic convolution,
    zero outside the grid; gathers whole rows (differentiable in ``q``)."""
    n = f.shape[0]
    q0 = jnp.floor(q)
    w = _keys_weights(q - q0)
    idx = q0.astype(jnp.int32)[None, :] + jnp.arange(-1, 3)[:, None]
    w = jnp.where((idx >= 0) & (idx < n), w, 0.0)
    rows = f[jnp.clip(idx, 0, n - 1)]
    return jnp.einsum("tk,tkm->km", w.astype(f.real.dtype), rows)


def _gauss_blur(img, sigma, margin: int = 8):
    """Gaussian blur of std ``sigma`` samples by FFT on a grid zero-padded by
    ``margin`` (nothing wraps around)."""
    p = jnp.pad(img, margin)
    fy = np.fft.fftfreq(p.shape[0])[:, None]
    fx = np.fft.rfftfreq(p.shape[1])[None, :]
    f2 = jnp.asarray((fy ** 2 + fx ** 2).astype(np.float32))
    out = irfft2(rfft2(p) * jnp.exp(-2 * np.pi ** 2 * sigma ** 2 * f2), s=p.shape)
    return out[margin:-margin, margin:-margin]


def _fresnel(grid, zeta):
    """The Fresnel transfer function over ζ = λz/dx² (fine samples²) on the field grid:
    in sample units (dx = λ = 1) the distance is ζ."""
    hy, hx = fresnel_tf_factors(grid, 1.0, 1.0, 1.0, zeta)
    return hy * hx


# ------------------------------------------------------------------------------- model

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
        taper = np.outer(_taper(self.grid[0], self.pad), _taper(self.grid[1], self.pad))
        ty, tx = _coefficient_points(self.grid, self.stride)
        c = self.field_real + 1j * self.field_imag
        g = spline_sample(spline_sample(c, ty, -2), tx, -1)
        return g * jnp.asarray(taper, jnp.float32)

    def spectrum(self) -> Array:
        """FFT of the field g (shared by all planes)."""
        return fft2(self.field())

    def _sample(self, u, s):
        """u on the field grid → the fine sensor grid of a plane at s (magnified by
        s/m0 relative to the field grid)."""
        o, (h, w) = self.oversample, self.frame
        half = (o - 1) / 2.0
        ay = (jnp.arange(o * h) - half) / o
        ax = (jnp.arange(o * w) - half) / o
        cy, cx = self.centre[0], self.centre[1]
        s = s / self.grid_magnification
        qy = o * (cy + (ay - cy) / s) + half + self.pad
        qx = o * (cx + (ax - cx) / s) + half + self.pad
        return _interp_rows(_interp_rows(u, qy).T, qx).T

    def render_plane(self, spec, t) -> Float[Array, "h w"]:
        """Pixel image of plane ``t`` (arbitrary gain) from ``spec`` = :meth:`spectrum`."""
        o, (h, w) = self.oversample, self.frame
        u = ifft2(spec * _fresnel(self.grid, self.distance(t)))
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


CHUNK = 4     # planes per call of the compiled renderer
MAX_PLANES = 4096
"""Most planes one :meth:`StackFit.predict` call returns (a 270×320 frame: 1.4 GB);
raise it for the session by assigning to this constant."""


def _check_count(n: int) -> None:
    if n < 1:
        raise DiffcamError(f"no planes to predict (asked for {n}).")
    if n > MAX_PLANES:
        raise DiffcamError(f"{n} planes asked for; one call predicts at most {MAX_PLANES} "
                           f"(diffcam.calibrate.stack_fit.MAX_PLANES): ask for fewer, or "
                           f"raise the limit.")


def _plane_index(t) -> int:
    """A plane index: an int (not a bool, not a fraction or a string)."""
    if isinstance(t, (bool, np.bool_)) or not isinstance(t, (int, np.integer)):
        raise DiffcamError(f"plane indices must be integers, got {t!r}.")
    return int(t)


@eqx.filter_jit
def _render_chunk(model: StackModel, planes):
    return model.render(planes)


def _render(model: StackModel, planes) -> np.ndarray:
    """Rendered ``planes`` (float64, arbitrary gain), ``CHUNK`` planes per call: one
    compiled function per model geometry (compiled inside the fit) serves every
    prediction."""
    ts = np.asarray(planes, np.float32).reshape(-1)
    padded = np.concatenate([ts, np.full((-len(ts)) % CHUNK, ts[-1], np.float32)])
    out = [np.asarray(_render_chunk(model, jnp.asarray(padded[k:k + CHUNK])), np.float64)
           for k in range(0, len(padded), CHUNK)]
    return np.concatenate(out)[:len(ts)]


# ----------------------------------------------------------------------------- options

class StackFitOptions(Options):
    """How :func:`fit_stack` runs. Lengths in fine samples (1/``oversample`` pixel).

    Attributes:
        max_steps: Adam steps at most.
        patience: stop after this many steps without a better validation Pearson.
        time_budget: wall-clock limit of the fit, s (registration, initialisation,
            compilation and steps; checked after every step, so a fit may end about one
            step later); ``math.inf`` for none.
        validation_fraction: share of each given plane's pixels held out (0 < f < 0.5).
        seed: the validation split's and the GS start's seed.
        zetas: candidate ζ_ref for the GS start, fine samples² (λ·z_eff/dx_fine²);
            the best start by training Pearson is kept.
        gs_iterations: Gerchberg–Saxton sweeps per candidate.
        oversample: fine samples per pixel (2: the prototype's).
        pad: fine samples of field grid beyond the frame on each side.
        field_stride: fine samples between field coefficients (the field is a cubic
            B-spline: band-limited at one coefficient per ``field_stride`` samples).
        kappa: the depth-law exponent κ, ζ(t) = ζ_ref·s(t)^(−κ): 1 is the Fresnel
            scaling theorem (z_eff = z2/M).
        fit_kappa: fit κ (else it stays at ``kappa``).
        frozen: κ ≡ 0 (the frozen-distance ablation).
        sigma: start of the blur std, fine samples.
        amplitude_blur: std of the blur of the reference plane that gives the starting
            amplitude envelope, fine samples.
        dark_ring: width of the frame-border ring whose median is the dark level
            (:func:`prepare_planes`), pixels.
        step_field, step_zeta, step_magnification, step_centre, step_blur, step_kappa:
            Adam step sizes of the field coefficients (of a field of unit mean
            intensity), log ζ, log s, centre (pixels), log σ and κ.
    """

    max_steps: int = 400
    patience: int = 40
    time_budget: float = 55.0
    validation_fraction: float = 0.1
    seed: int = 0
    zetas: tuple[float, ...] = eqx.field(
        default=(16.0,),
        converter=lambda z: tuple(float(v) for v in np.atleast_1d(z)))
    gs_iterations: int = 30
    oversample: int = 2
    pad: int = 40
    field_stride: int = 2
    kappa: float = 1.0
    fit_kappa: bool = False
    frozen: bool = False
    sigma: float = 1.0
    amplitude_blur: float = 6.0
    dark_ring: int = 6
    step_field: float = 0.02
    step_zeta: float = 0.003
    step_magnification: float = 2e-5
    step_centre: float = 0.02
    step_blur: float = 0.01
    step_kappa: float = 0.01

    def __check_init__(self):
        for name in ("max_steps", "patience", "oversample", "field_stride"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise DiffcamError(f"{name} must be a positive int, got {v!r}.")
        for name in ("gs_iterations", "pad", "dark_ring", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise DiffcamError(f"{name} must be an int ≥ 0, got {v!r}.")
        if not 0 < float(self.validation_fraction) < 0.5:
            raise DiffcamError(f"validation_fraction must be in (0, 0.5), got "
                               f"{self.validation_fraction!r}.")
        if not float(self.time_budget) > 0:
            raise DiffcamError(f"time_budget must be > 0 s, got {self.time_budget!r}.")
        zetas = tuple(self.zetas)
        if not zetas or not all(np.isfinite(float(z)) and float(z) > 0 for z in zetas):
            raise DiffcamError(f"zetas must be positive distances (fine samples²), got "
                               f"{self.zetas!r}.")
        for name in ("sigma", "amplitude_blur"):
            if not float(getattr(self, name)) > 0:
                raise DiffcamError(f"{name} must be > 0 fine samples, got "
                                   f"{getattr(self, name)!r}.")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name.startswith("step_") and not (0 <= float(v) < math.inf):
                raise DiffcamError(f"{f.name} must be a finite step ≥ 0, got {v!r}.")


    def to_dict(self) -> dict:
        return {f.name: (list(getattr(self, f.name)) if f.name == "zetas"
                         else getattr(self, f.name)) for f in dataclasses.fields(self)}


# ---------------------------------------------------------------------- preprocessing

def prepare_planes(images, ring: int = 6, *, labels: Sequence[int] | None = None
                   ) -> np.ndarray:
    """Dark-subtract and mean-normalise PSF planes (the fit's and the benchmark's
    preprocessing, applied to each plane on its own frame).

    The dark level of a plane is the median of a ``ring``-pixel band at the frame border
    (the caustic rarely reaches the border; the median ignores a few bright pixels);
    the plane is then divided by its mean, so every plane has unit mean.

    Args:
        images: (..., ny, nx) planes.
        ring: band width, pixels (0: no dark subtraction).
        labels: plane numbers used in error messages (default 0, 1, ...).

    Returns:
        float64 array of the same shape.
    """
    from diffcam.io import border_dark_level

    a = np.asarray(images, np.float64)
    h, w = a.shape[-2:]
    if ring:
        a = a - border_dark_level(a, ring)[..., None, None]
    out = np.empty_like(a)
    flat_in, flat_out = a.reshape(-1, h, w), out.reshape(-1, h, w)
    for k, f in enumerate(flat_in):
        mean = f.mean()
        if not mean > 0:
            name = k if labels is None else labels[k]
            raise DiffcamError(f"plane {name} has no signal above its dark level (mean "
                               f"{mean:.3g} after subtracting the border median): an "
                               f"empty or dark plane cannot be fitted.")
        flat_out[k] = f / mean
    return out


# -------------------------------------------------------------------- initialisation

def _to_field_grid(img, s, centre, model: StackModel):
    """A measured plane at magnification ``s`` (relative to the reference) resampled
    onto the field grid (at s = m0): (intensity ≥ 0, where-measured mask)."""
    o, (h, w) = model.oversample, model.frame
    s = s / model.grid_magnification
    half = (o - 1) / 2.0
    py = (np.arange(model.grid[0]) - model.pad - half) / o
    px = (np.arange(model.grid[1]) - model.pad - half) / o
    sy = centre[0] + s * (py - centre[0])
    sx = centre[1] + s * (px - centre[1])
    yy, xx = np.meshgrid(sy, sx, indexing="ij")
    val = ndi.map_coordinates(img, [yy, xx], order=3, mode="constant", cval=0.0)
    known = (yy >= -0.5) & (yy <= h - 0.5) & (xx >= -0.5) & (xx <= w - 0.5)
    return np.clip(val, 0, None) * known, known


@jax.jit
def _gs(amp, mods, knowns, kernels, theta, n_iter):
    """Gerchberg–Saxton: amplitude ``amp`` at the diffuser, measured moduli at the
    planes (only where known), the planes visited in turn."""
    def body(_, th):
        for m, k, h in zip(mods, knowns, kernels):
            u = transfer_step(amp * expj(th), h)
            u = jnp.where(k, fit_amplitude(u, m), u)
            th = jnp.angle(transfer_step(u, jnp.conj(h)))
        return th
    return jax.lax.fori_loop(0, n_iter, body, theta)


def _initial_model(imgs, planes, reg: Registration, zeta, opts: StackFitOptions
                   ) -> StackModel:
    """Amplitude from the blurred reference plane, phase from GS between the planes;
    the field's spline coefficients by least squares to A·e^{jθ}."""
    h, w = imgs[0].shape
    o, pad = opts.oversample, opts.pad
    grid = (_good_size(o * h + 2 * pad), _good_size(o * w + 2 * pad))
    stride = opts.field_stride
    coarse = _coefficient_shape(grid, stride)
    ref, anchor = planes[0], max(planes[1:], key=lambda t: abs(t - planes[0]))
    kappa0 = 0.0 if opts.frozen else float(opts.kappa)
    ss = [float(relative_magnification_at(t, reg.magnification, ref, anchor)) for t in planes]
    shell = StackModel(
        field_real=jnp.zeros(coarse, jnp.float32),
        field_imag=jnp.zeros(coarse, jnp.float32),
        log_zeta=jnp.float32(np.log(zeta)), log_s=jnp.float32(np.log(reg.magnification)),
        centre=jnp.asarray(reg.centre, jnp.float32), log_sigma=jnp.float32(np.log(opts.sigma)),
        kappa=jnp.float32(kappa0), frame=(h, w), pad=pad, grid=grid, stride=stride,
        reference=ref, anchor=anchor, oversample=o, frozen=bool(opts.frozen),
        grid_magnification=float(np.sqrt(min(ss) * max(ss))))
    taper = np.outer(_taper(grid[0], pad), _taper(grid[1], pad))
    grids = [_to_field_grid(img, s, reg.centre, shell) for img, s in zip(imgs, ss)]
    env = np.where(grids[0][1], ndi.gaussian_filter(grids[0][0], opts.amplitude_blur), 0.0)
    amp = np.sqrt(np.clip(env, 0, None)) * taper
    energy = (amp ** 2).sum()
    mods = [np.sqrt(i * energy / max(i.sum(), 1e-30)) for i, _ in grids]
    kernels = [_fresnel(grid, jnp.float32(zeta * s ** (-kappa0))) for s in ss]
    th0 = (0.1 * np.random.default_rng(opts.seed).standard_normal(grid)).astype(np.float32)
    theta = _gs(jnp.asarray(amp, jnp.float32), [jnp.asarray(m, jnp.float32) for m in mods],
                [jnp.asarray(k) for _, k in grids], kernels,
                jnp.asarray(th0), int(opts.gs_iterations))
    c = _coefficients_of(jnp.asarray(amp, jnp.float32) * expj(theta), grid, stride)
    return dataclasses.replace(shell, field_real=c.real, field_imag=c.imag)


def _coefficient_shape(grid, stride: int) -> tuple[int, int]:
    """Field coefficients per axis: one every ``stride`` fine samples, one more before
    the grid and two after (the cubic's support)."""
    return tuple(-(-n // stride) + 3 for n in grid)


def _coefficient_points(grid, stride: int):
    """Where the fine samples fall on the coefficient grid (fractional indices)."""
    return tuple(jnp.asarray(np.arange(n) / stride + 1.0, jnp.float32) for n in grid)


@partial(jax.jit, static_argnums=(1, 2, 3))
def _coefficients_of(g, grid, stride: int, iterations: int = 40):
    """Least-squares spline coefficients of the fine field ``g`` (conjugate gradients on
    the normal equations; the sampling's transpose is its vjp)."""
    ty, tx = _coefficient_points(grid, stride)

    def upsample(c):
        return spline_sample(spline_sample(c, ty, -2), tx, -1)

    _, transpose = jax.vjp(upsample, jnp.zeros(_coefficient_shape(grid, stride), g.dtype))
    normal = lambda c: transpose(upsample(c))[0]  # noqa: E731
    return jax.scipy.sparse.linalg.cg(normal, transpose(g)[0], maxiter=iterations)[0]


# -------------------------------------------------------------------------------- fit

class _Data(eqx.Module):
    ys: Array       # (P, h, w) prepared given planes; the reference first
    train: Array    # (P, h, w) 1 on training pixels
    val: Array      # (P, h, w) 1 on validation pixels
    ts: Array       # (P,) plane indices


def _scores(model: StackModel, data: _Data):
    spec = model.spectrum()
    pred = jnp.stack([model.render_plane(spec, data.ts[k]) for k in range(data.ts.shape[0])])
    r_tr = pearson(pred, data.ys, mask=data.train)
    r_va = pearson(pred, data.ys, mask=data.val)
    return r_tr, r_va


def _loss(model, data):
    r_tr, r_va = _scores(model, data)
    return (1.0 - r_tr).sum(), (r_tr.mean(), jax.lax.stop_gradient(r_va.mean()))


@eqx.filter_jit
def _evaluate(model, data):
    return _loss(model, data)[1]


@eqx.filter_jit
def _adam_step(model, state, data, lr):
    """One Adam step (β = 0.9, 0.999); returns the new model and state and the
    (training, validation) Pearson of the model *before* the step."""
    (_, (r_tr, r_va)), grads = eqx.filter_value_and_grad(_loss, has_aux=True)(model, data)
    m, v, k = state
    k = k + 1
    m = jax.tree.map(lambda a, g: 0.9 * a + 0.1 * g, m, grads)
    v = jax.tree.map(lambda a, g: 0.999 * a + 0.001 * g * g, v, grads)
    c1, c2 = 1 - 0.9 ** k, 1 - 0.999 ** k
    update = jax.tree.map(lambda a, b, s: -s * (a / c1) / (jnp.sqrt(b / c2) + 1e-12), m, v, lr)
    return eqx.apply_updates(model, update), (m, v, k), r_tr, r_va


def _step_sizes(model: StackModel, opts: StackFitOptions):
    kappa = opts.step_kappa if (opts.fit_kappa and not opts.frozen) else 0.0
    sizes = dict(field_real=opts.step_field, field_imag=opts.step_field,
                 log_zeta=opts.step_zeta, log_s=opts.step_magnification,
                 centre=opts.step_centre, log_sigma=opts.step_blur, kappa=kappa)
    params = eqx.filter(model, eqx.is_array)
    return dataclasses.replace(params, **{k: jnp.float32(v) for k, v in sizes.items()})


def _validation_masks(shape, n, fraction, seed):
    """(train, val) float32 masks: ``fraction`` of the pixels of each plane, drawn
    independently per plane from ``seed``."""
    val = np.random.default_rng(seed).random((n,) + tuple(shape)) < fraction
    return (~val).astype(np.float32), val.astype(np.float32)


@dataclasses.dataclass(frozen=True)
class StackFit:
    """The result of :func:`fit_stack`.

    Attributes:
        model: the fitted :class:`StackModel` (at the best validation step).
        planes: the given planes (the reference first).
        n_planes: planes in the stack (``None`` if unknown), the default of
            :meth:`predict`.
        registration: M(anchor)/M(reference) and the fixed point (pixels).
        history: mean training Pearson of the given planes, per step.
        validation: mean validation Pearson, per step (of the model before the step).
        stop_reason: why the fit stopped.
        best_step: the step whose model was kept.
        validation_score: the kept model's validation Pearson.
        baseline_validation: the scaling baseline's Pearson on the same validation
            pixels (each given plane predicted from the nearest other given plane).
        worse_than_baseline: ``validation_score < baseline_validation``.
        zeta_scan: ``{ζ candidate (fine samples²): training Pearson of its GS start}``.
        identifiable: what the data fix: ζ_ref in pixel units; with the pixel pitch and
            wavelength z2·M at the reference plane and over the stack (m), with z2 too
            the magnifications and z1 over the stack (:func:`_identifiable`).
        physical: the physical inputs given (pixel pitch, wavelength, z2; m or None).
        options: the :class:`StackFitOptions` as a dict.
        seconds: wall time of the fit, s.
        measured: the given planes as fitted (:func:`prepare_planes`), in ``planes``
            order, float32 (P, H, W): the residuals :meth:`predict` carries come from
            them (``None`` in files of format 1: rendering only).
    """

    model: StackModel
    planes: tuple[int, ...]
    n_planes: int | None
    registration: Registration
    history: np.ndarray
    validation: np.ndarray
    stop_reason: str
    best_step: int
    validation_score: float
    baseline_validation: float
    worse_than_baseline: bool
    zeta_scan: dict
    identifiable: dict
    physical: dict
    options: dict
    seconds: float
    measured: np.ndarray | None = None

    @property
    def steps(self) -> int:
        return int(len(self.history))

    def predict(self, planes=None, *, kappa: float | None = None, residual: bool = True
                ) -> np.ndarray:
        """Predicted planes, each normalised to unit mean (like :func:`prepare_planes`).

        Args:
            planes: plane indices (any ints, also outside the measured range), a count
                n (planes 0 … n−1), or ``None`` for every plane of the fitted stack.
            kappa: render with this depth-law exponent instead of the fitted one
                (``kappa=0``: the frozen-distance ablation of the same field).
            residual: carry the measured planes' residuals (the module docstring);
                ``False`` renders the model alone.

        Returns:
            float32 array (k, H, W).
        """
        ts = self._plane_list(planes)
        model = self.model
        if kappa is not None and not (isinstance(kappa, (int, float, np.number))
                                      and not isinstance(kappa, bool)
                                      and abs(float(kappa)) <= 10):
            raise DiffcamError(f"kappa must be a number in [-10, 10] (1: the scaling "
                               f"theorem's depth law, 0: frozen distance), got {kappa!r}.")
        if kappa is not None:
            model = eqx.tree_at(lambda m: m.kappa, model, jnp.float32(kappa))
            if model.frozen and kappa != 0:
                model = dataclasses.replace(model, frozen=False)
        if residual and self.measured is not None:
            out = self._with_residuals(model, ts)
        else:
            out = _render(model, ts)
        out /= out.mean(axis=(-2, -1), keepdims=True)
        return out.astype(np.float32)

    def _plane_list(self, planes) -> list[int]:
        """The planes to predict, checked: whole numbers, at most :data:`MAX_PLANES`,
        none beyond where the fitted magnification law reaches zero."""
        if planes is None:
            if self.n_planes is None:
                raise DiffcamError("this fit does not know the stack's plane count; pass "
                                   "the planes to predict.")
            planes = self.n_planes
        if isinstance(planes, (bool, np.bool_, str, bytes, float, np.floating)):
            raise DiffcamError(f"planes must be a count or a sequence of plane indices "
                               f"(integers), got {planes!r}.")
        if isinstance(planes, (int, np.integer)):
            _check_count(int(planes))
            ts = list(range(int(planes)))
        else:
            ts = [_plane_index(t) for t in np.asarray(planes, dtype=object).reshape(-1)]
            _check_count(len(ts))
        bad = [t for t in ts if not float(self.model.magnification(t)) > 0]
        if bad:
            raise DiffcamError(f"plane(s) {bad[:5]} lie beyond where the fitted "
                               f"magnification law reaches zero (it is linear in the plane "
                               f"index through planes {self.model.reference} and "
                               f"{self.model.anchor}); predict planes nearer the fitted "
                               f"ones.")
        return ts

    def _with_residuals(self, model: StackModel, ts: list[int]) -> np.ndarray:
        """(Σ w_k a_k)·render(t) + Σ w_k T_{k→t}(R_k) for every t (module docstring)."""
        rendered = _render(model, list(self.planes) + ts)
        given, rendered = rendered[:len(self.planes)], rendered[len(self.planes):]
        gain, coef = {}, {}
        for k, y, p in zip(self.planes, self.measured.astype(np.float64), given):
            a, b = np.polyfit(p.ravel(), y.ravel(), 1)
            gain[k] = a
            coef[k] = ndi.spline_filter(y - a * p - b, order=3)
        s = {t: float(relative_magnification_at(t, np.exp(float(model.log_s)),
                                                model.reference, model.anchor))
             for t in set(ts) | set(self.planes)}
        centre = tuple(float(c) for c in np.asarray(model.centre))
        out = np.empty_like(rendered)
        for n, t in enumerate(ts):
            weights = bracket_weights(t, self.planes)
            out[n] = sum(w * gain[k] for k, w in weights.items()) * rendered[n]
            for k, w in weights.items():
                out[n] += w * magnify_about(coef[k], s[t] / s[k], centre, prefiltered=True)
        return out

    def summary(self) -> dict:
        """The scalar facts of the fit, JSON-able."""
        m = self.model
        return {"planes": list(self.planes), "n_planes": self.n_planes,
                "stop_reason": self.stop_reason, "best_step": self.best_step,
                "steps": self.steps, "validation_score": self.validation_score,
                "baseline_validation": self.baseline_validation,
                "worse_than_baseline": self.worse_than_baseline,
                "zeta_reference_px2": m.zeta_pixels, "kappa": float(m.kappa),
                "frozen": m.frozen, "magnification": float(np.exp(float(m.log_s))),
                "grid_magnification": m.grid_magnification,
                "centre": [float(c) for c in np.asarray(m.centre)],
                "blur_sigma_fine": float(np.exp(float(m.log_sigma))),
                "seconds": self.seconds}

    def save(self, path: str | os.PathLike) -> Path:
        """Write the fit to one ``.npz`` file (arrays and a JSON metadata entry with a
        format version), atomically: a temporary file in the same folder, then
        ``os.replace``. Read it back with :func:`load_stack_fit`."""
        from diffcam.io import atomic_output, check_output_path

        path = check_output_path(path, suffixes=(".npz",))
        m = self.model
        meta = {
            "format": FORMAT, "version": FORMAT_VERSION,
            "geometry": {"frame": list(m.frame), "pad": m.pad, "grid": list(m.grid),
                         "stride": m.stride, "reference": m.reference, "anchor": m.anchor,
                         "oversample": m.oversample, "frozen": m.frozen,
                         "grid_magnification": m.grid_magnification},
            "planes": list(self.planes), "n_planes": self.n_planes,
            "registration": dataclasses.asdict(self.registration),
            "stop_reason": self.stop_reason, "best_step": self.best_step,
            "validation_score": self.validation_score,
            "baseline_validation": self.baseline_validation,
            "worse_than_baseline": self.worse_than_baseline,
            "zeta_scan": {str(k): v for k, v in self.zeta_scan.items()},
            "identifiable": self.identifiable, "physical": self.physical,
            "options": self.options, "seconds": self.seconds,
        }
        arrays = {k: np.asarray(getattr(m, k)) for k in _ARRAYS}
        if self.measured is not None:
            arrays["measured"] = np.asarray(self.measured, np.float32)
        with atomic_output(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, metadata=np.array(json.dumps(meta)),
                         history=np.asarray(self.history, np.float64),
                         validation=np.asarray(self.validation, np.float64), **arrays)
        return path


def load_stack_fit(path: str | os.PathLike) -> StackFit:
    """Read a :class:`StackFit` written by :meth:`StackFit.save`.

    Raises:
        DiffcamError: missing, corrupt or truncated file, not a stack-fit file, another
            format version (an older one says to fit again), or arrays that do not match
            the recorded geometry.
    """
    from diffcam.io import read_npz

    what = "a diffcam stack-fit file"
    data = read_npz(path, ("metadata",), what=what)
    try:
        meta = json.loads(str(data["metadata"][()]))
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise DiffcamError(f"{path}: not {what} (format {meta.get('format')!r}).")
        version = meta.get("version")
        if not isinstance(version, int) or version > FORMAT_VERSION:
            raise DiffcamError(f"{path}: stack-fit format version {version!r}; this diffcam "
                               f"reads versions ≤ {FORMAT_VERSION}: upgrade diffcam.")
        if version < FORMAT_VERSION:
            raise DiffcamError(f"{path}: stack-fit format version {version} holds a "
                               f"per-sample phase model this diffcam no longer renders; "
                               f"fit the stack again (diffcam fit STACK --planes …).")
        data = read_npz(path, ("metadata", "history", "validation") + _ARRAYS, what=what)
        model = _model_from(data, meta["geometry"], path)
        measured = _measured_from(path, meta, model)
        reg = meta["registration"]
        return StackFit(
            model=model, planes=tuple(int(t) for t in meta["planes"]),
            n_planes=None if meta["n_planes"] is None else int(meta["n_planes"]),
            registration=Registration(float(reg["magnification"]),
                                      tuple(float(c) for c in reg["centre"]),
                                      float(reg["pearson"]), float(reg.get("seconds", 0.0))),
            history=np.asarray(data["history"]), validation=np.asarray(data["validation"]),
            stop_reason=str(meta["stop_reason"]), best_step=int(meta["best_step"]),
            validation_score=float(meta["validation_score"]),
            baseline_validation=float(meta["baseline_validation"]),
            worse_than_baseline=bool(meta["worse_than_baseline"]),
            zeta_scan={float(k): v for k, v in meta["zeta_scan"].items()},
            identifiable=dict(meta["identifiable"]), physical=dict(meta["physical"]),
            options=dict(meta["options"]), seconds=float(meta["seconds"]),
            measured=measured)
    except DiffcamError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise DiffcamError(f"{path}: not a readable {what} ({type(err).__name__}: {err}); "
                           f"the metadata are missing or damaged.") from None


def _model_from(data, g: dict, path) -> StackModel:
    """The :class:`StackModel` of a fit file, its arrays checked against its geometry."""
    model = StackModel(
        **{k: jnp.asarray(data[k], jnp.float32) for k in _ARRAYS},
        frame=tuple(int(v) for v in g["frame"]), pad=int(g["pad"]),
        grid=tuple(int(v) for v in g["grid"]), stride=int(g["stride"]),
        reference=int(g["reference"]), anchor=int(g["anchor"]),
        oversample=int(g["oversample"]), frozen=bool(g["frozen"]),
        grid_magnification=float(g.get("grid_magnification", 1.0)))
    coarse = _coefficient_shape(model.grid, model.stride)
    if model.field_real.shape != coarse or model.field_imag.shape != coarse \
            or model.centre.shape != (2,):
        raise DiffcamError(f"{path}: arrays do not match the recorded geometry (field "
                           f"coefficients {model.field_real.shape}, expected {coarse}); the "
                           f"file is damaged.")
    if not all(np.isfinite(np.asarray(data[k])).all() for k in _ARRAYS):
        raise DiffcamError(f"{path}: the model holds NaN/Inf values; the file is damaged.")
    if not model.grid_magnification > 0:
        raise DiffcamError(f"{path}: grid magnification {model.grid_magnification!r} is "
                           f"not positive; the file is damaged.")
    return model


def _measured_from(path, meta: dict, model: StackModel) -> np.ndarray:
    """The prepared given planes stored by format ≥ 2, checked against the geometry."""
    from diffcam.io import read_npz

    measured = read_npz(path, ("measured",), what="a diffcam stack-fit file")["measured"]
    measured = np.asarray(measured, np.float32)
    if measured.shape != (len(meta["planes"]),) + model.frame or \
            not np.isfinite(measured).all():
        raise DiffcamError(f"{path}: the measured planes ({measured.shape}) do not match "
                           f"the recorded planes and frame or hold NaN/Inf; the file is "
                           f"damaged.")
    return measured


# ------------------------------------------------------------------------ input checks

def _given_planes(stack, planes):
    """Validate (stack, planes) before any compute → (list of float64 frames, planes,
    n_planes or None, input dtype)."""
    if isinstance(planes, (int, np.integer)) or isinstance(planes, (str, bytes)):
        raise DiffcamError(f"planes must be a sequence of at least 2 plane indices, got "
                           f"{planes!r}.")
    try:
        planes = list(planes)
    except TypeError:
        raise DiffcamError(f"planes must be a sequence of plane indices, got {planes!r}.") \
            from None
    for t in planes:
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)):
            raise DiffcamError(f"plane indices must be integers, got {t!r}.")
    planes = [int(t) for t in planes]
    if len(planes) < 2:
        raise DiffcamError(f"give at least 2 planes to fit (the magnification law needs "
                           f"two), got {planes}.")
    repeated = sorted({t for t in planes if planes.count(t) > 1})
    if repeated:
        raise DiffcamError(f"plane(s) {repeated} given more than once in {planes}.")
    if isinstance(stack, Mapping):
        missing = [t for t in planes if t not in stack]
        if missing:
            raise DiffcamError(f"plane(s) {missing} are not in the given frames (planes "
                               f"{sorted(stack)}).")
        frames, n_planes = [stack[t] for t in planes], None
    else:
        if isinstance(stack, (list, tuple)):
            shapes = {np.shape(f) for f in stack}
            if len(shapes) > 1:
                raise ShapeError(f"the stack's frames differ in shape: {sorted(shapes)}; "
                                 f"crop them to one size first.")
        arr = np.asarray(stack) if not hasattr(stack, "shape") else stack
        if np.ndim(arr) != 3 or 0 in np.shape(arr):
            raise ShapeError(f"the stack must be (n_planes, ny, nx), got shape "
                             f"{np.shape(arr)}.")
        n_planes = int(np.shape(arr)[0])
        bad = [t for t in planes if not 0 <= t < n_planes]
        if bad:
            raise DiffcamError(f"plane(s) {bad} out of range: the stack has {n_planes} "
                               f"planes (0 … {n_planes - 1}).")
        frames = [arr[t] for t in planes]
    frames = [np.asarray(f) for f in frames]
    shapes = {f.shape for f in frames}
    if len(shapes) > 1:
        raise ShapeError(f"the given frames differ in shape: {sorted(shapes)}; crop them "
                         f"to one size first.")
    if frames[0].ndim != 2 or 0 in frames[0].shape:
        raise ShapeError(f"each plane must be a non-empty 2-D image, got {frames[0].shape}.")
    if min(frames[0].shape) < 16:
        raise ShapeError(f"frames of {frames[0].shape} pixels are too small to fit (≥ 16 "
                         f"per side).")
    dtype = frames[0].dtype
    for t, f in zip(planes, frames):
        if not (np.issubdtype(f.dtype, np.integer) or np.issubdtype(f.dtype, np.floating)):
            raise DiffcamError(f"plane {t}: unsupported data type {f.dtype}.")
        finite = np.isfinite(f)
        if not finite.all():
            raise DiffcamError(f"plane {t} holds {int(f.size - finite.sum())} NaN/Inf "
                               f"pixel(s); clean or crop them first.")
        if float(np.ptp(f)) == 0:
            raise DiffcamError(f"plane {t} is constant ({float(f.flat[0]):g} everywhere): "
                               f"an empty or dark plane cannot be fitted.")
    return [f.astype(np.float64) for f in frames], planes, n_planes, dtype


def _check_saturation(frames, planes, level):
    if level is None:
        return
    counts = {t: int((f >= level).sum()) for t, f in zip(planes, frames)}
    bad = {t: n for t, n in counts.items() if n}
    if bad:
        total = sum(bad.values())
        listing = ", ".join(f"plane {t}: {n}" for t, n in bad.items())
        raise DiffcamError(f"{total} saturated pixel(s) (≥ {level:g}) in the given planes "
                           f"({listing}); their true values are unknown. Retake or crop "
                           f"them, or pass saturation=None to fit them as they are.")


def _check_physical(pixel_pitch, wavelength, z2) -> dict:
    """The physical inputs given (metres or ``None``), checked."""
    from diffcam.core.errors import check_positive

    phys = {"pixel_pitch": pixel_pitch, "wavelength": wavelength, "z2": z2}
    for name, v in phys.items():
        if v is not None:
            check_positive(name, v, "m")
            phys[name] = float(v)
    return phys


def _identifiable(phys: dict, model: StackModel, n_planes: int | None) -> dict:
    """What the planes fix, in physical units as far as ``phys`` allows.

    ζ_ref = λ·z_eff/d² with d the diffuser-side sample pitch, (pitch/o)/M_virtual; with
    z_eff = z2/M this is λ·z2·M(ref)·m0²/(pitch/o)²: the planes fix z2·M(t) =
    z2 + z2²/z1(t), not z2 and z1 apart (module docstring). Given z2 too,
    M(t) = z2·M(t)/z2 and z1(t) = z2/(M(t) − 1).
    """
    zeta_px = model.zeta_pixels
    ident = {"zeta_reference_px2": zeta_px,
             "note": "the planes fix ζ = λ·z2·M/pixel², i.e. z2·M(t) = z2 + z2²/z1(t) "
                     "given the pixel pitch and wavelength; z1 needs z2 as well."}
    pitch, lam, z2 = phys["pixel_pitch"], phys["wavelength"], phys["z2"]
    if pitch is None:
        return ident
    m0 = model.grid_magnification
    ident["lambda_z2_M_reference_m2"] = zeta_px * pitch ** 2 / m0 ** 2
    if lam is None:
        return ident
    z2m_ref = ident["lambda_z2_M_reference_m2"] / lam
    ident["z2_M_reference_m"] = z2m_ref
    ends = [0, n_planes - 1] if n_planes else sorted({model.reference, model.anchor})
    s = [float(model.magnification(t)) for t in ends]
    ident["z2_M_range_m"] = [z2m_ref * v for v in s]
    if z2 is not None:
        m = [z2m_ref * v / z2 for v in s]
        ident["magnification_range"] = m
        ident["z1_range_m"] = [z2 / (v - 1) if v > 1 else None for v in m]
    return ident


# ------------------------------------------------------------------------ entry point

def fit_stack(stack, planes: Sequence[int], *, options: StackFitOptions | None = None,
              progress: bool = True, saturation: float | str | None = "auto",
              pixel_pitch: float | None = None, wavelength: float | None = None,
              z2: float | None = None, registration: Registration | None = None,
              **overrides) -> StackFit:
    """Fit the wave model to the given planes of a PSF stack.

    Only ``stack[planes]`` is read: the other planes never enter (predict them with
    :meth:`StackFit.predict` and score them against the baseline).

    Args:
        stack: (n_planes, ny, nx) array (any gain and dark level: each given plane is
            prepared by :func:`prepare_planes`), or ``{plane index: (ny, nx) image}``.
        planes: two or more distinct plane indices; the first is the reference.
        options: :class:`StackFitOptions`; keywords named after its fields replace them.
        progress: show a tqdm bar over the steps.
        saturation: pixel value at or above which a pixel is saturated (input units):
            ``"auto"`` is 0.999 × the full scale of an integer input and no check for
            float input; ``None`` skips the check. Saturated pixels raise.
        pixel_pitch, wavelength, z2: optional physical inputs, metres; they turn ζ into
            z2·M(t) and, with z2, into z1(t) in ``identifiable`` (nothing is fitted from
            them).
        registration: M(anchor)/M(reference) and the fixed point, if already known
            (the anchor is the given plane farthest from the reference).

    Returns:
        :class:`StackFit`. A :class:`StackFitWarning` is issued when the kept model is
        worse than the scaling baseline on the validation pixels.

    Raises:
        DiffcamError: before any compute, for planes out of range, fewer than 2 planes,
            repeated planes, NaN/Inf pixels, a constant (empty or dark) plane,
            saturated pixels (with their count); ShapeError for frames of different
            shapes or a stack that is not 3-D.
    """
    opts = StackFitOptions.of(options, **overrides)
    frames, planes, n_planes, dtype = _given_planes(stack, planes)
    _check_saturation(frames, planes, _saturation_level(saturation, dtype))
    phys = _check_physical(pixel_pitch, wavelength, z2)
    t0 = time.perf_counter()
    imgs = [p.astype(np.float32) for p in prepare_planes(np.stack(frames), opts.dark_ring,
                                                          labels=planes)]
    ref = planes[0]
    anchor = max(planes[1:], key=lambda t: abs(t - ref))
    if registration is None:
        registration = register_magnification(imgs[0], imgs[planes.index(anchor)])
    train, val = _validation_masks(imgs[0].shape, len(planes), opts.validation_fraction,
                                   opts.seed)
    data = _Data(jnp.asarray(np.stack(imgs)), jnp.asarray(train), jnp.asarray(val),
                 jnp.asarray(planes, jnp.float32))
    model, scan = _start(imgs, planes, registration, data, opts)
    run = _descend(model, data, opts, t0, progress)
    _render(run.model, planes[:1])      # compiles the predictor inside the fit
    base = _baseline_validation(imgs, planes, registration, val, ref, anchor)
    ident = _identifiable(phys, run.model, n_planes)
    fit = StackFit(model=run.model, planes=tuple(planes), n_planes=n_planes,
                   registration=registration, history=np.asarray(run.train),
                   validation=np.asarray(run.validation), stop_reason=run.reason,
                   best_step=run.best_step, validation_score=run.best_validation,
                   baseline_validation=float(base),
                   worse_than_baseline=bool(run.best_validation < base), zeta_scan=scan,
                   identifiable=ident, physical=phys, options=opts.to_dict(),
                   seconds=time.perf_counter() - t0, measured=np.stack(imgs))
    if fit.worse_than_baseline:
        warnings.warn(f"the stack fit ends worse than the scaling baseline on its own "
                      f"validation pixels (Pearson {run.best_validation:.4f} < {base:.4f}): "
                      f"prefer the baseline for these planes, or fit more planes.",
                      StackFitWarning, stacklevel=2)
    return fit


def _saturation_level(saturation, dtype) -> float | None:
    if isinstance(saturation, str):
        if saturation != "auto":
            raise DiffcamError(f"saturation must be a level, 'auto' or None, got "
                               f"{saturation!r}.")
        return 0.999 * float(np.iinfo(dtype).max) \
            if np.issubdtype(dtype, np.integer) else None
    if saturation is not None:
        if isinstance(saturation, bool) or not isinstance(saturation, (int, float, np.number)) \
                or not np.isfinite(saturation):
            raise DiffcamError(f"saturation must be a finite pixel level, 'auto' or None, "
                               f"got {saturation!r}.")
        return float(saturation)
    return saturation


def _start(imgs, planes, registration, data, opts: StackFitOptions):
    """The GS start for every candidate ζ_ref; the best training Pearson wins.
    Returns (model, {ζ: training Pearson})."""
    scan, best = {}, None
    for zeta in opts.zetas:
        model = _initial_model(imgs, planes, registration, float(zeta), opts)
        r_tr, _ = _evaluate(model, data)
        scan[float(zeta)] = float(r_tr)
        if best is None or float(r_tr) > best[0]:
            best = (float(r_tr), model)
    return best[1], scan


class _Run(NamedTuple):
    model: StackModel        # the model of the best validation step
    best_step: int
    best_validation: float
    train: list              # mean training Pearson per step
    validation: list         # mean validation Pearson per step
    reason: str              # why it stopped


def _descend(model: StackModel, data: _Data, opts: StackFitOptions, t0: float,
             progress: bool) -> _Run:
    """Adam from ``model`` until validation stalls, ``max_steps`` or the time budget
    (counted from ``t0``, perf_counter seconds)."""
    lr = _step_sizes(model, opts)
    zeros = jax.tree.map(jnp.zeros_like, eqx.filter(model, eqx.is_array))
    state = (zeros, zeros, jnp.int32(0))
    best_val, best_model, best_step = -np.inf, model, 0
    train_hist, val_hist = [], []
    reason = f"max_steps ({opts.max_steps})"
    with new_bar(opts.max_steps, "stack fit", unit="step", progress=progress) as bar:
        for k in range(opts.max_steps):
            new_model, state, r_tr, r_va = _adam_step(model, state, data, lr)
            r_va = float(r_va)
            if not np.isfinite(r_va):
                reason = f"diverged (validation Pearson {r_va}) at step {k}"
                break
            train_hist.append(float(r_tr))
            val_hist.append(r_va)
            if r_va > best_val:
                best_val, best_model, best_step = r_va, model, k
            model = new_model
            bar.update(1)
            bar.set_postfix(val=f"{r_va:.4f}", best=f"{best_val:.4f}")
            if k - best_step >= opts.patience:
                reason = f"no validation improvement for {opts.patience} steps"
                break
            if time.perf_counter() - t0 > opts.time_budget:
                reason = f"time budget ({opts.time_budget:g} s)"
                break
    return _Run(best_model, best_step, float(best_val), train_hist, val_hist, reason)


def _baseline_validation(imgs, planes, reg, val, ref, anchor) -> float:
    """Mean over the given planes of the Pearson, on that plane's validation pixels, of
    the scaling baseline from the nearest *other* given plane (the baseline at a given
    plane is the plane itself, so it must not see its own validation pixels)."""
    scores = []
    for n, t in enumerate(planes):
        others = [q for q in planes if q != t]
        k = min(others, key=lambda q: (abs(t - q), q))
        s = relative_magnification_at(t, reg.magnification, ref, anchor) / \
            relative_magnification_at(k, reg.magnification, ref, anchor)
        pred = magnify_about(imgs[planes.index(k)], float(s), reg.centre)
        scores.append(float(pearson(pred, imgs[n], mask=val[n] > 0)))
    return float(np.mean(scores))
