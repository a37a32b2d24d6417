"""The preprocessing steps that make a capture fit to reconstruct, each a separate
function: background subtraction, saturation mask, box downsampling, L2 normalisation,
and for a volume the PSF stack's vertical envelope matched to the capture, or the
sensor window fitted to it."""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from diffcam.core.errors import (DiffcamError, ShapeError, check_field, check_finite,
                                 number_in, real_array, whole_number)
from diffcam.io.reading import Capture

__all__ = ["BackgroundWarning", "border_dark_level", "dark_level", "subtract_background",
           "saturation_mask", "downsample", "normalise_l2", "envelope_widths",
           "apply_envelope", "SensorWindow", "fit_sensor_window"]

_SATURATION = 0.999  # of full scale: at or above it a pixel counts as saturated


class BackgroundWarning(UserWarning):
    """Small negative values after background subtraction were clipped to zero."""


def border_dark_level(images, ring: int = 6) -> np.ndarray:
    """Median of a ``ring``-pixel band at the frame border, per frame (input units, shape
    ``images.shape[:-2]``): the dark level of a PSF or capture whose light rarely reaches
    the border (the median ignores a few bright pixels there).

    Raises:
        ShapeError: a frame too small for the band (2·ring ≥ its shorter side).
    """
    a = np.asarray(real_array("images", images), np.float64)
    h, w = a.shape[-2:]
    if ring < 1 or 2 * ring >= min(h, w):
        raise ShapeError(f"frame {h}×{w} is too small for a {ring}-pixel border ring (or "
                         f"ring < 1); give the dark level in counts instead.")
    band = np.zeros((h, w), bool)
    band[:ring] = band[-ring:] = band[:, :ring] = band[:, -ring:] = True
    return np.median(a[..., band], axis=-1)


def plane_light(images, ring: int = 6) -> np.ndarray:
    """The light of each frame: its sum after the
    [`border_dark_level`][diffcam.io.preprocessing.border_dark_level] (input units, shape
    ``images.shape[:-2]``; ``ring`` 0: no dark level), the quantity the inverse-square law
    relates across a PSF stack's planes
    ([`diffcam.evaluate.registration.magnification_from_light`][diffcam.evaluate.registration.magnification_from_light])."""
    a = np.asarray(real_array("images", images), np.float64)
    dark = border_dark_level(a, ring)[..., None, None] if ring else 0.0
    return (a - dark).sum(axis=(-2, -1))


def dark_level(image: np.ndarray, region: tuple[slice, slice]) -> np.ndarray:
    """Mean of ``image[..., region]`` over space: a background level per channel.

    The DiffuserCam tutorial takes ``region = (slice(5, 15), slice(5, 15))`` of the PSF
    capture (a dark corner) and subtracts it from both PSF and image.
    """
    patch = np.asarray(image)[(Ellipsis,) + tuple(region)]
    if patch.size == 0:
        raise ShapeError(f"the dark region {region} selects no pixels of an image of shape "
                         f"{np.shape(image)}.")
    return patch.mean(axis=(-2, -1))


def subtract_background(image: np.ndarray, background, *,
                        tolerance: float = 0.05) -> np.ndarray:
    """``image - background``, with the negative values that noise leaves clipped to 0.

    Args:
        image: ``(..., ny, nx)`` counts.
        background: a scalar (a sensor bias, e.g. DiffuserCam's ``image_bias = 100``), a
            per-channel level from [`dark_level`][diffcam.io.preprocessing.dark_level] of
            shape ``(...)``, or a dark frame of the image's shape.
        tolerance: negatives down to ``-tolerance · max(result)`` are noise: they are
            clipped with a
            [`BackgroundWarning`][diffcam.io.preprocessing.BackgroundWarning]. Deeper ones
            mean the background is wrong and raise.

    Returns:
        float32 array, non-negative.
    """
    image = np.asarray(real_array("image", image), dtype=np.float32)
    background = np.asarray(real_array("background", background), dtype=np.float32)
    check_finite("image", image)
    check_finite("background", background)
    if background.ndim and background.shape == image.shape[:-2]:
        background = background[..., None, None]
    elif background.ndim and background.shape != image.shape:
        raise ShapeError(f"background of shape {background.shape} does not match the "
                         f"image {image.shape}; give a scalar, one level per channel "
                         f"{image.shape[:-2]}, or a dark frame of the image's shape.")
    out = image - background
    check_finite("image - background", out)
    lo, hi = float(out.min()), float(out.max())
    if lo < 0:
        if hi <= 0 or -lo > tolerance * hi:
            raise DiffcamError(
                f"background subtraction leaves values down to {lo:.4g} against a maximum "
                f"of {hi:.4g}: the background is too large for this image (wrong dark "
                f"frame, bias or region?). Check it, or raise tolerance (now {tolerance}).")
        n = int((out < 0).sum())
        warnings.warn(f"clipped {n} negative value(s) (down to {lo:.3g}, "
                      f"{-lo / hi:.2%} of the maximum) left by background subtraction",
                      BackgroundWarning, stacklevel=2)
        out = np.maximum(out, 0)
    return out


