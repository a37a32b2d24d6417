"""Optical elements on a centred grid: apertures (paper Eqs. 3–4), the point-source field
at the aperture plane (Eq. 2), a thin lens, and the thin diffuser (Eq. 5).

Elements are transmission functions (arrays of shape ``(ny, nx)``) or fields; combine
them by multiplication. Any array works as an aperture mask: real DiffuserCam apertures
are rectangular or set by the sensor.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Complex, Float, Num

from .errors import DiffcamError, check_field, check_finite, check_positive, is_concrete, \
    fmt_length, sampling_problem
from .grid import pitch_yx, radius2, yx
from .propagate import piston

__all__ = [
    "circular_aperture",
    "rectangular_aperture",
    "point_source_field",
    "point_source_max_frequency",
    "thin_lens",
    "apply_phase",
]


def _check_grid(shape, dx):
    if len(shape) < 2 or shape[-2] <= 0 or shape[-1] <= 0:
        raise DiffcamError(f"grid shape must be (..., ny, nx) with ny, nx > 0, got {shape}.")
    for p in pitch_yx(dx):
        check_positive("dx (pixel pitch)", p, "m")


def _edge(signed_distance, dx, edge: str):
    """Transmission from the signed distance inside an edge (m): hard or soft."""
    if edge == "hard":
        return (signed_distance >= 0).astype(jnp.float32)
    if edge == "soft":
        # fraction of a pixel inside a straight edge: a ramp one pixel wide; this is
        # close to the area fraction and has a gradient with respect to the edge position
        return jnp.clip(0.5 + signed_distance / dx, 0.0, 1.0)
    raise DiffcamError(f"edge must be 'hard' or 'soft', got {edge!r}.")


def circular_aperture(shape, dx, radius, centre=(0.0, 0.0), *, edge: str = "hard"
                      ) -> Float[Array, "ny nx"]:
    """Circular aperture C(x, y) of paper Eq. 4: 1 inside ``radius``, 0 outside.

    Args:
        shape: grid shape ``(..., ny, nx)``.
        dx: pitch, metres (scalar or ``(dy, dx)``).
        radius: aperture radius, metres.
        centre: ``(y0, x0)`` of the aperture centre, metres.
        edge: ``"hard"`` (samples with r ≤ radius, as in the paper) or ``"soft"`` (a
            one-pixel ramp: differentiable in ``radius`` and ``centre``, and closer to
            the area of a continuous disc).

    Raises:
        DiffcamError: radius ≤ 0, or the aperture does not fit in the grid.
    """
    _check_grid(shape, dx)
    check_positive("radius", radius, "m")
    if is_concrete(radius, centre, dx):
        dy, dxx = (float(p) for p in pitch_yx(dx))
        half_y = (shape[-2] // 2) * dy
        half_x = (shape[-1] // 2) * dxx
        ry = float(radius) + abs(float(centre[0]))
        rx = float(radius) + abs(float(centre[1]))
        if ry > half_y or rx > half_x:
            raise DiffcamError(
                f"aperture (radius {fmt_length(float(radius))}, centre {centre}) reaches "
                f"beyond the grid half-width ({fmt_length(half_y)} × {fmt_length(half_x)}); "
                f"enlarge the grid (more samples) or reduce the radius.")
    r = jnp.sqrt(radius2(shape, dx, centre))
    return _edge(radius - r, jnp.minimum(*pitch_yx(dx)), edge)


def rectangular_aperture(shape, dx, height, width, centre=(0.0, 0.0), *, edge: str = "hard"
                         ) -> Float[Array, "ny nx"]:
    """Rectangular aperture of ``height × width`` metres centred at ``(y0, x0)``."""
    _check_grid(shape, dx)
    check_positive("height", height, "m")
    check_positive("width", width, "m")
    y, x = yx(shape, dx)
    dy, dxx = pitch_yx(dx)
    ty = _edge(height / 2 - jnp.abs(y - centre[0]), dy, edge)
    tx = _edge(width / 2 - jnp.abs(x - centre[1]), dxx, edge)
    return ty * tx


def point_source_max_frequency(wavelength, z1, radius, offset=0.0) -> float:
    """Largest local spatial frequency of the point-source chirp within ``radius`` (1/m).

    (radius + |offset|)/(λ·z1): the spherical wave from a source at lateral distance
    ``offset`` and depth ``z1``, seen at the edge of an aperture of ``radius``.
    """
    return (radius + abs(offset)) / (wavelength * z1)


def point_source_field(shape, dx, wavelength, z1, x1=0.0, y1=0.0, *, aperture_radius=None,
                       accept_undersampling: bool = False) -> Complex[Array, "ny nx"]:
    """Paraxial field of a unit point source at (x1, y1, z1) on the aperture plane, Eq. 2:

        U(x, y) = e^{jkz1}/(jλz1) · exp(jk((x − x1)² + (y − y1)²)/(2 z1)).

    Args:
        shape: grid shape ``(..., ny, nx)``.
        dx: pitch, metres.
        wavelength: metres.
        z1: source distance in front of the aperture, metres (> 0).
        x1, y1: lateral source position, metres.
        aperture_radius: the chirp must be sampled only where light passes: give the
            aperture radius (metres) to check there; ``None`` checks the whole grid.
        accept_undersampling: warn instead of raising when the chirp aliases.

    Raises:
        SamplingError: the chirp's local frequency exceeds Nyquist 1/(2·dx) within
            the checked radius. Close sources need the scaling-theorem path
            (:mod:`diffcam.camera`), which never samples this chirp.
    """
    _check_grid(shape, dx)
    check_positive("wavelength", wavelength, "m")
    check_positive("z1", z1, "m")
    check_finite("x1", x1)
    check_finite("y1", y1)
    if is_concrete(dx, wavelength, z1, x1, y1, aperture_radius):
        dy, dxx = (float(p) for p in pitch_yx(dx))
        if aperture_radius is None:
            radius = np.hypot(shape[-2] // 2 * dy, shape[-1] // 2 * dxx)
            where = "at the grid corner"
        else:
            radius = float(aperture_radius)
            where = "at the aperture edge"
        f_max = point_source_max_frequency(float(wavelength), float(z1), radius,
                                           np.hypot(float(x1), float(y1)))
        nyquist = 1 / (2 * max(dy, dxx))
        if f_max > nyquist:
            dx_needed = 1 / (2 * f_max)
            sampling_problem(
                f"point-source chirp is undersampled {where}: local frequency "
                f"{f_max / 1e3:.0f} cycles/mm > Nyquist {nyquist / 1e3:.0f} cycles/mm; use "
                f"dx ≤ {fmt_length(dx_needed)}, z1 ≥ "
                f"{fmt_length(float(z1) * f_max / nyquist)}, or the scaling-theorem PSF path",
                accept_undersampling)
    y, x = yx(shape, dx)
    k = 2 * jnp.pi / wavelength
    chirp = jnp.exp(1j * k * ((x - x1) ** 2 + (y - y1) ** 2) / (2 * z1))
    return piston(wavelength, z1) / (1j * wavelength * z1) * chirp


def thin_lens(shape, dx, wavelength, focal_length) -> Complex[Array, "ny nx"]:
    """Thin-lens transmission exp(−jk(x² + y²)/(2f)), f in metres (f < 0: diverging)."""
    _check_grid(shape, dx)
    check_positive("wavelength", wavelength, "m")
    check_positive("focal_length", focal_length, "m", allow_negative=True)
    if is_concrete(focal_length) and float(focal_length) == 0:
        raise DiffcamError("focal_length must be non-zero (metres).")
    k = 2 * jnp.pi / wavelength
    return jnp.exp(-1j * k * radius2(shape, dx) / (2 * focal_length))


def apply_phase(field: Num[Array, "... ny nx"], phase: Float[Array, "... ny nx"]
                ) -> Complex[Array, "... ny nx"]:
    """Thin diffuser (paper Eq. 5): U'' = U' · e^{jθd}; ``phase`` θd in radians."""
    check_field(field)
    check_finite("phase", phase)
    if is_concrete(phase) and np.shape(phase)[-2:] != np.shape(field)[-2:]:
        raise DiffcamError(f"phase shape {np.shape(phase)} does not match the field's "
                           f"spatial shape {np.shape(field)[-2:]}.")
    return field * jnp.exp(1j * jnp.asarray(phase))
