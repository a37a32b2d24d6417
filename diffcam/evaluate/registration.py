"""Magnification registration between PSF planes, and the scaling baseline built on it.

Between two planes of a diffuser camera's PSF stack the caustic mostly *scales* about a
fixed point (Fresnel scaling theorem: a source at z1 magnifies the diffuser's pattern by
M = (z1 + z2)/z1 about the point the optical axis meets the sensor). That point is not
the frame centre in real data (a cropped or shifted sensor), so it is fitted.

- `register_magnification` — fixed point and relative magnification between two
  planes (Pearson maximised over both, cubic splines);
- `scaling_baseline` — every plane as the nearest given plane magnified by
  M(t)/M(k) about that point, M linear in the plane index t. This is the baseline every
  stack prediction (`diffcam.calibrate.fit_stack`) is compared with.

Everything here is in **pixel units** (pixel k's centre at coordinate k, (y, x) order)
and plane indices; NumPy/SciPy, outside ``jit``. Planes equally spaced in 1/z1 (the
usual DiffuserCam stack) have M = (z1 + z2)/z1 = 1 + z2/z1 linear in the index, which is
the law used here (verified on the built-in stack to 3·10⁻⁴ in relative magnification
over 43 planes).
"""

from __future__ import annotations

import bisect
import dataclasses
import time
from typing import Mapping, Sequence

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError, real_array
from diffcam.model.spline import bspline

__all__ = ["Registration", "register_magnification", "magnify_about", "spline_coefficients",
           "magnification_slope", "relative_magnification_at", "magnification_from_light",
           "scaling_baseline", "bracket_weights"]

_POLE = np.sqrt(3.0) - 2.0
"""The pole of the cubic B-spline's interpolation filter (Unser 1993)."""


@dataclasses.dataclass(frozen=True)
class Registration:
    """The magnification relating plane ``b`` to plane ``a``: ``b ≈ a`` magnified by
    ``magnification`` about ``centre``.

    Attributes:
        magnification: M(b)/M(a), dimensionless (> 1: ``b`` is larger).
        centre: the fixed point (y, x), pixels (pixel k's centre at k; may lie outside
            the frame).
        pearson: Pearson correlation of ``b`` and the magnified ``a`` at the optimum.
        seconds: wall time of the registration, s.
    """

    magnification: float
    centre: tuple[float, float]
    pearson: float
    seconds: float = 0.0


def magnify_about(image, magnification: float, centre, *, prefiltered: bool = False
                  ) -> np.ndarray:
    """``out(p) = image(centre + (p − centre)/magnification)``: ``image`` magnified about
    ``centre`` by cubic B-splines, zero outside the frame (as
    ``scipy.ndimage.map_coordinates(.., order=3, mode="constant")``, to rounding).

    A magnification is separable: each output row and column reads four coefficient
    rows and columns, so the work is 8 products per pixel.

    Args:
        image: (ny, nx) float image.
        magnification: dimensionless (> 0).
        centre: (y, x), pixels.
        prefiltered: ``image`` is already `spline_coefficients` of the image
            (saves the prefilter when one image is magnified many times).
    """
    coef = np.asarray(image, np.float64) if prefiltered else spline_coefficients(image)
    (h, w), (cy, cx) = coef.shape, (float(centre[0]), float(centre[1]))
    rows, row_weights = _spline_taps(cy + (np.arange(h) - cy) / magnification, h)
    cols, col_weights = _spline_taps(cx + (np.arange(w) - cx) / magnification, w)
    along_y = sum(row_weights[k][:, None] * coef[rows[k]] for k in range(4))
    return sum(col_weights[k] * along_y[:, cols[k]] for k in range(4))


def spline_coefficients(image) -> np.ndarray:
    """Cubic B-spline coefficients of a (ny, nx) image, float64: the spline through
    every pixel, mirror-symmetric at the edges (``scipy.ndimage.spline_filter(image,
    order=3)``, to rounding). The exact recursive filter of Unser (1993), one causal
    and one anti-causal pass along each axis."""
    coef = np.asarray(image, np.float64)
    for axis in (0, 1):
        coef = np.moveaxis(_prefilter_first_axis(np.moveaxis(coef, axis, 0)), 0, axis)
    return coef