def saturation_mask(capture: Capture, level: float | None = None) -> np.ndarray:
    """Boolean mask of saturated pixels (True where a pixel reached the sensor's ceiling).

    Args:
        capture: a [`Capture`][diffcam.io.reading.Capture] (its ``full_scale`` sets the
            default level).
        level: counts at or above which a pixel is saturated; default
            ``0.999 · full_scale`` (65470 for 16-bit files, so a 12-bit sensor's
            ``4095·16 = 65520`` counts as saturated). Required for float data.
    """
    if level is None:
        if capture.full_scale is None:
            raise DiffcamError(f"{capture.path}: float data has no full scale; pass the "
                               f"saturation level in counts (level=...).")
        level = _SATURATION * capture.full_scale
    return np.asarray(capture.image) >= level


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Box-average the last two axes by an integer ``factor`` (``factor²`` pixels → 1).

    Rows/columns that do not fill a whole box are dropped, split evenly between the two
    ends so the centre stays the centre. Returns float32.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise DiffcamError(f"factor must be a positive integer, got {factor!r}.")
    image = np.asarray(real_array("image", image), dtype=np.float32)
    check_field(image, "image")
    ny, nx = image.shape[-2:]
    my, mx = ny // factor, nx // factor
    if my == 0 or mx == 0:
        raise ShapeError(f"image {image.shape[-2:]} is smaller than one {factor}x{factor} box.")
    y0, x0 = (ny - my * factor) // 2, (nx - mx * factor) // 2
    core = image[..., y0:y0 + my * factor, x0:x0 + mx * factor]
    boxes = core.reshape(image.shape[:-2] + (my, factor, mx, factor))
    return boxes.mean(axis=(-3, -1), dtype=np.float64).astype(np.float32)


def normalise_l2(image: np.ndarray) -> np.ndarray:
    """``image / ||image||₂`` over the last two axes (per channel / per plane)."""
    image = np.asarray(real_array("image", image), dtype=np.float32)
    check_field(image, "image")
    norm = np.sqrt(np.sum(image.astype(np.float64) ** 2, axis=(-2, -1), keepdims=True))
    if np.any(norm == 0):
        raise DiffcamError("cannot L2-normalise an all-zero image (or channel).")
    return (image / norm).astype(np.float32)


