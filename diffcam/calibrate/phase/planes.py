"""Extra intensity planes for the projection solvers (phase diversity).

Near and far intensities leave θd undetermined up to its twin, and for a strongly
scattering diffuser (a random phase spanning many 2π) the near/far projections stall
far from it. One more intensity at a known distance behind the diffuser under a plane
wave, a *defocused plane*, removes both problems: RAAR with the far-field and plane
projections averaged converges on the paper's Fig. 6 random diffuser where near/far
alone stall (see `diffcam.calibrate.phase.projections`).

A captured PSF is such a plane. By the Fresnel scaling theorem (docs/design.md), the PSF of a
point at z1 on a sensor z2 behind the diffuser is, up to a constant, the plane-wave
intensity z_eff = z1·z2/(z1 + z2) behind the diffuser magnified by M = (z1 + z2)/z1:
`psf_plane` undoes the magnification onto the diffuser grid.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.model.camera import Camera
from diffcam.core.errors import (DiffcamError, ShapeError, check_field, check_positive,
                                 real_array)
from diffcam.model.sensor import resample
from diffcam.optics.propagation import effective_distance, magnification

__all__ = ["DefocusedPlane", "psf_plane", "check_planes"]

_EDGE = 2  # samples next to a capture's border left out (the spline reads the zeros
#            beyond the frame there)


class DefocusedPlane(NamedTuple):
    """A plane-wave intensity ``distance`` behind the diffuser, on the calibration grid.

    Attributes:
        intensity: (ny, nx) on the diffuser-plane grid (pitch ``geometry.dx``), any scale
            (it is matched to the near field's energy, so it must hold all the light).
        distance: free-space distance from the diffuser, metres (> 0).
        mask: (ny, nx), 1 where ``intensity`` was measured, 0 where it is unknown (the
            solvers leave the field there as it is).
    """

    intensity: Float[Array, "ny nx"]
    distance: float
    mask: Float[Array, "ny nx"]


def psf_plane(psf: Float[Array, "cy cx"], camera: Camera, z1: float) -> DefocusedPlane:
    """A captured on-axis PSF at depth ``z1`` as a
    [`DefocusedPlane`][diffcam.calibrate.phase.planes.DefocusedPlane].

    Args:
        psf: the PSF on ``camera.out_shape`` at pitch ``camera.dx``, registered to the
            optical axis, background subtracted (any scale).
        camera: the camera that captured it: pitch, z2, wavelength, grid.
        z1: the point source's depth, metres.

    Returns:
        The plane z_eff = z1·z2/(z1 + z2) behind the diffuser on ``camera.shape``: the PSF
        demagnified by M = (z1 + z2)/z1 (`diffcam.model.sensor.resample`, cubic,
        the PSF zero outside its frame, so no light wraps across it), masked to the part of
        the grid the capture covers.
    """
    real_array("psf", psf)
    check_field(psf, "psf")
    check_positive("z1", z1, "m")
    p = np.asarray(psf, np.float32)
    if p.ndim != 2 or p.shape != tuple(camera.out_shape):
        raise ShapeError(f"psf must be the camera's out_shape {tuple(camera.out_shape)}, "
                         f"got {p.shape}.")
    if p.min() < 0 or p.max() <= 0:
        raise DiffcamError(f"psf has negative values or no light (min {p.min():.3g}, max "
                           f"{p.max():.3g}); subtract the background with "
                           f"diffcam.io.subtract_background and clip at 0.")
    z1, z2, dx = float(z1), float(camera.z2), float(camera.dx)
    mag = magnification(z1, z2)
    shape = tuple(camera.shape)
    plane = resample(jnp.asarray(p), dx, dx, shape, 1 / mag, kind="cubic")
    inside = [np.abs(np.arange(n) - n // 2) * mag <= c // 2 - _EDGE  # in PSF samples
              for n, c in zip(shape, p.shape)]
    mask = jnp.asarray(inside[0][:, None] & inside[1][None, :], jnp.float32)
    return DefocusedPlane(jnp.clip(plane, 0, None) * mask, effective_distance(z1, z2), mask)


def check_planes(planes, shape) -> tuple[DefocusedPlane, ...]:
    """Validate extra planes against the captures' ``shape``; returns them as a tuple."""
    planes = tuple(planes)
    for k, plane in enumerate(planes):
        if not isinstance(plane, DefocusedPlane):
            raise DiffcamError(f"planes[{k}] must be a DefocusedPlane (see "
                               f"diffcam.calibrate.psf_plane), got {type(plane).__name__}.")
        real_array(f"planes[{k}].intensity", plane.intensity)
        check_field(plane.intensity, f"planes[{k}].intensity")
        if np.shape(plane.intensity) != tuple(shape) or np.shape(plane.mask) != tuple(shape):
            raise ShapeError(f"planes[{k}] is {np.shape(plane.intensity)} (mask "
                             f"{np.shape(plane.mask)}); the captures are {tuple(shape)}.")
        check_positive(f"planes[{k}].distance", plane.distance, "m")
        if float(np.min(plane.intensity)) < 0 or float(np.max(plane.intensity)) <= 0:
            raise DiffcamError(f"planes[{k}].intensity has negative values or no light.")
    return planes
