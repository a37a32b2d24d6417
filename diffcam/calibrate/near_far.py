"""The near/far calibration (paper Fig. 2, Eqs. 9–13): its geometry, its forward model
(the one place θd becomes near- and far-field intensities) and the checks every
retrieval entry runs.

Two captures of the same diffuser under a plane wave through the aperture C:

- the **near field**, at ``near_distance`` behind the diffuser (the paper puts the
  diffuser on the sensor's cover glass: 0.5 mm of glass ≈ 0.33 mm of free space, see
  :func:`glass_equivalent_distance`; 0 means "at the diffuser"), pitch ``dx``;
- the **far field**, at the back focal plane of a Fourier lens of focal length ``f``
  (paper Eq. 13), on the Fourier-lens grid of pitch λf/(N·dx) per axis.

Both captures must already be on these grids (``diffcam.calibrate.captures`` resamples
a sensor image onto them). :class:`NearFarModel` predicts them from θd: plane-wave
illumination through the aperture C, the thin diffuser e^{jθd} (Eq. 5), then (near) free
space by ``near_distance`` with the angular spectrum and (far) the Fourier lens (Eq. 13).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.errors import DiffcamError, ShapeError, check_field, check_positive, fmt_length
from diffcam.core.backend import transfer_step
from diffcam.core.grid import fft2c, pitch_yx
from diffcam.optics.elements import apply_phase
from diffcam.optics.propagation import transfer_function

__all__ = ["CalibrationGeometry", "NearFarModel", "calibration_intensities",
           "glass_equivalent_distance", "check_captures", "check_far_pitch"]


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
    :func:`diffcam.optics.propagation.fourier_lens` by the constant
    (N·dy·dx/(λf))² in intensity (:func:`calibration_intensities` applies it).

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
    for a unit-intensity plane wave: :class:`NearFarModel` in physical units.

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


def check_captures(near, far, *, near_name="near", far_name="far") -> None:
    """Shapes, finiteness, sign and information content of a near/far intensity pair."""
    for name, img in ((near_name, near), (far_name, far)):
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
