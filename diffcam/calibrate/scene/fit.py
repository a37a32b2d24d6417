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
from diffcam.core.grid import crop_to, int_pair, pad_to
from diffcam.core.options import Options
from diffcam.core.progress import progress_bar
from diffcam.reconstruct.checks import check_iterations
from diffcam.reconstruct.fista import nonnegative_least_squares
from diffcam.model.field import FieldPSF
from diffcam.reconstruct.operators import convolution_model, field_model, grid_shapes
from diffcam.calibrate.scene.pairs import (FLIPS, as_pairs, border_window, channel_peaks,
                                           check_scene_pairs, flip_scene, scaled_pairs)

__all__ = ["ScenePsfOptions", "ScenePsf", "SceneFieldPsf", "fit_psf_from_scenes",
           "fit_field_psf_from_scenes", "field_positions", "predict_raw"]


class ScenePsfOptions(Options):
    """How [`fit_psf_from_scenes`][diffcam.calibrate.scene.fit.fit_psf_from_scenes] runs.

    Attributes:
        iterations: FISTA iterations of the final fit (the regularisation: early stop).
        flip: one of `FLIPS`, or ``"auto"`` to try each.
        search_iterations: FISTA iterations of each trial fit when ``flip="auto"``.
        border_taper: fraction of the sensor's height and width, at each border, over
            which the misfit's weight falls to zero (a Tukey window; 0: every pixel
            weighs the same). It removes the PSF's seams at the offsets where edges
            that all scenes share leave the sensor, and costs 0.6 dB in reconstructions
            on the Lensless Learning pairs at 0.15 (docs/scene_psf.md).
    """

    iterations: int = 300
    flip: str = "auto"
    search_iterations: int = 60
    border_taper: float = 0.0

    def __check_init__(self):
        for name in ("iterations", "search_iterations"):
            check_iterations(getattr(self, name), name)
        if self.flip not in FLIPS + ("auto",):
            raise DiffcamError(f"flip must be 'auto' or one of {FLIPS}, got {self.flip!r}.")
        if not 0 <= self.border_taper < 0.5:
            raise DiffcamError(f"border_taper is a fraction of the sensor at each border, "
                               f"0 to below 0.5; got {self.border_taper!r}.")


class ScenePsf(NamedTuple):
    """A PSF calibrated from scenes.

    Attributes:
        psf: ``(c, ny, nx)`` non-negative PSF per channel, sensor units per unit of
            scene, optical axis at ``(ny//2, nx//2)`` (the sensor's shape).
        offset: ``(c,)`` dark offset of the raws, sensor units.
        flip: the flip of the scenes (`FLIPS`) into the sensor frame.
        residual: ``(iterations,)`` relative misfit ``||b - c - A h|| / ||b - c̄||``
            of the final fit (the offset-free parts; weighted by the border taper).
        flip_residuals: final relative misfit of each trial flip (empty if not searched).
    """

    psf: np.ndarray
    offset: np.ndarray
    flip: str
    residual: np.ndarray
    flip_residuals: dict


class SceneFieldPsf(NamedTuple):
    """A field-dependent PSF calibrated from scenes: ``b = crop(Σ_k g_k ∗ (w_k · x)) + c``.

    Attributes:
        fields: one `diffcam.model.field.FieldPSF` per channel: kernels ``g_k``
            ``(K, ny, nx)``, the PSF at each of ``K`` field positions (a grid spanning the
            sensor, `field_positions`), sensor units per unit of scene; coefficients the
            identity, so the weights ``w_k`` are the thin-plate spline that interpolates
            between the positions; singular values those of the kernels' stack.
        offset: ``(c,)`` dark offset of the raws, sensor units.
        flip: the flip of the scenes (`FLIPS`) into the sensor frame.
        residual: ``(iterations,)`` relative misfit of the fit, as `ScenePsf`'s.
        flip_residuals: final relative misfit of each trial flip (one PSF each).
    """

    fields: tuple
    offset: np.ndarray
    flip: str
    residual: np.ndarray
    flip_residuals: dict


