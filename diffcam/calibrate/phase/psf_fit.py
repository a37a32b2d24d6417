"""Fitting the diffuser phase to captured PSFs through paper Eq. 7, then predicting
PSFs at other depths.

The model of PSF k is s_k·PSF(θd; z1_k, z2) + b_k (`diffcam.model.point_spread.psf`), fitted
together with optional near/far captures (`diffcam.calibrate.phase.lsq.near_far_model`)
by `diffcam.calibrate.phase.lsq.fit_phase`. A PSF is a defocused, magnified intensity
of the diffuser field, so it also breaks the conjugate-twin ambiguity of near/far
data.

With near/far captures the residuals are weighted by the shot-noise standard deviation
of each pixel (``loss="weighted_intensity"``): a far field is a bright centre over dim
tails, and plain intensity residuals let the centre dominate, so from a flat start the
fit crawls and stalls (paper Fig. 3 problem at 1024², near + far + one PSF at
z1 = 25 mm, z2 = 1 mm: phase Pearson 0.90, MSE 0.73 rad² after 200 L-BFGS steps and
still 0.90 after 1000), while the weighted fit reaches the phase itself, not its twin,
in 150 steps (MSE 1e-4 rad²).

Geometry in identifiable form: paraxially z1, z2, the pitch dx and the wavelength λ
enter the PSF only through the Fresnel numbers λz/dx², so λ and dx stay fixed (the
camera's) and distances are fitted; ``stats`` reports them in metres and as
ζ = λz/dx². Depths are either known (``"fixed"``), one per PSF (``"per_psf"``), or two
parameters for planes spaced uniformly in 1/z1 (``"inverse_linear"``: 1/z1 linear in
the plane index t, fixed by the depths of the first and last fitted planes). Distances
are fitted as log-ratios to their start values, so every parameter is dimensionless
and of order one.
"""

from __future__ import annotations

from typing import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.model import Camera, psf
from diffcam.model.camera import real_dtype
from diffcam.core.errors import (DiffcamError, ShapeError, check_field, check_positive,
                                 real_array)
from diffcam.model.sensor import bin_pixels
from diffcam.model.stack import psf_stack
from diffcam.evaluate.metrics import psf_fidelity, twin_phase
from diffcam.calibrate.phase.near_far import NearFarModel, check_captures
from diffcam.calibrate.phase.lsq import FitOptions, PhaseGrid, fit_phase, near_far_model, warn_if_stalled
from diffcam.calibrate.phase.projections import initial_phase
from diffcam.calibrate.phase.result import RetrievalResult

__all__ = ["fit_to_psfs", "DepthLaw", "predict_psfs", "resolve_twin", "depths", "PSFModel", "DEPTH_MODELS"]

DEPTH_MODELS = ("fixed", "per_psf", "inverse_linear")


def depths(extra, z1, depth_model: str, plane_index=None, at=None) -> Float[Array, " k"]:
    """Depths (m) under the fitted ``extra`` parameters: of the fitted PSFs, or with
    ``depth_model="inverse_linear"`` of the planes ``at`` (plane indices, default the
    fitted ones). ``z1`` and ``plane_index`` are the start depths and plane indices."""
    z1 = jnp.asarray(z1)
    z1 = z1.astype(jnp.promote_types(z1.dtype, jnp.float32))
    if depth_model == "fixed":
        return z1
    if depth_model == "per_psf":
        return z1 * jnp.exp(extra["log_z1"])
    t = jnp.asarray(plane_index, z1.dtype)
    first, last = jnp.argmin(t), jnp.argmax(t)
    inv_a = jnp.exp(-extra["log_z1_ends"][0]) / z1[first]
    inv_b = jnp.exp(-extra["log_z1_ends"][1]) / z1[last]
    s = (jnp.asarray(plane_index if at is None else at, z1.dtype) - t[first]) / (
        t[last] - t[first])
    return 1.0 / (inv_a + (inv_b - inv_a) * s)


def _on_sensor(image, camera, sensor):
    """Integrate a PSF over sensor pixels (``sensor = (pitch, shape)``), or pass it on."""
    if sensor is None:
        return image
    return bin_pixels(image, camera.dx, sensor[0], sensor[1])


