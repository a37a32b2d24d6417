"""The near/far calibration (paper Fig. 2, Eqs. 9–13): its geometry, its forward model
(the one place θd becomes near- and far-field intensities) and the checks every
retrieval entry runs.

Two captures of the same diffuser under a plane wave through the aperture C:

- the **near field**, at ``near_distance`` behind the diffuser (the paper puts the
  diffuser on the sensor's cover glass: 0.5 mm of glass ≈ 0.33 mm of free space, see
  `glass_equivalent_distance`; 0 means "at the diffuser"), pitch ``dx``;
- the **far field**, at the back focal plane of a Fourier lens of focal length ``f``
  (paper Eq. 13), on the Fourier-lens grid of pitch λf/(N·dx) per axis.

Both captures must already be on these grids (``diffcam.calibrate.phase.captures`` resamples
a sensor image onto them). `NearFarModel` predicts them from θd: plane-wave
illumination through the aperture C, the thin diffuser e^{jθd} (Eq. 5), then (near) free
space by ``near_distance`` with the angular spectrum and (far) the Fourier lens (Eq. 13).
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.errors import (DiffcamError, GeometryWarning, ShapeError, check_field,
                                 check_positive, fmt_length, real_array)
from diffcam.core.backend import transfer_step
from diffcam.core.grid import fft2c, pitch_yx
from diffcam.optics.elements import apply_phase
from diffcam.optics.propagation import transfer_function

__all__ = ["CalibrationGeometry", "NearFarModel", "calibration_intensities",
           "glass_equivalent_distance", "check_captures", "check_far_pitch",
           "far_speckle_ratio", "check_far_speckle"]


def glass_equivalent_distance(thickness: float, refractive_index: float = 1.5) -> float:
    """Free-space distance (m) with the paraxial propagation of ``thickness`` (m) of glass:
    t/n (0.5 mm of n = 1.5 glass ≈ 0.33 mm)."""
    check_positive("thickness", thickness, "m", allow_zero=True)
    check_positive("refractive_index", refractive_index, "1")
    return thickness / refractive_index


class CalibrationGeometry(eqx.Module):
    """Fixed numbers of the near/far calibration set-up, SI units.

    Attributes:
        dx: diffuser-plane (and near-capture) pitch, metres per sample.
        wavelength: metres.
        focal_length: Fourier-lens focal length f, metres.
        near_distance: diffuser → near-capture plane, free-space equivalent, metres
            (≥ 0; 0 puts the near capture at the diffuser).
    """

    dx: float
    wavelength: float
    focal_length: float
    near_distance: float = 0.0

    def __check_init__(self):
        check_positive("dx (pixel pitch)", self.dx, "m")
        check_positive("wavelength", self.wavelength, "m")
        check_positive("focal_length", self.focal_length, "m")
        check_positive("near_distance", self.near_distance, "m", allow_zero=True)

    def far_pitch(self, shape) -> tuple[float, float]:
        """Fourier-lens pitch (λf/(Ny·dx), λf/(Nx·dx)) of a ``(..., ny, nx)`` grid, metres."""
        ny, nx = shape[-2], shape[-1]
        lf = self.wavelength * self.focal_length
        return lf / (ny * self.dx), lf / (nx * self.dx)


class NearFarModel(eqx.Module):
    """θd → (near, far) intensities, each in energy units (each sums to Σ|C|²): the far
    field is the unitary centred DFT of the diffuser field, which differs from
    [`diffcam.optics.lens.fourier_lens`][diffcam.optics.lens.fourier_lens] by the constant
    (N·dy·dx/(λf))² in intensity
    ([`calibration_intensities`][diffcam.calibrate.phase.near_far.calibration_intensities] applies
    it).

    Attributes:
        aperture: amplitude transmission C on the calibration grid (ny, nx).
        kernel: the angular-spectrum transfer function to the near-capture plane, or
            ``None`` when the near capture is at the diffuser.
    """

    aperture: Array
    kernel: Array | None

    @classmethod
    def build(cls, aperture, geometry: "CalibrationGeometry") -> "NearFarModel":
        """The model of ``geometry`` on the grid of ``aperture`` (ny, nx)."""
        C = jnp.asarray(aperture)
        z = float(geometry.near_distance)
        kernel = None if z == 0 else transfer_function(C.shape, geometry.dx,
                                                        geometry.wavelength, z)
        return cls(C, kernel)

    def __call__(self, phase: Float[Array, "... ny nx"], extra=None):
        u = apply_phase(self.aperture, phase)
        near = u if self.kernel is None else transfer_step(u, self.kernel.astype(u.dtype))
        ny, nx = u.shape[-2:]
        far = fft2c(u) / np.sqrt(ny * nx)
        return jnp.abs(near) ** 2, jnp.abs(far) ** 2


def calibration_intensities(phase: Float[Array, "... ny nx"], aperture: Float[Array, "ny nx"],
                            geometry: "CalibrationGeometry"
                            ) -> tuple[Float[Array, "... ny nx"], Float[Array, "... ny nx"]]:
    """Near-field intensity (pitch dx) and far-field intensity (pitch λf/(N·dx)) in W/m²
    for a unit-intensity plane wave:
    [`NearFarModel`][diffcam.calibrate.phase.near_far.NearFarModel] in physical units.

    Propagation is circular on the given grid, so pad the diffuser into a grid wide
    enough for the near-field spread and at least twice the aperture (the far field is
    then Nyquist-sampled in intensity).
    """
    C = jnp.asarray(aperture, jnp.complex64 if jnp.asarray(phase).dtype != jnp.float64
                    else jnp.complex128)
    near, far = NearFarModel.build(C, geometry)(phase)
    ny, nx = C.shape[-2:]
    dx = float(geometry.dx)
    far_scale = ny * nx * (dx * dx / (float(geometry.wavelength) * float(geometry.focal_length))) ** 2
    return near, far * far_scale


def check_far_pitch(far_pitch, geometry: CalibrationGeometry, shape, rtol: float = 1e-3):
    """Raise unless the far capture's pitch (m) is the Fourier-lens pitch λf/(N·dx)."""
    want = geometry.far_pitch(shape)
    for got, need, axis in zip(pitch_yx(far_pitch), want, "yx"):
        check_positive("far_pitch", got, "m")
        if abs(float(got) - need) > rtol * need:
            raise DiffcamError(
                f"far-field pitch along {axis} is {fmt_length(float(got))} but a Fourier lens "
                f"of f = {fmt_length(geometry.focal_length)} at λ = "
                f"{fmt_length(geometry.wavelength)} on this {shape[-2]}×{shape[-1]} grid of "
                f"pitch {fmt_length(geometry.dx)} puts it at λf/(N·dx) = {fmt_length(need)}; "
                f"resample the capture with diffcam.calibrate.resample_far_field (or check "
                f"f, λ, dx and the sensor pitch).")