@partial(jax.jit, static_argnames=("iterations",))
def _fit(raws: Array, scenes: Array, window: Array, iterations: int):
    """FISTA over all pairs: ``raws`` ``(k, c, ny, nx)``, ``scenes`` ``(k, K, c, ny, nx)``
    (each scene times each of the ``K`` field weights), the misfit weighted by
    ``window`` ``(ny, nx)``; returns the kernels ``(K, c, ny, nx)``, the offset ``(c,)``
    and the residual history."""
    sensor = raws.shape[-2:]
    model = convolution_model(scenes, sensor, "crop")    # the scenes as kernels
    # ||A||² per channel: exact for K = 1 (a circulant), the trace bound for K > 1
    lipschitz = jnp.max(jnp.sum(jnp.abs(model.otf) ** 2, axis=(0, 1)), axis=(-2, -1))
    squares = window ** 2 / (jnp.sum(window ** 2) * raws.shape[0])

    def mean(r):         # each channel's weighted mean over pairs and pixels: fits c
        return jnp.sum(squares * r, axis=(0, -2, -1), keepdims=True)

    def blur(h):
        return model(pad_to(h, model.object_shape)).sum(axis=1)

    def adjoint(r):      # the adjoint of r ↦ window · (r - mean(r))
        r = window * r - squares * jnp.sum(window * r, axis=(0, -2, -1), keepdims=True)
        return crop_to(model.adjoint(r[:, None]), sensor).sum(axis=0)

    def weighted(r):
        return window * (r - mean(r))

    h0 = jnp.zeros(scenes.shape[1:], raws.dtype)
    h, residual, _, _, _ = nonnegative_least_squares(
        lambda h: weighted(blur(h)), adjoint, weighted(raws), h0,
        lipschitz[:, None, None], iterations)
    offset = mean(raws - blur(h))[0, :, 0, 0]
    return h, offset, residual


def _choose_flip(raws: Array, truths: np.ndarray, window: Array, options: ScenePsfOptions,
                 progress: bool) -> tuple[str, dict]:
    """The flip of the scenes (one PSF fitted per trial) and each trial's misfit."""
    flips = FLIPS if options.flip == "auto" else (options.flip,)
    trials = {}
    if len(flips) > 1:
        with progress_bar(options.search_iterations * len(flips), "flips", progress):
            for flip in flips:
                _, _, res = _fit(raws, jnp.asarray(flip_scene(truths, flip))[:, None],
                                 window, options.search_iterations)
                trials[flip] = float(res[-1])
    return (min(trials, key=trials.get) if trials else flips[0]), trials


def _finite(*arrays) -> None:
    if not all(np.isfinite(a).all() for a in arrays):
        raise DiffcamError("the PSF fit from scenes did not stay finite; check that the "
                           "raws and truths are the captures of each other.")


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
        options: [`ScenePsfOptions`][diffcam.calibrate.scene.fit.ScenePsfOptions];
            ``overrides`` replace its fields.
        progress: progress bars for runs over 2 s.

    Returns:
        [`ScenePsf`][diffcam.calibrate.scene.fit.ScenePsf].

    Raises:
        DiffcamError: see `check_scene_pairs`; bad options.
    """
    kernels, _, offset, residual, flip, trials = _fit_kernels(
        raws, truths, None, ScenePsfOptions.of(options, **overrides), progress)
    return ScenePsf(psf=kernels[0], offset=offset, flip=flip, residual=residual,
                    flip_residuals=trials)


def _fit_kernels(raws, truths, grid, options, progress):
    """The scenes' kernels by `_fit`, in the raws' units: one PSF per channel (``grid``
    ``None``: kernels ``(1, c, my, mx)``, positions ``None``), or one at each of a
    ``grid`` of field positions, the scenes weighted by `_sensor_weights`; with the
    positions, the offset, the residual, the flip and the flips' residuals."""
    raws, truths, raw_peak, gain = scaled_pairs(*check_scene_pairs(raws, truths))
    positions = None if grid is None else field_positions(grid, raws.shape[-2:])
    raws_j = jnp.asarray(raws)
    window = jnp.asarray(border_window(raws.shape[-2:], options.border_taper))
    flip, trials = _choose_flip(raws_j, truths, window, options, progress)
    scenes = flip_scene(truths, flip)[:, None]
    what = "PSF from scenes"
    if positions is not None:
        scenes = scenes * _sensor_weights(positions, raws.shape[-2:])[None, :, None]
        what = "field PSF from scenes"
    with progress_bar(options.iterations, what, progress):
        g, offset, residual = jax.block_until_ready(_fit(raws_j, jnp.asarray(scenes),
                                                         window, options.iterations))
    kernels = (np.asarray(g, np.float64) * gain[:, None, None]).astype(np.float32)
    offset = (np.asarray(offset, np.float64) * raw_peak).astype(np.float32)
    residual = np.asarray(residual)
    _finite(kernels, offset, residual)
    return kernels, positions, offset, residual, flip, trials