class PSFModel(eqx.Module):
    """θd and the extra parameters → (PSF_1 … PSF_K[, near, far]): paper Eq. 7 at each
    fitted depth, as a pytree (the camera's numbers, the depths and the near/far model
    are leaves; the depth model and the sensor binning are static)."""

    camera: Camera
    z1: Array
    plane_index: Array | None
    spectrum: tuple | None
    near_far: NearFarModel | None
    depth_model: str = eqx.field(static=True)
    sensor: tuple | None = eqx.field(static=True)  # (pitch, shape) of the PSF pixels

    def __call__(self, phase, extra):
        camera = self.camera
        extra = extra or {}
        if "log_z2" in extra:
            camera = eqx.tree_at(lambda c: c.z2, camera, camera.z2 * jnp.exp(extra["log_z2"]))
        z1 = depths(extra, self.z1, self.depth_model, self.plane_index)
        out = tuple(_on_sensor(psf(phase, camera, z1[k], spectrum=self.spectrum), camera,
                               self.sensor) for k in range(self.z1.shape[0]))
        if self.near_far is not None:
            out = out + tuple(self.near_far(phase))
        return out


class DepthLaw(eqx.Module):
    """Which distances a PSF fit may change, and how the depths are parameterised.

    Attributes:
        kind: ``"fixed"`` (the given depths), ``"per_psf"`` (one free depth per PSF) or
            ``"inverse_linear"`` (1/z1 linear in the plane index: two parameters).
        plane_index: the plane number of each PSF (needed by ``"inverse_linear"``).
        fit_z2: also fit the diffuser-to-sensor distance.
    """

    kind: str = "fixed"
    plane_index: tuple | None = eqx.field(default=None, converter=lambda t: None if t is None
                                          else tuple(float(v) for v in np.ravel(t)))
    fit_z2: bool = False

    def __check_init__(self):
        if self.kind not in DEPTH_MODELS:
            raise DiffcamError(f"depth law must be one of {DEPTH_MODELS}, got {self.kind!r}.")
        if self.kind == "inverse_linear":
            if self.plane_index is None:
                raise DiffcamError("DepthLaw('inverse_linear') needs plane_index: the plane "
                                   "number of each PSF.")
            if len(set(self.plane_index)) < 2:
                raise DiffcamError("DepthLaw('inverse_linear') needs PSFs of ≥ 2 planes.")

    def start(self, n_psfs: int, dtype) -> dict:
        """The fitted parameters' start values (log-ratios to the given distances)."""
        if self.plane_index is not None and len(self.plane_index) != n_psfs:
            raise DiffcamError(f"plane_index has {len(self.plane_index)} entries for "
                               f"{n_psfs} PSFs; give one plane number per PSF.")
        extra = {"log_z2": jnp.zeros((), dtype)} if self.fit_z2 else {}
        if self.kind == "per_psf":
            extra["log_z1"] = jnp.zeros(n_psfs, dtype)
        if self.kind == "inverse_linear":
            extra["log_z1_ends"] = jnp.zeros(2, dtype)
        return extra


def _depth_law(depth) -> DepthLaw:
    if isinstance(depth, DepthLaw):
        return depth
    return DepthLaw(depth)


class PsfFitOptions(FitOptions):
    """How [`fit_to_psfs`][diffcam.calibrate.phase.psf_fit.fit_to_psfs] runs: the fields of
    [`FitOptions`][diffcam.calibrate.phase.lsq.FitOptions], and

    Attributes:
        depth: a [`DepthLaw`][diffcam.calibrate.phase.psf_fit.DepthLaw] (or its kind): which
            distances are fitted.
        init: ``"flat"``, ``"random"`` (with ``key``) or a phase on the camera grid.
        sensor_pitch: pixel pitch of the measured PSFs (m) when it is coarser than the
            camera's grid: the model then integrates each PSF over those pixels
            (`diffcam.model.sensor.bin_pixels`), so the phase can live on a finer
            grid than binned data.
    """

    depth: object = "fixed"
    init: object = "flat"
    sensor_pitch: float | None = None


