"""Captures in: the paper's preprocessing, and synthetic captures from the forward model.

Preprocessing (paper Section 3.2) of a raw near/far pair, in order:

1. saturated pixels are found on the raw counts (a mask for the least-squares fit;
   a capture saturated everywhere is an error);
2. the background (sensor bias, dark frame or level) is subtracted with
   `diffcam.io.subtract_background` (small negatives clipped with a warning,
   large ones an error);
3. exposure differences are divided out (counts per unit exposure; an exposure series
   is merged into one high-dynamic-range image, `merge_exposures`), then each
   image is min–max normalised;
4. the far capture is centred (its intensity centroid moved to index N//2) and interpolated
   from the sensor pitch to the Fourier-lens pitch λf/(N·dx); the near capture from the
   sensor pitch to the diffuser-grid pitch dx (`diffcam.model.sensor.resample`).

Synthetic captures (`synthetic_captures`) run the forward model at the
computational pitch, integrate over sensor pixels, and add shot noise, a background
and quantisation with `diffcam.model.sensor`.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.errors import DiffcamError, check_field, check_positive, real_array
from diffcam.core.options import Options
from diffcam.io import subtract_background
from diffcam.model.sensor import bin_pixels, quantise, resample, saturate, shot_noise
from diffcam.calibrate.phase.near_far import (CalibrationGeometry, calibration_intensities,
                                        check_far_speckle)

__all__ = ["normalise_min_max", "merge_exposures", "centroid", "centre_on_axis", "resample_capture",
           "resample_far_field", "prepare_captures", "PreparedCaptures",
           "synthetic_captures", "CaptureOptions", "SyntheticSensor"]


def normalise_min_max(image: Float[Array, "ny nx"]) -> np.ndarray:
    """(image − min)/(max − min), as the paper normalises its captures."""
    a = np.asarray(image, np.float32)
    lo, hi = float(a.min()), float(a.max())
    if hi == lo:
        raise DiffcamError(f"cannot min–max normalise a constant image ({hi:.6g} everywhere): "
                           f"blank or fully saturated capture.")
    return (a - lo) / (hi - lo)


def centroid(image: Float[Array, "ny nx"]) -> tuple[float, float]:
    """Intensity centroid (y, x) in samples from the centre index (N//2)."""
    a = np.asarray(image, np.float64)
    total = a.sum()
    if total <= 0:
        raise DiffcamError("the image has no positive intensity; nothing to centre on.")
    ny, nx = a.shape[-2:]
    cy = (a.sum(axis=-1) * (np.arange(ny) - ny // 2)).sum() / total
    cx = (a.sum(axis=-2) * (np.arange(nx) - nx // 2)).sum() / total
    return float(cy), float(cx)


def centre_on_axis(image: Float[Array, "ny nx"]) -> tuple[np.ndarray, tuple[int, int]]:
    """Roll the image (circularly, whole samples) so its centroid lands on index N//2.

    Returns the rolled image and the ``(dy, dx)`` roll applied, in samples.
    """
    cy, cx = centroid(image)
    shift = (-int(round(cy)), -int(round(cx)))
    return np.roll(np.asarray(image), shift, axis=(-2, -1)), shift


def resample_capture(image: Float[Array, "my mx"], sensor_pitch: float, pitch, shape
                     ) -> Float[Array, "ny nx"]:
    """A capture at ``sensor_pitch`` (m) read on a centred ``shape`` grid of ``pitch`` (m,
    scalar or (dy, dx)), values in irradiance (per unit area).

    The capture is interpolated (cubic B-spline) at the grid points, never area-averaged:
    the retrieval models point samples, and averaging over the new, coarser pixels would
    blur speckle that the sensor resolved (at the Fourier-lens pitch of a 2× padded grid
    a speckle spans about two samples, and area-averaging sensor pixels onto it drops the
    RAAR figure from 1.0 to 0.84 on the paper's Fig. 3 problem). Outside its frame the
    capture is zero: the frame is zero-extended before the (FFT, periodic) spline
    prefilter, as [`diffcam.evaluate.magnify_psf`][diffcam.evaluate.baseline.magnify_psf]
    does, so light at one edge never leaks into the opposite one and the same pitch and
    shape return the capture.
    """
    real_array("capture", image)
    check_field(image, "capture")
    check_positive("sensor_pitch", sensor_pitch, "m")
    py, px = (pitch, pitch) if np.ndim(pitch) == 0 else pitch
    if abs(py - px) > 1e-9 * px:
        raise DiffcamError("resample_capture needs square output pixels; resample each axis "
                           "separately for a non-square grid.")
    out = resample(jnp.asarray(image, jnp.float32), sensor_pitch, px,
                   tuple(shape[-2:]), kind="cubic")
    # power per pixel → irradiance; the spline's ringing below zero is clipped
    return jnp.maximum(out * (sensor_pitch / px) ** 2, 0.0)


def resample_far_field(image: Float[Array, "my mx"], sensor_pitch: float,
                       geometry: CalibrationGeometry, shape) -> Float[Array, "ny nx"]:
    """A far-field capture at ``sensor_pitch`` (m) on the Fourier-lens grid of ``shape``:
    pitch λf/(N·dx) (docs/design.md, "Fourier-lens pitch")."""
    return resample_capture(image, sensor_pitch, geometry.far_pitch(shape), shape)


class PreparedCaptures(NamedTuple):
    """Near and far intensities on the calibration grid, ready for retrieval.

    ``near_mask`` / ``far_mask`` are 1 on usable pixels and 0 where the raw capture
    saturated (resampled onto the grid, so partial values mark mixed pixels).
    """

    near: Float[Array, "ny nx"]
    far: Float[Array, "ny nx"]
    near_mask: Float[Array, "ny nx"]
    far_mask: Float[Array, "ny nx"]


def merge_exposures(raws: Float[Array, "k ny nx"], exposures, *, background=0.0,
                    saturation: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """High-dynamic-range merge of k captures of one scene at different exposures.

    Each pixel is Σᵢ wᵢ·(rawᵢ − background)/tᵢ / Σᵢ wᵢ over the unsaturated captures,
    wᵢ = tᵢ (the Poisson-optimal weight: counts grow with tᵢ). A Fourier-lens capture of
    a diffuser spans many decades (a bright zero order, a faint speckle halo that holds
    the phase): one 12-bit exposure quantises most of the halo to zero.

    Args:
        raws: (k, ny, nx) raw counts.
        exposures: k exposure times (any common unit).
        background: level or dark frame (counts), subtracted with
            [`diffcam.io.subtract_background`][diffcam.io.preprocessing.subtract_background].
        saturation: raw count at or above which a pixel is saturated.

    Returns:
        ``(irradiance, usable)``: counts per unit exposure, and 1 where at least one
        capture was unsaturated.
    """
    raws = np.asarray(raws, np.float32)
    if raws.ndim != 3 or raws.shape[0] != np.size(exposures):
        raise DiffcamError(f"merge_exposures needs (k, ny, nx) captures and k exposures, got "
                           f"{raws.shape} and {np.size(exposures)} exposures.")
    t = np.asarray(exposures, np.float64).reshape(-1, 1, 1)
    check_positive("exposures", t, "s")
    ok = np.ones_like(raws) if saturation is None else (raws < saturation).astype(np.float32)
    signal = subtract_background(raws, background) / t
    w = ok * t
    total = w.sum(axis=0)
    merged = np.where(total > 0, (w * signal).sum(axis=0) / np.where(total > 0, total, 1), 0)
    return merged.astype(np.float32), (total > 0).astype(np.float32)


def _clean(raw, name, background, exposure, saturation):
    raw = np.asarray(real_array(f"{name} capture", raw), np.float32)
    check_field(raw, f"{name} capture")
    if raw.ndim not in (2, 3):
        raise DiffcamError(f"{name} capture must be one 2-D image or a (k, ny, nx) exposure "
                           f"series, got shape {raw.shape}; convert colour to one channel.")
    if saturation is not None and not (raw < saturation).any(axis=0).any():
        raise DiffcamError(f"{name} capture is saturated everywhere (all ≥ {saturation}); "
                           f"re-capture with a shorter exposure.")
    if raw.ndim == 3:
        image, ok = merge_exposures(raw, exposure, background=background,
                                    saturation=saturation)
    else:
        ok = np.ones_like(raw) if saturation is None else (raw < saturation).astype(np.float32)
        check_positive(f"{name} exposure", exposure, "s")
        image = subtract_background(raw, background) / exposure
    if ok.mean() < 0.5:
        warnings.warn(f"{name} capture: {1 - ok.mean():.0%} of pixels saturated", stacklevel=3)
    if float(image.max()) <= 0:
        raise DiffcamError(f"{name} capture is all zero after background subtraction; "
                           f"check the background level and the exposure.")
    return normalise_min_max(image), ok


class CaptureOptions(Options):
    """How [`prepare_captures`][diffcam.calibrate.phase.captures.prepare_captures] cleans the raw
    captures.

    Attributes:
        background: per capture (near, far), a level or a dark frame (counts).
        exposure: per capture, exposure time (s, or any common unit), or k times for
            an exposure series.
        saturation: raw count at or above which a pixel is saturated (e.g. 4095 for a
            12-bit sensor); ``None`` skips the check.
        centre: move the far capture's centroid onto the optical axis first.
    """

    background: object = (0.0, 0.0)
    exposure: object = (1.0, 1.0)
    saturation: float | None = None
    centre: bool = True


class SyntheticSensor(Options):
    """The sensor [`synthetic_captures`][diffcam.calibrate.phase.captures.synthetic_captures]
    records with.

    Attributes:
        photons: electrons at the brightest pixel of each capture.
        bit_depth: bits of the digital numbers.
        background: uniform background, fraction of full scale.
        far_exposures: relative exposure times of a far-field exposure series (e.g.
            ``(1, 30, 1000)``), or ``None`` for one far capture.
    """

    photons: float = 1e4
    bit_depth: int = 12
    background: float = 0.02
    far_exposures: tuple | None = None


def prepare_captures(near_raw, far_raw, geometry: CalibrationGeometry, shape, *,
                     sensor_pitch: float, options: CaptureOptions | None = None,
                     **overrides) -> PreparedCaptures:
    """Raw near and far captures →
    [`PreparedCaptures`][diffcam.calibrate.phase.captures.PreparedCaptures] on the ``shape`` grid.

    Args:
        near_raw, far_raw: raw sensor images (counts), one channel each; either may be
            a (k, ny, nx) exposure series, merged by
            [`merge_exposures`][diffcam.calibrate.phase.captures.merge_exposures].
        geometry: the set-up (diffuser pitch dx, λ, f, near distance), SI units.
        shape: ``(ny, nx)`` of the calibration grid (the near capture at pitch dx, the
            far one at λf/(N·dx)); wide enough for the captures' content.
        sensor_pitch: camera pixel pitch, metres.
        options: [`CaptureOptions`][diffcam.calibrate.phase.captures.CaptureOptions] (background,
            exposure, saturation, centre); keywords named after its fields replace them.

    Warns ([`GeometryWarning`][diffcam.core.errors.GeometryWarning]) when the far capture's
    speckle is ≳ 2× finer or coarser than the near capture predicts at the Fourier-lens
    pitch (`check_far_speckle`): f, λ or ``sensor_pitch``
    is wrong, and the retrieval would return a confident wrong phase.
    """
    o = CaptureOptions.of(options, **overrides)
    background, exposure = o.background, o.exposure
    near, near_ok = _clean(near_raw, "near", background[0], exposure[0], o.saturation)
    far, far_ok = _clean(far_raw, "far", background[1], exposure[1], o.saturation)
    if o.centre:
        far, shift = centre_on_axis(far)
        far_ok = np.roll(far_ok, shift, axis=(-2, -1))
    near_g = resample_capture(near, sensor_pitch, geometry.dx, shape)
    far_g = resample_far_field(far, sensor_pitch, geometry, shape)
    check_far_speckle(near_g, far_g, geometry, sensor_pitch=sensor_pitch, stacklevel=3)
    near_m = resample_capture(near_ok, sensor_pitch, geometry.dx, shape)
    far_m = resample_far_field(far_ok, sensor_pitch, geometry, shape)
    # interpolating the masks leaves values between 0 and 1 beside saturated pixels
    return PreparedCaptures(near_g, far_g, (near_m > 0.999).astype(jnp.float32),
                            (far_m > 0.999).astype(jnp.float32))


def synthetic_captures(phase: Float[Array, "ny nx"], aperture: Float[Array, "ny nx"],
                       geometry: CalibrationGeometry, key: Array, *, sensor_pitch: float,
                       sensor_shape, options: SyntheticSensor | None = None,
                       **overrides) -> tuple[np.ndarray, np.ndarray]:
    """Raw near and far captures of a diffuser, as a camera would record them.

    The forward model
    ([`calibration_intensities`][diffcam.calibrate.phase.near_far.calibration_intensities]) runs
    on the phase's grid; each intensity is integrated over sensor pixels of ``sensor_pitch``
    (m) on ``sensor_shape``, scaled to ``photons`` electrons at its brightest pixel, given
    Poisson shot noise, a uniform ``background`` (fraction of full scale), and quantised to
    ``bit_depth`` bits with the brightest mean signal plus background at 95 % of full scale.
    ``far_exposures`` (relative times, e.g. ``(1, 30, 1000)``) records the far field as an
    exposure series instead: exposure t collects t·``photons`` at the peak and saturates.

    The sensor (``photons``, ``bit_depth``, ``background``, ``far_exposures``) is a
    [`SyntheticSensor`][diffcam.calibrate.phase.captures.SyntheticSensor] given as ``options``;
    keywords named after its fields replace them.

    Returns:
        ``(near_counts, far_counts)`` float arrays of digital numbers (far: (k, ny, nx)
        with ``far_exposures``); the background in counts is
        ``round(background · (2**bit_depth − 1))``.
    """
    sensor = SyntheticSensor.of(options, **overrides)
    photons, bit_depth = sensor.photons, sensor.bit_depth
    background, far_exposures = sensor.background, sensor.far_exposures
    near, far = calibration_intensities(phase, aperture, geometry)
    shape = np.shape(phase)
    images = (bin_pixels(near, geometry.dx, sensor_pitch, tuple(sensor_shape)),
              resample(far, geometry.far_pitch(shape)[1], sensor_pitch, tuple(sensor_shape)))
    full_well = photons * (1 + background) / 0.95
    times = (1.0,) if far_exposures is None else tuple(far_exposures)
    keys = jax.random.split(key, 1 + len(times))

    def record(k, img, t):
        e = shot_noise(k, img / jnp.max(img) * photons * t) + background * full_well
        return np.asarray(quantise(saturate(e, full_well), bit_depth, full_well))

    near_counts = record(keys[0], images[0], 1.0)
    far_counts = np.stack([record(k, images[1], t) for k, t in zip(keys[1:], times)])
    return near_counts, far_counts if far_exposures is not None else far_counts[0]