def _prefilter_first_axis(f: np.ndarray) -> np.ndarray:
    n, z = f.shape[0], _POLE
    if n == 1:
        return f.copy()
    mirrored = np.r_[0:n, n - 2:0:-1]          # f extended by mirror symmetry, one period
    powers = z ** np.arange(len(mirrored), dtype=np.float64)
    out = np.empty_like(f)
    out[0] = np.tensordot(powers, f[mirrored], axes=1) / (1 - z ** len(mirrored))
    for k in range(1, n):
        out[k] = f[k] + z * out[k - 1]
    out[n - 1] = z / (z * z - 1) * (out[n - 1] + z * out[n - 2])
    for k in range(n - 2, -1, -1):
        out[k] = z * (out[k + 1] - out[k])
    return 6.0 * out


def _spline_taps(q: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The four coefficient indices (mirror-folded at the edges) and cubic B-spline
    weights of each coordinate ``q`` on an axis of ``n`` samples; weights 0 outside
    [0, n − 1] (the frame)."""
    base = np.floor(q).astype(np.int64)
    inside = (q >= 0) & (q <= n - 1)
    index, weight = [], []
    for k in range(-1, 3):
        j = base + k
        weight.append(bspline(q - j) * inside)
        j = np.abs(j)
        index.append(np.clip(np.where(j > n - 1, 2 * (n - 1) - j, j), 0, n - 1))
    return np.stack(index), np.stack(weight)


def _moments(img):
    w = np.clip(img, 0, None)
    m = w.sum()
    if m <= 0:
        return None, None
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    cy, cx = (w * yy).sum() / m, (w * xx).sum() / m
    rg = np.sqrt((w * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum() / m)
    return np.array([cy, cx]), rg


def _check_plane(image, name):
    a = np.asarray(real_array(name, image))
    if a.ndim != 2 or 0 in a.shape:
        raise ShapeError(f"{name} must be a non-empty 2-D image (ny, nx), got shape "
                         f"{a.shape}.")
    if not np.isfinite(a).all():
        raise DiffcamError(f"{name} holds {int((~np.isfinite(a)).sum())} NaN/Inf pixel(s); "
                           f"clean or crop them first.")
    if float(np.ptp(a)) == 0:
        raise DiffcamError(f"{name} is constant ({float(a.flat[0]):g} everywhere): an "
                           f"empty or dark plane has no pattern to register.")
    return a.astype(np.float64)


def register_magnification(a, b) -> Registration:
    """Fit ``b ≈ gain·magnify_about(a, M, centre) + offset`` by maximising Pearson.

    The start comes from intensity moments: under a magnification about p both the
    centroid and the radius of gyration scale about p, so M₀ = r_b/r_a and
    p₀ = (c_b − M₀c_a)/(1 − M₀) (the centroid of ``b`` when M₀ ≈ 1). Nelder–Mead then
    refines (log M, p) on the images blurred by 2 px, and again on the raw images, with
    cubic splines throughout. Nothing assumes the frame centre. About 3 s for 270×320.

    Args:
        a, b: (ny, nx) images of the same shape, background-subtracted (any gain).

    Returns:
        [`Registration`][diffcam.evaluate.registration.Registration] (M(b)/M(a), fixed point
        in pixels, Pearson).

    Raises:
        ShapeError: not two 2-D images of one shape.
        DiffcamError: NaN/Inf or a constant image.
    """
    import scipy.ndimage as ndi  # SciPy on first use: the package imports fast
    import scipy.optimize as sopt

    t0 = time.perf_counter()
    a = _check_plane(a, "image a")
    b = _check_plane(b, "image b")
    if a.shape != b.shape:
        raise ShapeError(f"images to register differ in shape: {a.shape} and {b.shape}.")
    ca, ra = _moments(a)
    cb, rb = _moments(b)
    if ca is None or cb is None or ra == 0:
        s0, p0 = 1.0, np.array(a.shape, np.float64) / 2
    else:
        s0 = rb / ra
        p0 = (cb - s0 * ca) / (1 - s0) if abs(1 - s0) > 0.01 else cb
    h, w = a.shape
    p0 = np.clip(p0, [-h, -w], [2 * h, 2 * w])
    x = np.array([np.log(s0), p0[0], p0[1]])
    step = 0.05 * max(h, w)
    res = None
    for sigma in (2.0, 0.0):
        fa = ndi.gaussian_filter(a, sigma) if sigma else a
        fb = ndi.gaussian_filter(b, sigma) if sigma else b
        fa = spline_coefficients(fa)

        def cost(p, fa=fa, fb=fb):
            # float64 on the host (numpy's Pearson): Nelder–Mead compares costs to 1e-7
            moved = magnify_about(fa, np.exp(p[0]), (p[1], p[2]), prefiltered=True)
            return -np.corrcoef(moved.ravel(), fb.ravel())[0, 1]

        simplex = np.array([x, x + [0.01, 0, 0], x + [0, step, 0], x + [0, 0, step]])
        res = sopt.minimize(cost, x, method="Nelder-Mead",
                            options=dict(initial_simplex=simplex, xatol=1e-4, fatol=1e-7,
                                         maxiter=600))
        x = res.x
    return Registration(float(np.exp(x[0])), (float(x[1]), float(x[2])), float(-res.fun),
                        time.perf_counter() - t0)


def magnification_slope(magnification: float, plane_a: int, plane_b: int) -> float:
    """Slope c of the law M(t) ∝ 1 + c·t (t a plane index) through M(b)/M(a) =
    ``magnification``: c = (M − 1)/(b − M·a), per plane."""
    den = plane_b - magnification * plane_a
    if plane_a == plane_b or den == 0:
        raise DiffcamError(f"cannot fix a magnification law from planes {plane_a} and "
                           f"{plane_b} with ratio {magnification:g}.")
    return (magnification - 1.0) / den


def relative_magnification_at(t, magnification, plane_a: int, plane_b: int):
    """M(t)/M(plane_a) under the linear law through M(b)/M(a) = ``magnification``
    (dimensionless; ``t`` a plane index or an array of them; NumPy or JAX)."""
    c = (magnification - 1.0) / (plane_b - magnification * plane_a)
    return (1.0 + c * t) / (1.0 + c * plane_a)


def magnification_from_light(light_a: float, light_b: float, magnification: float) -> float:
    """The absolute magnification M(a) = 1 + z2/z1(a) of plane a, from the light two
    planes collect and their relative magnification M(b)/M(a) = ``magnification``.

    The aperture collects a point source's light in proportion to the solid angle it
    subtends, 1/z1² = ((M − 1)/z2)² (inverse-square law), so with r = √(light_a/light_b)
    and M(b) = m·M(a): r = (M(a) − 1)/(m·M(a) − 1), i.e. M(a) = (r − 1)/(r·m − 1). It
    needs one source power and exposure for both captures, the light summed over the
    whole caustic (dark level subtracted) and planes far enough apart that r differs
    from 1/m (a source at infinity).

    Args:
        light_a, light_b: total light of the two planes, any common unit (> 0).
        magnification: M(b)/M(a), from
            [`register_magnification`][diffcam.evaluate.registration.register_magnification].

    Raises:
        DiffcamError: when the light does not follow the law for a source in front of
            the aperture (M(a) not finite or not above 1, or below 1/m).
    """
    if not (light_a > 0 and light_b > 0 and magnification > 0):
        raise DiffcamError(f"magnification_from_light needs positive light and "
                           f"magnification, got {light_a!r}, {light_b!r}, {magnification!r}.")
    r = np.sqrt(light_a / light_b)
    with np.errstate(divide="ignore", invalid="ignore"):
        m_a = (r - 1.0) / (r * magnification - 1.0)
    if not (np.isfinite(m_a) and m_a > 1.0 and m_a * magnification > 1.0):
        raise DiffcamError(f"the planes' light (ratio {light_a / light_b:.4g}) does not follow "
                           f"the inverse-square law of a point source with relative "
                           f"magnification {magnification:.4g} (M = {m_a:.4g}): were they "
                           f"captured with one source power and exposure?")
    return float(m_a)


def _plane_list(planes, name="planes") -> list[int]:
    if isinstance(planes, (int, np.integer)):
        if planes < 1:
            raise DiffcamError(f"{name}: the number of planes must be ≥ 1, got {planes}.")
        return list(range(int(planes)))
    out = []
    for t in planes:
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)):
            raise DiffcamError(f"{name} must be integer plane indices, got {t!r}.")
        out.append(int(t))
    if not out:
        raise DiffcamError(f"{name} is empty; give at least one plane index.")
    return out


def bracket_weights(t: float, planes: Sequence[int]) -> dict[int, float]:
    """Weights of the given ``planes`` at plane ``t``: linear in t between the two given
    planes that bracket it (1 at its own plane, 0 at the other), the nearest given plane
    alone (weight 1) outside the given range. No tuned constants."""
    ps = sorted(int(p) for p in planes)
    if t <= ps[0]:
        return {ps[0]: 1.0}
    if t >= ps[-1]:
        return {ps[-1]: 1.0}
    k = bisect.bisect_right(ps, t)
    a, b = ps[k - 1], ps[k]
    f = (t - a) / (b - a)
    return {a: 1.0 - f, b: f} if f else {a: 1.0}


def scaling_baseline(given: Mapping[int, np.ndarray], planes: int | Sequence[int], *,
                     registration: Registration | None = None, blend: bool = False
                     ) -> np.ndarray:
    """The scaling baseline: plane t as the nearest given plane k magnified about the
    fixed point by M(t)/M(k), M linear in the plane index.

    ``blend=True`` is an ablation for judging the stack model (not the baseline a user
    would use): between two given planes, both are magnified to t and mixed with
    `bracket_weights`, the weights the model's prediction uses for its residuals.

    The law comes from the two given planes farthest apart (the first and the last
    index), registered with
    [`register_magnification`][diffcam.evaluate.registration.register_magnification] unless
    ``registration`` (of the last given plane relative to the first) is passed. Cubic
    B-splines, zero outside the frame; ties go to the lower given plane. Gain and offset are
    those of the given plane (compare by Pearson).

    Args:
        given: ``{plane index: (ny, nx) image}``, at least two planes.
        planes: the planes to predict: a count n (planes 0 … n−1) or a sequence of
            plane indices.
        registration: M(last)/M(first) and the fixed point (pixels), if already known.
        blend: mix the two bracketing given planes instead of taking the nearest.

    Returns:
        float64 array (len(planes), ny, nx).
    """
    if len(given) < 2:
        raise DiffcamError(f"the scaling baseline needs at least two given planes to fix "
                           f"the magnification law, got {len(given)}.")
    keys = sorted(int(k) for k in given)
    imgs = {k: np.asarray(real_array(f"plane {k}", given[k]), np.float64) for k in keys}
    shapes = {v.shape for v in imgs.values()}
    if len(shapes) != 1:
        raise ShapeError(f"given planes differ in shape: {sorted(shapes)}.")
    first, last = keys[0], keys[-1]
    if registration is None:
        registration = register_magnification(imgs[first], imgs[last])
    ts = _plane_list(planes)
    filt = {k: spline_coefficients(imgs[k]) for k in keys}
    out = np.empty((len(ts),) + imgs[first].shape)
    m = registration.magnification
    for n, t in enumerate(ts):
        nearest = min(keys, key=lambda q: (abs(t - q), q))
        weights = bracket_weights(t, keys) if blend else {nearest: 1.0}
        out[n] = 0.0
        for k, w in weights.items():
            s = relative_magnification_at(t, m, first, last) / \
                relative_magnification_at(k, m, first, last)
            out[n] += w * (imgs[k] if t == k else magnify_about(
                filt[k], s, registration.centre, prefiltered=True))
    return out