def fit_to_psfs(psfs: Float[Array, "k cy cx"], camera: Camera, z1: Sequence[float], *,
                near_far=None, masks=None, spectrum=None,
                options: FitOptions | None = None, **overrides) -> RetrievalResult:
    """Fit θd (with or without near/far captures) to one or more captured PSFs.

    Args:
        psfs: K measured PSFs (k, cy, cx) on ``camera.out_shape`` at the camera's pitch
            (or on pixels of ``sensor_pitch``), registered to the optical axis (any scale
            and background: both are fitted).
        camera: the [`Camera`][diffcam.model.camera.Camera]: grid, pitch dx, λ, z2 (the
            start value when the depth law fits z2), aperture.
        z1: depths of the PSFs, metres, (k,): known values, or start values.
        near_far: optional ``(near, far, geometry)``: calibration intensities on the
            camera grid (``camera.shape``, pitch ``camera.dx``; far at the Fourier-lens
            pitch) and their
            [`CalibrationGeometry`][diffcam.calibrate.phase.near_far.CalibrationGeometry] (``dx``
            the camera's).
        masks: K (or K + 2 with near/far) weight images, 0 at saturated pixels.
        spectrum: broadband light as in
            [`diffcam.model.point_spread.psf`][diffcam.model.point_spread.psf].
        options: [`PsfFitOptions`][diffcam.calibrate.phase.psf_fit.PsfFitOptions] (or a
            [`FitOptions`][diffcam.calibrate.phase.lsq.FitOptions]; default loss
            ``"weighted_intensity"``: each residual over √(y + ȳ), y the measured intensity
            and ȳ its mean, which keeps the dim tails of a far field in the fit);
            ``**overrides`` replace its fields (``depth=``, ``init=``, ``sensor_pitch=``,
            ``coarse=``, ``key=``, ``iterations=``, ...).

    Returns:
        [`RetrievalResult`][diffcam.calibrate.phase.result.RetrievalResult]; ``stats`` adds ``z1``
        and ``z2`` (m), ``zeta1`` and ``zeta2`` (λz/dx²) and ``depth_model``.
    """
    opts = PsfFitOptions.of(options, **overrides)
    depth, init, sensor_pitch = _depth_law(opts.depth), opts.init, opts.sensor_pitch
    dtype = real_dtype(camera)
    psfs = _check_psfs(psfs, camera, sensor_pitch)
    z1 = np.asarray(z1, np.float64).reshape(-1)
    check_positive("z1", z1, "m")
    if z1.size != psfs.shape[0]:
        raise ShapeError(f"{z1.size} depths for {psfs.shape[0]} PSFs; give one z1 per PSF.")
    extra = depth.start(z1.size, dtype)
    nf_model, nf_measured = _near_far(near_far, camera)
    aperture = np.asarray(camera.aperture())
    grid = PhaseGrid.for_aperture(aperture, opts.coarse)
    theta0 = grid.restrict(initial_phase(init, camera.shape, opts.key)[0].astype(dtype))
    plane_index = None if depth.plane_index is None else jnp.asarray(depth.plane_index, dtype)
    model = PSFModel(camera, jnp.asarray(z1, dtype), plane_index, spectrum, nf_model,
                     depth.kind, _sensor(camera, sensor_pitch))
    result = warn_if_stalled(fit_phase(model, list(psfs) + nf_measured, theta0, grid,
                                       support=aperture > 0, masks=masks, extra0=extra or None,
                                       options=opts), init)
    fitted = result.stats["extra"] or {}
    z2 = float(camera.z2) * float(np.exp(fitted.get("log_z2", 0.0)))
    z1_fit = np.asarray(depths(fitted, z1, depth.kind, depth.plane_index), np.float64)
    scale = float(camera.wavelength) / float(camera.dx) ** 2
    stats = dict(result.stats, z1=z1_fit, z2=z2, zeta1=z1_fit * scale, zeta2=z2 * scale,
                 depth_model=depth.kind)
    return result._replace(stats=stats)