def envelope_widths(image: np.ndarray, psfs: np.ndarray, samples: int = 5) -> np.ndarray:
    """The widths of the vertical Gaussian envelopes that make the PSF planes' footprints
    match a capture's, estimated from the capture itself.

    A capture ``Σ_z h_z * v_z`` of non-negative scenes is at least as tall as its PSFs'
    footprints; when a capture's vertical light profile is narrower than the planes'
    footprints (a scene lit over a narrower range of angles than the calibration point
    source), a solver explains it with haze in the planes with the smallest PSFs. The
    envelope of plane ``z`` is ``exp(-(y - y_z)² / 2σ_z²)`` about the plane's row
    centroid ``y_z``, with ``σ_z = σ · s_z / max(s)`` (``s_z`` the rms height of the
    plane's light: the envelope scales with the plane's magnification). ``σ`` is the
    one whose apodised planes explain the capture's row profile (its sum over columns)
    best as a sum of non-negative 1-D convolutions (least squares,
    `scipy.optimize.nnls`, the crop model's valid part), found by a bounded
    search over 0.1 to 10 times the plane height on ``samples`` planes spread evenly
    over the stack. The profiles are binned to at most 100 rows for the fit (on the
    shipped capture σ moves by 0.4 % against the unbinned fit, and the fit takes 0.4 s).

    Args:
        image: ``(ny, nx)`` capture, counts (a flat offset of a few hundredths of the
            mean, e.g. an unsubtracted bias, changes σ by about 1 %).
        psfs: ``(nz, my, mx)`` non-negative PSF stack, ``my <= ny``.
        samples: planes in the fit (at least 1, at most ``nz``).

    Returns:
        float64 ``(nz,)``, pixels: ``σ_z`` per plane
        ([`apply_envelope`][diffcam.io.preprocessing.apply_envelope]).
    """
    samples = whole_number("samples", samples, 1)
    profile, planes, centres = light_profiles(image, psfs)
    rows = np.arange(planes.shape[1])
    spread = np.sqrt(planes @ rows ** 2 / planes.sum(axis=1) - centres ** 2)
    scale = spread / spread.max()
    fitted = sampled_planes(len(planes), samples)
    # the fit on profiles binned to at most PROFILE_ROWS rows (σ is smooth on that scale)
    factor = -(-planes.shape[1] // PROFILE_ROWS)
    profile, kernels = bin_samples(profile, factor), bin_samples(planes[fitted], factor)
    binned_rows = (np.arange(kernels.shape[1]) + 0.5) * factor - 0.5

    def misfit(log_sigma):
        sigma = np.exp(log_sigma) * scale[fitted, None]
        gauss = np.exp(-0.5 * ((binned_rows[None] - centres[fitted, None]) / sigma) ** 2)
        return _nnls_misfit(profile, kernels * gauss)

    from scipy.optimize import minimize_scalar  # SciPy on first use: fast package import

    height = planes.shape[1]
    best = minimize_scalar(misfit, bounds=(np.log(0.1 * height), np.log(10 * height)),
                           method="bounded", options={"xatol": 0.01})
    return float(np.exp(best.x)) * scale


def apply_envelope(psfs: np.ndarray, widths) -> np.ndarray:
    """Each PSF plane times the vertical Gaussian ``exp(-(y - y_z)² / 2σ_z²)`` about its
    light centre ``y_z`` (the row centroid).

    Args:
        psfs: ``(nz, my, mx)`` non-negative PSF stack.
        widths: ``(nz,)`` pixels, ``σ_z``
            ([`envelope_widths`][diffcam.io.preprocessing.envelope_widths]).

    Returns:
        float32 ``(nz, my, mx)``.
    """
    widths = np.asarray(widths, np.float64)
    psfs = np.asarray(psfs, np.float32)
    if psfs.ndim != 3 or widths.shape != psfs.shape[:1] or not np.all(
            (widths > 0) & np.isfinite(widths)):
        raise DiffcamError(f"apply_envelope needs a (nz, my, mx) stack and nz finite widths "
                           f"> 0 (pixels); got a stack of shape {psfs.shape} and widths of "
                           f"shape {widths.shape}.")
    _, planes, centres = light_profiles(psfs[0], psfs)
    rows = np.arange(psfs.shape[1])
    gauss = np.exp(-0.5 * ((rows[None] - centres[:, None]) / widths[:, None]) ** 2)
    return (psfs * gauss[:, :, None]).astype(np.float32)


PROFILE_ROWS = 100   # samples of the binned profiles the footprint fits use


def sampled_planes(n: int, samples: int) -> np.ndarray:
    """Indices of ``samples`` planes spread evenly over ``n`` (the ends included, at
    most ``n``): the planes the footprint fits use."""
    return np.unique(np.linspace(0, n - 1, max(1, min(samples, n))).round()).astype(int)


def bin_samples(profiles, factor: int) -> np.ndarray:
    """Sums of ``factor`` consecutive samples along the last axis (a partial last bin
    dropped)."""
    n = profiles.shape[-1] // factor
    return profiles[..., :n * factor].reshape(profiles.shape[:-1] + (n, factor)).sum(-1)


def light_profiles(image, psfs):
    """The capture's row profile (its sum over columns), each plane's row profile, and
    each plane's row centroid (pixels): the inputs of the footprint fits."""
    psfs = np.asarray(real_array("psfs", psfs), np.float64)
    image = np.asarray(real_array("image", image), np.float64)
    if not (np.isfinite(psfs).all() and np.isfinite(image).all()):
        raise DiffcamError("the footprint fits need a finite capture and PSF stack; clean the "
                           "NaN/Inf pixels first.")
    if psfs.ndim != 3 or image.ndim != 2 or psfs.shape[1] > image.shape[0]:
        raise ShapeError(f"the footprint fits need a (ny, nx) capture and a (nz, my, mx) PSF "
                         f"stack with my <= ny; got {image.shape} and {psfs.shape}.")
    planes = np.maximum(psfs, 0).sum(axis=2)
    total = planes.sum(axis=1)
    if np.any(total <= 0) or not image.max() > 0:
        raise DiffcamError("the footprint fits need light (values above 0) in the capture "
                           "and in every PSF plane.")
    centres = planes @ np.arange(psfs.shape[1]) / total
    return np.maximum(image, 0).sum(axis=1), planes, centres


def _valid_matrix(n: int, kernels) -> np.ndarray:
    """The ``(n, Σ_k (n + m_k - 1))`` matrix of ``s ↦ Σ_k valid(kernel_k * s_k)``: the
    crop model along one axis, ``n`` sensor samples."""
    from scipy.linalg import toeplitz

    return np.hstack([toeplitz(np.r_[k[-1], np.zeros(n - 1)],
                               np.concatenate([k[::-1], np.zeros(n - 1)]))
                      for k in kernels])


def _nnls_misfit(profile, kernels) -> float:
    """``min ||Σ_k valid(kernel_k * s_k) - profile||`` over ``s_k >= 0``: the part of a
    1-D profile that non-negative signals blurred by the ``kernels`` cannot explain."""
    from scipy.optimize import nnls

    matrix = _valid_matrix(len(profile), kernels)
    return float(nnls(matrix, profile, maxiter=50 * matrix.shape[1])[1])


class SensorWindow(NamedTuple):
    """A vertical Gaussian sensor response, ``S(y) = exp(-(y - centre_row)² / 2σ²)``:
    the fraction of the light row ``y`` records, relative to the PSF calibration's
    ([`fit_sensor_window`][diffcam.io.preprocessing.fit_sensor_window]).

    Attributes:
        centre_row: pixels, the sensor row of the window's peak (row 0 at the top).
        sigma: pixels, the window's standard deviation along y.
    """

    centre_row: float
    sigma: float

    def response(self, shape) -> np.ndarray:
        """``S`` on a sensor of ``shape`` ``(ny, nx)``: float32 ``(ny, 1)`` (it
        broadcasts along x), for the solvers' ``sensor_response``."""
        rows = np.arange(int(shape[-2]), dtype=np.float64)[:, None]
        return np.exp(-0.5 * ((rows - self.centre_row) / self.sigma) ** 2).astype(np.float32)


def fit_sensor_window(image: np.ndarray, psfs: np.ndarray, samples: int = 5,
                      light_weight: float = 0.02) -> SensorWindow:
    """The vertical sensor window ``S(y)`` that makes a PSF stack explain a capture's row
    profile, estimated from the capture itself.

    A window fixed on the sensor multiplies the crop model, ``b = S ⊙ C Σ_z h_z * v_z``:
    the same for every scene point, unlike a change of each PSF. Its centre is the
    optical axis on the sensor, the row about which the stack's planes magnify (the
    intercept of the planes' row centroids against their rms heights). Its ``σ``
    minimises ``½ ||S ⊙ Σ_z valid(p_z * s_z) - p||² + λ Σ s`` over ``s_z >= 0``: ``p``
    the capture's row profile (its sum over columns, at unit norm), ``p_z`` the row
    profiles of ``samples`` planes spread evenly over the stack (columns at unit
    norm), binned to at most 100 rows, and ``λ`` a share ``light_weight`` of the
    weight that empties the fit (a narrow window explains any profile with enough
    light at its edges; the L1 term makes that light cost). Bounded search over 0.1
    to 10 times the PSF height; the L1 fit by 400 iterations of projected FISTA.

    Args:
        image: ``(ny, nx)`` capture, counts (bias subtracted).
        psfs: ``(nz, my, mx)`` non-negative PSF stack, ``my <= ny``, on the sensor's
            pixels (the crop model's centring: PSF row ``my // 2`` on sensor row
            ``ny // 2``).
        samples: planes in the fit (at least 1, at most ``nz``).
        light_weight: ``λ`` as a share of the weight that empties the fit, in (0, 1).

    Returns:
        [`SensorWindow`][diffcam.io.preprocessing.SensorWindow], pixels.
    """
    from scipy.optimize import minimize_scalar  # SciPy on first use: fast package import

    samples = whole_number("samples", samples, 1)
    light_weight = number_in("light_weight", light_weight, 1e-6, 1 - 1e-6,
                             "a share of the emptying weight in (0, 1)")
    profile, planes, centres = light_profiles(image, psfs)
    centre_row = optical_axis(planes, centres) + image.shape[0] // 2 - planes.shape[1] // 2
    fitted = sampled_planes(len(planes), samples)
    factor = -(-planes.shape[1] // PROFILE_ROWS)
    profile = bin_samples(profile, factor)
    matrix = _valid_matrix(len(profile), bin_samples(planes[fitted], factor))
    matrix = matrix / np.linalg.norm(matrix, axis=0).max()
    profile = profile / np.linalg.norm(profile)
    weight = light_weight * np.max(matrix.T @ profile)
    binned_rows = (np.arange(len(profile)) + 0.5) * factor - 0.5

    def objective(log_sigma):
        window = np.exp(-0.5 * ((binned_rows - centre_row) / np.exp(log_sigma)) ** 2)
        return _l1_fit(window[:, None] * matrix, profile, weight)

    height = planes.shape[1]
    best = minimize_scalar(objective, bounds=(np.log(0.1 * height), np.log(10 * height)),
                           method="bounded", options={"xatol": 0.01})
    return SensorWindow(centre_row, float(np.exp(best.x)))


def optical_axis(planes, centres) -> float:
    """The index about which a stack's 1-D profiles ``planes`` ``(nz, m)`` magnify: the
    intercept of their centroids ``centres`` against their rms widths (their mean
    centroid when the widths do not change)."""
    index = np.arange(planes.shape[1])
    spread = np.sqrt(planes @ index ** 2 / planes.sum(axis=1) - centres ** 2)
    if np.ptp(spread) > 0.01 * spread.max():
        return float(np.polyfit(spread / spread.max(), centres, 1)[1])
    return float(np.mean(centres))


def l1_solution(matrix, target, weight, iterations: int = 400) -> np.ndarray:
    """``argmin ½ ||A s - t||² + weight Σ s`` over ``s >= 0`` by projected FISTA."""
    step = 1 / np.linalg.eigvalsh(matrix @ matrix.T)[-1]     # 1 / ||A||²
    s = y = np.zeros(matrix.shape[1])
    t = 1.0
    for _ in range(iterations):
        s_new = np.maximum(y - step * (matrix.T @ (matrix @ y - target) + weight), 0)
        t_new = (1 + np.sqrt(1 + 4 * t * t)) / 2
        y, s, t = s_new + (t - 1) / t_new * (s_new - s), s_new, t_new
    return s


def _l1_fit(matrix, target, weight, iterations: int = 400) -> float:
    """``min ½ ||A s - t||² + weight Σ s`` over ``s >= 0``: the minimum."""
    s = l1_solution(matrix, target, weight, iterations)
    r = matrix @ s - target
    return float(0.5 * r @ r + weight * s.sum())
