"""Optical elements on a centred grid: apertures (paper Eqs. 3–4), the point-source field
at the aperture plane (Eq. 2), a thin lens, and the thin diffuser (Eq. 5).

Elements are transmission functions (arrays of shape ``(ny, nx)``) or fields; combine
them by multiplication. Any array works as an aperture mask: real DiffuserCam apertures
are rectangular or set by the sensor.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Complex, Float, Num

from diffcam.core.errors import (DiffcamError, check_field, check_finite, check_positive,
                                 fmt_length, is_concrete)
from diffcam.core.grid import pitch_yx, radius2, yx
from diffcam.core.phasor import expj
from diffcam.optics.fields import piston
from diffcam.optics.propagation import spherical_chirp
from diffcam.optics.sampling import check_point_source_sampling

__all__ = [
    "circular_aperture",
    "rectangular_aperture",
    "point_source_field",
    "spherical_wave",
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
    r2 = radius2(shape, dx, centre)
    if edge == "hard":
        return (r2 <= _hard_edge_r2(radius, r2.dtype)).astype(jnp.float32)
    return _edge(radius - _safe_sqrt(r2), jnp.minimum(*pitch_yx(dx)), edge)


def _hard_edge_r2(radius, dtype):
    """The largest r² of ``dtype`` whose rounded square root is ≤ ``radius``: r² ≤ it
    keeps exactly the samples with sqrt(r²) ≤ radius (the hard edge), in either
    precision, with no square root over the grid. XLA computes such a square root once
    and keeps it as an N² array for reverse mode (4 MB of a 1024² gradient's 20); a
    comparison with a scalar it recomputes in each consumer. (r² ≤ radius² alone
    rounds differently: samples on the rim flipped between float32 and float64.) The
    threshold is within two units in the last place of radius², found by stepping; its
    derivative in the radius is 0, like the hard edge's."""
    limit = jax.lax.stop_gradient(jnp.asarray(radius))
    t = (limit * limit).astype(dtype)
    for _ in range(4):
        t = jnp.where(jnp.sqrt(t) > limit, jnp.nextafter(t, jnp.zeros_like(t)), t)
    for _ in range(4):
        up = jnp.nextafter(t, jnp.full_like(t, jnp.inf))
        t = jnp.where(jnp.sqrt(up) <= limit, up, t)
    return t


def _safe_sqrt(r2):
    """sqrt with a finite gradient at 0 (the sample on the centre): the double ``where``
    keeps d sqrt(r²) = 1/(2r) = inf out of the backward pass, where inf·0 would be NaN
    (in the gradient with respect to ``dx``, ``radius`` or ``centre``)."""
    positive = r2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, r2, 1.0)), 0.0)


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


def spherical_wave(shape, dx, wavelength, z1, *, y1=0.0, x1=0.0):
    """The two 1-D factors ``(cy[:, None], cx[None, :])`` of the paraxial spherical wave
    exp(jk((x − x1)² + (y − y1)²)/(2 z1)) of a point source at (x1, y1, z1) (metres), on
    the centred grid of ``shape`` and pitch ``dx``: paper Eq. 2 without its constant
    e^{jkz1}/(jλz1). Unchecked; `point_source_field` is the checked entry."""
    dy, dxx = pitch_yx(dx)
    cy = spherical_chirp(shape[-2], dy, wavelength, z1, y1)
    cx = spherical_chirp(shape[-1], dxx, wavelength, z1, x1)
    return cy[:, None], cx[None, :]


def point_source_field(shape, dx, wavelength, z1, *, y1=0.0, x1=0.0, aperture_radius=None,
                       accept_undersampling: bool = False) -> Complex[Array, "ny nx"]:
    """Paraxial field of a unit point source at (x1, y1, z1) on the aperture plane, Eq. 2:

        U(x, y) = e^{jkz1}/(jλz1) · exp(jk((x − x1)² + (y − y1)²)/(2 z1)).

    Args:
        shape: grid shape ``(..., ny, nx)``.
        dx: pitch, metres.
        wavelength: metres.
        z1: source distance in front of the aperture, metres (> 0).
        y1, x1: lateral source position, metres (keywords).
        aperture_radius: the chirp must be sampled only where light passes: give the
            aperture radius (metres) to check there; ``None`` checks the whole grid.
        accept_undersampling: warn instead of raising when the chirp aliases.

    Raises:
        SamplingError: the chirp's local frequency exceeds Nyquist 1/(2·dx) within
            the checked radius. Close sources need the scaling-theorem path
            (`diffcam.model.point_spread`), which never samples this chirp.
    """
    _check_grid(shape, dx)
    check_positive("wavelength", wavelength, "m")
    check_positive("z1", z1, "m")
    check_finite("x1", x1)
    check_finite("y1", y1)
    if is_concrete(dx, wavelength, z1, x1, y1, aperture_radius):
        dy, dxx = (float(p) for p in pitch_yx(dx))
        if aperture_radius is None:
            radius, where = np.hypot(shape[-2] // 2 * dy, shape[-1] // 2 * dxx), "at the grid corner"
        else:
            radius, where = float(aperture_radius), "at the aperture edge"
        check_point_source_sampling(float(wavelength), float(z1), radius,
                                    float(np.hypot(float(x1), float(y1))), max(dy, dxx), where,
                                    accept_undersampling)
    cy, cx = spherical_wave(shape, dx, wavelength, z1, y1=y1, x1=x1)
    return piston(wavelength, z1) / (1j * wavelength * z1) * (cy * cx)


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
    return _phase_screen(jnp.asarray(field), jnp.asarray(phase))


@jax.checkpoint
def _phase_screen(field, phase):
    """U·e^{jθ}, recomputed in a reverse pass instead of kept for it: e^{jθ} costs a few
    products (`diffcam.core.phasor.expj`), keeping it a complex array written and
    read again (a 4096² PSF's gradient: 448 → 320 MB of temporaries and about a sixth
    faster, ``benchmarks/bench_grad.py``)."""
    return field * expj(phase)
