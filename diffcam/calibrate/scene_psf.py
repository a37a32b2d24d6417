"""The camera's PSF from scenes: calibration without a point source.

A diffuser camera's measurement is linear in its PSF: ``b = crop(h * x) + c`` for a scene
``x`` (on the sensor grid), the sensor window ``crop`` of the full linear convolution
and a dark offset ``c``. Convolution commutes, so with ground-truth scenes known (an
aligned photograph through a lens of the same scene) ``h`` is the solution of a
non-negative least-squares problem over all pairs ``k``, per colour channel::

    min_{h >= 0, c}  Σ_k ½ ||crop(x_k * h) + c - b_k||²

solved by FISTA (`diffcam.reconstruct.nonnegative_least_squares`) with every
convolution an FFT product (the scenes play the part of the PSF in
`diffcam.reconstruct.convolution_model`'s crop model). The offset is eliminated
exactly: the residual's mean per channel (over pairs and pixels) is projected out at
every step, and ``c`` is that mean at the end.

Registration between the lensed frame and the sensor frame:

* **shift** — absorbed by ``h`` (a shifted scene is a shifted PSF); the fitted PSF's
  position carries it;
* **flips** — not absorbed: the four flips of the scenes are tried with a short fit each
  and the one that explains the raws best is kept (`ScenePsfOptions`);
* **gain and offset per channel** — the gain is the PSF's scale, the offset ``c``;
* **the monitor's dark surround** — the scene is zero outside the lensed frame (the
  crop model pads it with zeros).

The scenes must be sampled at the sensor's pitch (same shape as the raws); a scale
mismatch between the two frames is not fitted. The early-stopped FISTA is the only
regulariser: on the Lensless Learning pairs 300 iterations predict held-out raws with
Pearson ≈ 0.99 per channel (benchmarks/bench_scene_psf.py).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from diffcam.core.errors import DiffcamError, ShapeError, real_array
from diffcam.core.grid import crop_to, pad_to
from diffcam.core.options import Options
from diffcam.core.progress import progress_bar
from diffcam.reconstruct.checks import check_iterations
from diffcam.reconstruct.fista import nonnegative_least_squares
from diffcam.reconstruct.operators import convolution_model

__all__ = ["FLIPS", "ScenePsfOptions", "ScenePsf", "check_scene_pairs", "flip_scene",
           "fit_psf_from_scenes", "predict_raw"]

FLIPS = ("none", "y", "x", "yx")
"""Flips of the scene frame relative to the sensor frame: none, up-down, left-right,
both (a 180° rotation)."""


class ScenePsfOptions(Options):
    """How [`fit_psf_from_scenes`][diffcam.calibrate.scene_psf.fit_psf_from_scenes] runs.

    Attributes:
        iterations: FISTA iterations of the final fit (the regularisation: early stop).
        flip: one of `FLIPS`, or ``"auto"`` to try each.
        search_iterations: FISTA iterations of each trial fit when ``flip="auto"``.
    """

    iterations: int = 300
    flip: str = "auto"
    search_iterations: int = 60

    def __check_init__(self):
        for name in ("iterations", "search_iterations"):
            check_iterations(getattr(self, name), name)
        if self.flip not in FLIPS + ("auto",):
            raise DiffcamError(f"flip must be 'auto' or one of {FLIPS}, got {self.flip!r}.")


class ScenePsf(NamedTuple):
    """A PSF calibrated from scenes.

    Attributes:
        psf: ``(c, ny, nx)`` non-negative PSF per channel, sensor units per unit of
            scene, optical axis at ``(ny//2, nx//2)`` (the sensor's shape).
        offset: ``(c,)`` dark offset of the raws, sensor units.
        flip: the flip of the scenes (`FLIPS`) into the sensor frame.
        residual: ``(iterations,)`` relative misfit ``||b - c - A h|| / ||b - c̄||``
            of the final fit (the offset-free parts).
        flip_residuals: final relative misfit of each trial flip (empty if not searched).
    """

    psf: np.ndarray
    offset: np.ndarray
    flip: str
    residual: np.ndarray
    flip_residuals: dict


def _as_pairs(images, what: str) -> np.ndarray:
    """``(k, c, ny, nx)`` float32 from a sequence of ``(c, ny, nx)`` or ``(ny, nx)`` real
    images, finite and within float32's range."""
    if isinstance(images, np.ndarray) and images.ndim in (2, 3):
        raise ShapeError(f"{what}: give a sequence of images (one per pair), got one "
                         f"array of shape {images.shape}; wrap it in a list.")
    try:
        arrays = [np.asarray(real_array(f"{what}[{k}]", a)) for k, a in enumerate(images)]
    except TypeError:
        raise DiffcamError(f"{what}: give a sequence of images (one per pair), got "
                           f"{images!r:.60}.") from None
    if not arrays:
        raise DiffcamError(f"{what}: no images given; give at least one pair.")
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1 or arrays[0].ndim not in (2, 3):
        raise ShapeError(f"{what}: the images must share one shape (ny, nx) or "
                         f"(channels, ny, nx), got {sorted(shapes)}.")
    stack = np.stack(arrays)
    if not np.isfinite(stack).all():
        raise DiffcamError(f"{what}: NaN/Inf values; clean the data first.")
    top = float(np.max(np.abs(stack)))
    if top > float(np.finfo(np.float32).max):
        raise DiffcamError(f"{what}: values up to {top:.3g}, beyond float32's range "
                           f"(3.4e+38), in which the fit runs; divide them by a constant "
                           f"first (the PSF scales with the raws).")
    stack = stack.astype(np.float32)
    return stack[:, None] if stack.ndim == 3 else stack


def check_scene_pairs(raws, truths) -> tuple[np.ndarray, np.ndarray]:
    """Raws and scenes as ``(k, c, ny, nx)`` float32 arrays, checked before any fit.

    Raises:
        DiffcamError: different numbers of raws and scenes, of channels or of pixels; a
            scene that is dark everywhere (it does not overlap the sensor frame) or has
            negative values; a raw that is constant; complex, NaN/Inf or beyond
            float32's range.
    """
    raws, truths = _as_pairs(raws, "raws"), _as_pairs(truths, "truths")
    if len(raws) != len(truths):
        raise DiffcamError(f"{len(raws)} raw(s) but {len(truths)} truth(s); give one "
                           f"ground-truth scene per raw capture, in the same order.")
    if raws.shape[1] != truths.shape[1]:
        raise ShapeError(f"the raws have {raws.shape[1]} channel(s), the truths "
                         f"{truths.shape[1]}; read both in colour (or both in grayscale).")
    if raws.shape[2:] != truths.shape[2:]:
        raise ShapeError(f"raws are {raws.shape[2]}×{raws.shape[3]} pixels, truths "
                         f"{truths.shape[2]}×{truths.shape[3]}; resample the truths to the "
                         f"sensor's pixels (the scene on the sensor grid) first.")
    if (truths < 0).any():
        k, ch = np.argwhere((truths < 0).any(axis=(-2, -1)))[0]
        raise DiffcamError(f"truth {k} (channel {ch}) has negative values (min "
                           f"{float(truths[k, ch].min()):.3g}); a scene is an intensity: "
                           f"subtract its dark level with clipping "
                           f"(diffcam.io.subtract_background) or np.clip(truth, 0, None).")
    lit = np.max(truths, axis=(-2, -1)) > 0
    if not lit.all():
        k, ch = np.argwhere(~lit)[0]
        raise DiffcamError(f"truth {k} (channel {ch}) is dark everywhere: it does not "
                           f"overlap the sensor frame; check its registration.")
    flat = np.ptp(raws, axis=(-2, -1)) == 0
    if flat.any():
        k, ch = np.argwhere(flat)[0]
        raise DiffcamError(f"raw {k} (channel {ch}) is constant: it holds no image.")
    return raws, truths


def flip_scene(scene: Float[ArrayLike, "... ny nx"], flip: str) -> np.ndarray:
    """``scene`` flipped into the sensor frame (``flip`` one of `FLIPS`)."""
    scene = np.asarray(scene)
    if "y" in flip:
        scene = scene[..., ::-1, :]
    if "x" in flip:
        scene = scene[..., :, ::-1]
    return scene


@partial(jax.jit, static_argnames=("iterations",))
def _fit(raws: Array, truths: Array, iterations: int):
    """FISTA over all pairs: ``raws``, ``truths`` ``(k, c, ny, nx)``; returns the PSF
    ``(c, ny, nx)``, the offset ``(c,)`` and the residual history."""
    sensor = raws.shape[-2:]
    model = convolution_model(truths, sensor, "crop")    # the scenes as kernels
    lipschitz = jnp.max(jnp.sum(jnp.abs(model.otf) ** 2, axis=0), axis=(-2, -1))

    def centred(r):      # remove each channel's mean over pairs and pixels: fits c
        return r - jnp.mean(r, axis=(0, -2, -1), keepdims=True)

    def forward(h):
        return centred(model(pad_to(h, model.object_shape)))

    def adjoint(r):
        return crop_to(model.adjoint(centred(r)), sensor).sum(axis=0)

    h0 = jnp.zeros(raws.shape[1:], raws.dtype)
    h, residual, _, _, _ = nonnegative_least_squares(
        forward, adjoint, centred(raws), h0, lipschitz[:, None, None], iterations)
    offset = jnp.mean(raws - model(pad_to(h, model.object_shape)), axis=(0, -2, -1))
    return h, offset, residual


def fit_psf_from_scenes(raws: Sequence[ArrayLike], truths: Sequence[ArrayLike],
                        options: ScenePsfOptions | None = None, *, progress: bool = True,
                        **overrides) -> ScenePsf:
    """The PSF (per channel) that best maps the ground-truth scenes to the raws.

    Args:
        raws: raw captures, each ``(c, ny, nx)`` (channels first, as
            [`diffcam.io.read_image`][diffcam.io.reading.read_image] gives them) or
            ``(ny, nx)``, sensor units, background subtracted or not (the offset is fitted).
        truths: the scene of each raw on the sensor grid, same shape, non-negative
            (a lensed photograph registered to the sensor up to a shift and a flip).
        options: [`ScenePsfOptions`][diffcam.calibrate.scene_psf.ScenePsfOptions];
            ``overrides`` replace its fields.
        progress: progress bars for runs over 2 s.

    Returns:
        [`ScenePsf`][diffcam.calibrate.scene_psf.ScenePsf].

    Raises:
        DiffcamError: see `check_scene_pairs`; bad options.
    """
    options = ScenePsfOptions.of(options, **overrides)
    raws, truths = check_scene_pairs(raws, truths)
    # the fit runs on each channel scaled to unit peak: float32 sums of products of raw
    # values overflow from ~1e19 (a raw of 1e30 would give an all-NaN PSF)
    raw_peak, truth_peak = _channel_peaks(raws), _channel_peaks(truths)
    gain = raw_peak / truth_peak
    if not np.finfo(np.float32).tiny < gain.min() <= gain.max() < np.finfo(np.float32).max:
        raise DiffcamError(f"the PSF's scale max(raw)/max(truth) reaches {gain.min():.3g}…"
                           f"{gain.max():.3g}, outside float32's range; divide the raws or "
                           f"the truths by a constant first (the PSF scales with raw/truth).")
    raws = raws / raw_peak[:, None, None].astype(np.float32)
    truths = truths / truth_peak[:, None, None].astype(np.float32)
    raws_j = jnp.asarray(raws)
    flips = FLIPS if options.flip == "auto" else (options.flip,)
    trials = {}
    if len(flips) > 1:
        with progress_bar(options.search_iterations * len(flips), "flips", progress):
            for flip in flips:
                _, _, res = _fit(raws_j, jnp.asarray(flip_scene(truths, flip)),
                                 options.search_iterations)
                trials[flip] = float(res[-1])
    flip = min(trials, key=trials.get) if trials else flips[0]
    with progress_bar(options.iterations, "PSF from scenes", progress):
        h, offset, residual = jax.block_until_ready(_fit(
            raws_j, jnp.asarray(flip_scene(truths, flip)), options.iterations))
    psf = (np.asarray(h, np.float64) * gain[:, None, None]).astype(np.float32)
    offset = (np.asarray(offset, np.float64) * raw_peak).astype(np.float32)
    residual = np.asarray(residual)
    if not (np.isfinite(psf).all() and np.isfinite(offset).all()
            and np.isfinite(residual).all()):
        raise DiffcamError("the PSF fit from scenes did not stay finite; check that the "
                           "raws and truths are the captures of each other.")
    return ScenePsf(psf=psf, offset=offset, flip=flip, residual=residual,
                    flip_residuals=trials)


def _channel_peaks(images: np.ndarray) -> np.ndarray:
    """max |images| per channel of a ``(k, c, ny, nx)`` stack, float64 (1 where 0)."""
    peak = np.max(np.abs(images), axis=(0, 2, 3)).astype(np.float64)
    return np.where(peak > 0, peak, 1.0)


def predict_raw(calibration: ScenePsf, truth: Float[ArrayLike, "c ny nx"]) -> np.ndarray:
    """The raw capture the calibrated camera records of ``truth`` (a scene in the lensed
    frame, shape ``(c, ny, nx)`` like the calibration's raws, or ``(ny, nx)`` for one
    channel): ``crop(h * x) + c``, computed on the PSF and the scene scaled to unit peak.

    Raises:
        DiffcamError: a truth that is not a finite, non-negative real image of the
            calibration's shape, a calibration with NaN/Inf or negative values, or a
            prediction beyond float32's range.
    """
    truth = _as_pairs([flip_scene(real_array("truth", truth), calibration.flip)],
                      "truth")[0]
    psf = _as_pairs([calibration.psf], "calibration.psf")[0]
    offset = np.asarray(real_array("calibration.offset", calibration.offset), np.float64)
    if truth.shape != psf.shape or offset.shape != psf.shape[:1]:
        raise ShapeError(f"truth {truth.shape} does not match the calibration's "
                         f"{psf.shape} (channels, ny, nx) and offset {offset.shape}.")
    if (truth < 0).any() or (psf < 0).any() or not np.isfinite(offset).all():
        raise DiffcamError("predict_raw needs a non-negative truth and a calibration with "
                           "a non-negative PSF and a finite offset (fit_psf_from_scenes "
                           "gives one).")
    psf_peak = _channel_peaks(psf[None])[:, None, None]
    truth_peak = _channel_peaks(truth[None])[:, None, None]
    model = convolution_model(jnp.asarray(psf / psf_peak), truth.shape, "crop")
    unit = model(pad_to(jnp.asarray(truth / truth_peak), model.object_shape))
    peaks = psf_peak * truth_peak
    raw = np.asarray(unit, np.float64) * peaks + offset[:, None, None]
    if not np.abs(raw).max() <= float(np.finfo(np.float32).max):
        raise DiffcamError(f"the predicted raw exceeds float32's range (PSF and truth peak "
                           f"at {float(peaks.max()):.3g} together); divide the truth by a "
                           f"constant first.")
    return raw.astype(np.float32)