def field_positions(grid: tuple[int, int], sensor_shape: tuple[int, int]) -> np.ndarray:
    """``(gy·gx, 2)`` field positions ``(y, x)``, pixels from the axis: a ``gy × gx`` grid
    whose outer points are the sensor's edges (one point: the axis)."""
    gy, gx = int_pair(grid, "grid")
    if not (1 <= gy <= 5 and 1 <= gx <= 5):
        raise DiffcamError(f"grid is (rows, columns) of field positions, each 1 to 5, e.g. "
                           f"(2, 2); got {grid!r}.")
    ny, nx = sensor_shape
    ys = np.linspace(-ny / 2, ny / 2, gy) if gy > 1 else np.zeros(1)
    xs = np.linspace(-nx / 2, nx / 2, gx) if gx > 1 else np.zeros(1)
    return np.stack(np.meshgrid(ys, xs, indexing="ij"), -1).reshape(-1, 2).astype(np.float32)


def _field(kernels: np.ndarray, positions: np.ndarray) -> FieldPSF:
    """The `FieldPSF` of kernels ``(K, ny, nx)`` at ``positions``, interpolated."""
    k = len(kernels)
    stack = np.asarray(kernels, np.float64).reshape(k, -1)
    gram = np.linalg.eigvalsh(stack @ stack.T)[::-1]      # the stack's σ², largest first
    return FieldPSF(kernels=jnp.asarray(kernels), coefficients=jnp.eye(k, dtype=jnp.float32),
                    positions=jnp.asarray(positions),
                    singular_values=jnp.asarray(np.sqrt(np.maximum(gram, 0)), jnp.float32))


def _sensor_weights(positions: np.ndarray, sensor_shape) -> np.ndarray:
    """``(K, ny, nx)`` the weights of kernels at ``positions`` on the sensor frame, as
    `diffcam.reconstruct.operators.field_model` puts them on the object grid."""
    object_shape, _ = grid_shapes(sensor_shape, sensor_shape, "crop")
    unit = _field(np.zeros((len(positions), 1, 1), np.float32), positions)
    return np.asarray(crop_to(unit.weights(object_shape), sensor_shape))