# far_speckle_ratio on simulated captures at the right pitch: 0.80–1.04 (cameraman and
# random diffusers, weak to strongly scattering, 100 to 10⁴ photons at the peak, near
# capture at 0 or 0.33 mm, 128²); with the far pitch 2× too large 1.42–1.49, 2× too small
# 0.38–0.56, 10× too large 1.40–1.58 (the grid caps it), 10× too small 0.09–0.11. Its
# median at the right pitch:
SPECKLE_RATIO_TYPICAL = 0.9
SPECKLE_RATIO_RANGE = (0.5, 1.25)   # outside: GeometryWarning
_DISC_R90 = 0.745   # 90 % radius of a disc's autocorrelation (lag 0 left out) / diameter


def _radius_quantile(power: np.ndarray, q: float) -> float:
    """Radius (samples) of the centred disc holding the fraction ``q`` of ``power`` (FFT
    order, lag 0 left out), on whole-sample rings."""
    ny, nx = power.shape
    ly, lx = np.meshgrid(np.fft.fftfreq(ny) * ny, np.fft.fftfreq(nx) * nx, indexing="ij")
    rings = np.rint(np.hypot(ly, lx)).astype(np.intp).ravel()
    p = np.asarray(power, np.float64).ravel().copy()
    p[0] = 0.0
    total = np.cumsum(np.bincount(rings, p))
    return max(float(np.searchsorted(total, q * total[-1])), 0.5)


def _speckle_radii(near, far) -> tuple[float, float]:
    """Lag radii (samples of dx) holding 90 % of |DFT(far·Hann window)|² and of the near
    intensity's autocorrelation, lag 0 left out (see `far_speckle_ratio`). A uniform
    stray-light level is taken off both: the far capture's window-weighted mean, the near
    capture's median (the grid is mostly outside the aperture)."""
    near = np.asarray(near, np.float64)
    far = np.asarray(far, np.float64)
    window = np.outer(*(np.hanning(n + 1)[:n] for n in far.shape))  # no frame-edge leakage
    far = (far - np.sum(far * window) / np.sum(window)) * window
    near = np.maximum(near - np.median(near), 0.0)
    measured = np.abs(np.fft.fft2(far)) ** 2
    predicted = np.abs(np.fft.ifft2(np.abs(np.fft.fft2(near)) ** 2))
    return _radius_quantile(measured, 0.9), _radius_quantile(predicted, 0.9)