def _check_psfs(psfs, camera, sensor_pitch) -> np.ndarray:
    """The measured PSFs as an array of the camera's dtype, after checking them."""
    psfs = np.asarray(real_array("psfs", psfs), np.dtype(real_dtype(camera)))
    check_field(psfs, "psfs")
    sensor = _sensor(camera, sensor_pitch)
    want = tuple(camera.out_shape) if sensor is None else sensor[1]
    if psfs.ndim != 3 or psfs.shape[-2:] != want:
        raise ShapeError(f"psfs must be (k, {want[0]}, {want[1]}) (the camera's out_shape, "
                         f"binned to sensor_pitch if given), got {psfs.shape}.")
    for k, p in enumerate(psfs):
        if p.min() < 0 or p.max() == p.min():
            raise DiffcamError(f"PSF {k} is negative somewhere or constant (min {p.min():.3g}, "
                               f"max {p.max():.3g}); subtract the background with "
                               f"diffcam.io.subtract_background and check the exposure.")
    return psfs


def _near_far(near_far, camera) -> tuple[NearFarModel | None, list]:
    """The near/far forward model and captures of ``near_far=(near, far, geometry)``."""
    if near_far is None:
        return None, []
    if len(near_far) != 3 or near_far[2] is None:
        raise DiffcamError("near_far must be (near, far, geometry) with geometry a "
                           "CalibrationGeometry.")
    near, far, geometry = near_far
    check_captures(near, far)
    if np.shape(near) != tuple(camera.shape):
        raise ShapeError(f"near/far captures {np.shape(near)} must be on the camera grid "
                         f"{tuple(camera.shape)}.")
    if abs(float(geometry.dx) - float(camera.dx)) > 1e-6 * float(camera.dx):
        raise DiffcamError(f"geometry.dx {geometry.dx} m differs from camera.dx "
                           f"{float(camera.dx)} m; put both on one grid.")
    return near_far_model(camera.aperture(), geometry), [near, far]


def _sensor(camera, sensor_pitch):
    if sensor_pitch is None:
        return None
    check_positive("sensor_pitch", sensor_pitch, "m")
    ratio = float(camera.dx) / float(sensor_pitch)
    cy, cx = camera.out_shape
    return float(sensor_pitch), (int(round(cy * ratio)), int(round(cx * ratio)))


def predict_psfs(phase: Float[Array, "ny nx"], camera: Camera, z1, *, z2=None,
                 spectrum=None, sensor_pitch=None) -> np.ndarray:
    """PSFs (nz, cy, cx), unit sum, of a (retrieved) phase at depths ``z1`` (m), with an
    optional fitted ``z2`` (m), integrated over pixels of ``sensor_pitch`` (m) if given;
    [`diffcam.model.stack.psf_stack`][diffcam.model.stack.psf_stack] underneath."""
    if z2 is not None:
        camera = eqx.tree_at(lambda c: c.z2, camera, jnp.asarray(z2, camera.z2.dtype))
    stack = psf_stack(phase, camera, np.asarray(z1, np.float64), spectrum=spectrum,
                      progress=False)
    sensor = _sensor(camera, sensor_pitch)
    return stack if sensor is None else np.asarray(_on_sensor(stack, camera, sensor))


def resolve_twin(phase: Float[Array, "ny nx"], reference_psf: Float[Array, "cy cx"],
                 camera: Camera, z1: float) -> tuple[np.ndarray, bool]:
    """Choose between a near/far-retrieved phase and its conjugate twin −θd(−x).

    Near and far intensities cannot tell them apart; one captured PSF at depth ``z1``
    (metres; ``camera.out_shape``, any scale) can: the candidate whose PSF matches it
    better (registered Pearson,
    [`diffcam.evaluate.metrics.psf_fidelity`][diffcam.evaluate.metrics.psf_fidelity]) is
    returned, with ``True`` if that was the twin. For a fit that also refines the phase
    against the PSF, use [`fit_to_psfs`][diffcam.calibrate.phase.psf_fit.fit_to_psfs] with
    ``init=phase``.
    """

    twin = twin_phase(jnp.asarray(phase))
    candidates = jnp.stack([psf(jnp.asarray(phase), camera, z1), psf(twin, camera, z1)])
    score = psf_fidelity(candidates, jnp.asarray(reference_psf))["pearson"]
    use_twin = bool(score[1] > score[0])
    return np.asarray(twin if use_twin else phase), use_twin