def fit_field_psf_from_scenes(raws: Sequence[ArrayLike], truths: Sequence[ArrayLike],
                              grid: tuple[int, int] = (2, 2),
                              options: ScenePsfOptions | None = None, *,
                              progress: bool = True, **overrides) -> SceneFieldPsf:
    """The field-dependent PSF (per channel) that best maps the scenes to the raws:
    kernels at a ``grid`` of field positions, interpolated across the field (the
    low-rank model of `diffcam.model.field`), fitted jointly by non-negative least
    squares like `fit_psf_from_scenes` (the flip is chosen with one PSF).

    Args:
        raws, truths: as `fit_psf_from_scenes`'s.
        grid: ``(rows, columns)`` of field positions spanning the sensor, 1 to 5 each.
        options: [`ScenePsfOptions`][diffcam.calibrate.scene.fit.ScenePsfOptions];
            ``overrides`` replace its fields.
        progress: progress bars for runs over 2 s.

    Returns:
        [`SceneFieldPsf`][diffcam.calibrate.scene.fit.SceneFieldPsf].

    Raises:
        DiffcamError: see `check_scene_pairs`; a bad grid; bad options.
    """
    kernels, positions, offset, residual, flip, trials = _fit_kernels(
        raws, truths, grid, ScenePsfOptions.of(options, **overrides), progress)
    fields = tuple(_field(kernels[:, ch], positions) for ch in range(kernels.shape[1]))
    return SceneFieldPsf(fields=fields, offset=offset, flip=flip, residual=residual,
                         flip_residuals=trials)


def predict_raw(calibration: ScenePsf | SceneFieldPsf,
                truth: Float[ArrayLike, "c ny nx"]) -> np.ndarray:
    """The raw capture the calibrated camera records of ``truth`` (a scene in the lensed
    frame, shape ``(c, ny, nx)`` like the calibration's raws, or ``(ny, nx)`` for one
    channel): ``crop(h * x) + c``, or ``crop(Σ_k g_k ∗ (w_k · x)) + c`` for a
    field-dependent calibration, computed on the kernels and the scene scaled to unit
    peak.

    Raises:
        DiffcamError: a truth that is not a finite, non-negative real image of the
            calibration's shape, a calibration with NaN/Inf or negative values, or a
            prediction beyond float32's range.
    """
    truth = as_pairs([flip_scene(real_array("truth", truth), calibration.flip)],
                      "truth")[0]
    field = isinstance(calibration, SceneFieldPsf)
    kernels = (as_pairs([f.kernels for f in calibration.fields], "calibration.fields")
               .swapaxes(0, 1) if field else as_pairs([calibration.psf], "calibration.psf"))
    offset = np.asarray(real_array("calibration.offset", calibration.offset), np.float64)
    if truth.shape != kernels.shape[1:] or offset.shape != kernels.shape[1:2]:
        raise ShapeError(f"truth {truth.shape} does not match the calibration's "
                         f"{kernels.shape[1:]} (channels, ny, nx) and offset {offset.shape}.")
    if (truth < 0).any() or (kernels < 0).any() or not np.isfinite(offset).all():
        raise DiffcamError("predict_raw needs a non-negative truth and a calibration with "
                           "non-negative kernels and a finite offset (fit_psf_from_scenes "
                           "or fit_field_psf_from_scenes gives one).")
    psf_peak = channel_peaks(kernels)[:, None, None]
    truth_peak = channel_peaks(truth[None])[:, None, None]
    scene, unit_kernels = jnp.asarray(truth / truth_peak), jnp.asarray(kernels / psf_peak)
    if field:
        unit = jnp.stack([_channel_model(f, k, truth.shape)(s) for f, k, s in
                          zip(calibration.fields, unit_kernels.swapaxes(0, 1), scene)])
    else:
        model = convolution_model(unit_kernels[0], truth.shape, "crop")
        unit = model(pad_to(scene, model.object_shape))
    peaks = psf_peak * truth_peak
    raw = np.asarray(unit, np.float64) * peaks + offset[:, None, None]
    if not np.abs(raw).max() <= float(np.finfo(np.float32).max):
        raise DiffcamError(f"the predicted raw exceeds float32's range (PSF and truth peak "
                           f"at {float(peaks.max()):.3g} together); divide the truth by a "
                           f"constant first.")
    return raw.astype(np.float32)


def _channel_model(field: FieldPSF, kernels: Array, shape):
    """One channel's forward model on its sensor-frame scene, with ``kernels`` in place
    of the field's."""
    model = field_model(_field(kernels, np.asarray(field.positions)), shape[-2:])
    return lambda scene: model(pad_to(scene, model.object_shape))