def far_speckle_ratio(near: Float[Array, "ny nx"], far: Float[Array, "ny nx"]) -> float:
    """How wide the far capture's speckle says the lit diffuser is, over how wide the near
    capture shows it (dimensionless; ≈ `SPECKLE_RATIO_TYPICAL` at the right pitch).

    The DFT of the far intensity is the autocorrelation of the diffuser field, which
    vanishes at lags beyond the lit width D of the diffuser: speckle grain λf/D. The near
    intensity shows D. Compared: the lag radii (samples of dx) holding 90 % of
    |DFT(far·Hann window)|² and of the near intensity's autocorrelation, lag 0 left out.
    The ratio scales as (far pitch assumed)/(far pitch of the data); dx cancels.
    """
    measured, predicted = _speckle_radii(near, far)
    return measured / predicted


def check_far_speckle(near: Float[Array, "ny nx"], far: Float[Array, "ny nx"],
                      geometry: CalibrationGeometry, *, sensor_pitch: float | None = None,
                      stacklevel: int = 2) -> float:
    """Warn (`GeometryWarning`) if the far capture's speckle is
    ≳ 2× finer or coarser than the near capture predicts (`far_speckle_ratio`
    outside `SPECKLE_RATIO_RANGE`): the far pitch λf/(N·dx), hence f, λ or the
    sensor pitch (m), is wrong. Returns the ratio."""
    check_captures(near, far)
    measured, predicted = _speckle_radii(near, far)
    ratio = measured / predicted
    if not SPECKLE_RATIO_RANGE[0] <= ratio <= SPECKLE_RATIO_RANGE[1]:
        warnings.warn(_speckle_message(ratio, predicted, geometry, np.shape(far), sensor_pitch),
                      GeometryWarning, stacklevel=stacklevel)
    return ratio


def _speckle_message(ratio, predicted, geometry, shape, sensor_pitch) -> str:
    """The GeometryWarning of `check_far_speckle`: measured and expected grain (m and
    samples of the far grid) and what to check."""
    pitch = geometry.far_pitch(shape)[1]
    factor = ratio / SPECKLE_RATIO_TYPICAL   # ≈ (pitch assumed)/(pitch of the data)
    lit = predicted / _DISC_R90 * float(geometry.dx)   # D, the lit diffuser width
    expected = float(geometry.wavelength) * float(geometry.focal_length) / lit
    # speckle finer than a sample does not show: the grid caps the ratio, hence "at most"
    big, small, most = ("large", "small", "at most ") if factor > 1 else ("small", "large", "")
    sensor = "" if sensor_pitch is None else f" = {fmt_length(sensor_pitch)}"
    return (f"the far capture does not match the geometry: its speckle grain is {most}"
            f"{fmt_length(expected / factor)} ({expected / factor / pitch:.2g} samples) where "
            f"λf/D = {fmt_length(expected)} ({expected / pitch:.2g} samples) is expected for "
            f"the D ≈ {fmt_length(lit)} of diffuser the near capture shows lit. The far pitch "
            f"λf/(N·dx) = {fmt_length(pitch)} looks {max(factor, 1 / factor):.2g}× "
            f"{'or more ' if most else ''}too {big}: check the focal length "
            f"(f = {fmt_length(geometry.focal_length)}), the wavelength "
            f"(λ = {fmt_length(geometry.wavelength)}) and the sensor pixel pitch{sensor} "
            f"(f or λ too {big}, or the sensor pitch too {small}).")


def check_captures(near, far, *, near_name="near", far_name="far") -> None:
    """Shapes, finiteness, sign and information content of a near/far intensity pair."""
    for name, img in ((near_name, near), (far_name, far)):
        real_array(f"{name} intensity", img)
        check_field(img, f"{name} intensity")
        if np.ndim(img) != 2:
            raise ShapeError(f"{name} intensity must be one 2-D image (ny, nx), got shape "
                             f"{np.shape(img)}; retrieve a batch with jax.vmap on the core.")
    if np.shape(near) != np.shape(far):
        raise ShapeError(
            f"near {np.shape(near)} and far {np.shape(far)} captures differ in shape; both must "
            f"be on the same N×N computational grid (the far one at the Fourier-lens pitch): "
            f"use diffcam.calibrate.prepare_captures.")
    for name, img in ((near_name, near), (far_name, far)):
        a = np.asarray(img)
        lo, hi = float(a.min()), float(a.max())
        if lo < 0:
            raise DiffcamError(f"{name} intensity has negative values (min {lo:.3g}); "
                               f"subtract the background with diffcam.io.subtract_background, "
                               f"which clips small negatives.")
        if hi == lo:
            raise DiffcamError(f"{name} intensity is constant ({hi:.6g} everywhere): the capture "
                               f"is blank or fully saturated; re-capture with another exposure.")
