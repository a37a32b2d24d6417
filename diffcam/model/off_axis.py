"""What changes a diffuser camera's PSF across its field: three physical terms, each a
`Camera` field that is ``None`` (left out) by default.

Without them the engine's off-axis PSF is the on-axis one moved by −(y1, x1)·z2/z1 (a
thin diffuser with the aperture in its plane); `diffcam.model.field` models what they
add.

**The stop's shadow** (``aperture_distance`` d, metres). The circular aperture of radius
a stands d in front of the diffuser. Seen from a source at (y1, x1, z1) (z1 from the
diffuser) its geometric shadow on the diffuser is the disc

    centre −(y1, x1)·d/(z1 − d),   radius a·z1/(z1 − d),

so another source lights another patch of the diffuser, and its PSF is another pattern.
The shadow is geometric: the stop's Fresnel number a²/(λd) is in the hundreds for
sizes of interest (a = 0.1 mm, d = 1 mm, λ = 532 nm: 19), so its edge diffraction spans
√(λd) ≈ 23 µm, a few samples of the edge ramp at most.

**The sensor's angular response** (``acceptance_exponent`` p). A pixel (its microlens,
the depth of its stack) records the fraction

    A(θ) = cos^p θ

of the power of a plane wave arriving at incidence θ (half of it at θ = arccos 2^(−1/p)).
The field at the sensor is a sum of plane waves, sin θ = λ|f| for spatial frequency f,
so the recorded field has its angular spectrum multiplied by √A. For an off-axis source
the whole spectrum is tilted by the source's field angle: the light from the edge of
the field arrives obliquely, and the response filters it differently (the PSF's shape
changes). On the direct path √A multiplies the transfer function. On the scaling path
the field at the sensor is the magnified z_eff field times the spherical wave
exp(jk|u − ρ1|²/(2(z1 + z2))) of the source; that wave is written about the PSF's
centre u_c = −ρ1·z2/z1 as a gentle chirp (sampled on the sensor grid) times the tilt
f_c = −ρ1/(λz1), which moves the filter instead: √A(λ|f + f_c|) on the FFT of the
sampled field, exact at any field angle. That FFT spans the crop plus `MARGIN` samples
per side (the response's kernel, ~λ/(π sin θ), is well within them).

**Vignetting** (``vignetting_exponent`` n). The irradiance a point source delivers
falls as cos^n of its field angle θ1, cos θ1 = z1/√(z1² + y1² + x1²): n = 3 for the
light reaching the diffuser (1/r² and its obliquity), 4 with the sensor's own
obliquity. A normalised PSF (unit sum) divides it out; ``normalise=False`` shows it.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import Float

from diffcam.core.backend import fft2, ifft2
from diffcam.core.errors import DiffcamError, fmt_length, is_concrete, sampling_problem
from diffcam.core.grid import fft_freqs, pad_to
from diffcam.core.phasor import expj
from diffcam.optics.elements import circular_aperture

__all__ = ["disc_samples", "acceptance", "response_amplitude", "stop_shadow", "lit_radius",
           "accepted_on_sensor", "vignetting", "check_off_axis", "MARGIN"]

MARGIN = 8
"""Samples added per side of the sensor crop over which the scaling path filters the
field by the angular response (wrap-around stays outside the crop)."""


def disc_samples(radius) -> Float[Array, "7 2"]:
    """Points standing for an extended source, a disc: its centre and six points on a
    circle of ``radius`` (any length unit, returned in it), 60° apart, weighted alike.
    ``(7, 2)`` offsets ``(y, x)``; ``radius`` may be traced."""
    angles = jnp.arange(6) * (jnp.pi / 3)
    rim = radius * jnp.stack([jnp.sin(angles), jnp.cos(angles)], axis=1)
    return jnp.concatenate([jnp.zeros((1, 2), rim.dtype), rim])


def acceptance(sin2_theta, exponent) -> Array:
    """A(θ) = cos^p θ = (1 − sin²θ)^(p/2): the fraction of a plane wave's power a pixel
    records at incidence θ (``sin2_theta`` = sin²θ; evanescent waves record none)."""
    cos2 = jnp.maximum(1 - sin2_theta, jnp.finfo(jnp.result_type(sin2_theta, 0.0)).tiny)
    return jnp.where(sin2_theta < 1, cos2 ** (exponent / 2), 0.0)


def response_amplitude(shape, dx, wavelength, exponent, tilt=(0.0, 0.0)) -> Array:
    """√A on the FFT grid of ``shape`` (pitch ``dx``, metres), for a field whose
    frequencies are offset by ``tilt`` (fy, fx) (cycles/m): multiplies its spectrum."""
    fy, fx = fft_freqs(shape, dx)
    sin2 = wavelength ** 2 * ((fy + tilt[0]) ** 2 + (fx + tilt[1]) ** 2)
    return jnp.sqrt(acceptance(sin2, exponent))


def _shadow_geometry(camera, z1, y1, x1):
    """Centre (y, x) and radius (metres) of the stop's shadow on the diffuser."""
    d = camera.aperture_distance
    return (-y1 * d / (z1 - d), -x1 * d / (z1 - d)), camera.aperture_radius * z1 / (z1 - d)


def stop_shadow(camera, z1, offset) -> Float[Array, "Ny Nx"]:
    """The stop's shadow on the padded diffuser grid for the source at ``offset`` (y1,
    x1) and ``z1`` (metres)."""
    centre, radius = _shadow_geometry(camera, z1, offset[0], offset[1])
    shadow = circular_aperture(camera.shape, camera.dx, radius, centre, edge=camera.edge)
    return pad_to(shadow, camera.padded_shape)


def lit_radius(camera, z1: float, rho: float) -> float:
    """Largest distance from the axis (metres) at which light from a source ``rho``
    (metres) off axis at ``z1`` passes the aperture onto the diffuser."""
    if camera.aperture_distance is None:
        return camera.support_radius()
    centre, radius = _shadow_geometry(camera, z1, rho, 0.0)
    return float(radius) + abs(float(centre[0]))


def accepted_on_sensor(field, camera, wavelength, z1, y1, x1) -> Array:
    """The sampled z_eff field on the sensor crop plus `MARGIN` per side, as the pixels
    record it (the module's scaling-path filter): the crop, complex, up to a phase."""
    ny, nx = field.shape[-2:]
    cy, cx = camera.out_shape
    lam_r = wavelength * (z1 + camera.z2)
    shift = camera.z2 / z1

    def chirp(c, offset):   # exp(jπ(u − u_c)²/(λ(z1 + z2))) on the crop's axis + margin
        u = (jnp.arange(c + 2 * MARGIN) - MARGIN - c // 2) * camera.dx
        return expj(jnp.pi * (u + offset * shift) ** 2 / lam_r)
    tilted = field * chirp(cy, y1)[:, None] * chirp(cx, x1)[None, :]
    tilt = (-y1 / (wavelength * z1), -x1 / (wavelength * z1))
    out = ifft2(fft2(tilted) * response_amplitude((ny, nx), camera.dx, wavelength,
                                                  camera.acceptance_exponent, tilt))
    return out[..., MARGIN:ny - MARGIN, MARGIN:nx - MARGIN]


def vignetting(camera, z1, positions) -> Array:
    """cos^n θ1 of each source's field angle, (npos, 1, 1); 1 without the term."""
    if camera.vignetting_exponent is None:
        return 1.0
    cos2 = z1 ** 2 / (z1 ** 2 + positions[:, 0] ** 2 + positions[:, 1] ** 2)
    return (cos2 ** (camera.vignetting_exponent / 2))[:, None, None]


def check_off_axis(camera, z_min: float, rho: float, wavelengths,
                   accept_undersampling: bool) -> None:
    """The stop stands between the source and the diffuser and its shadow fits the grid
    (``z_min``, ``rho``: nearest depth, farthest offset, metres); on the scaling path the
    chirp `accepted_on_sensor` samples is below Nyquist at the shortest of
    ``wavelengths`` (metres)."""
    if not is_concrete(camera):
        return
    if camera.aperture_distance is not None:
        d = float(camera.aperture_distance)
        if z_min <= d:
            raise DiffcamError(
                f"a source at z1 = {fmt_length(z_min)} is not in front of the stop "
                f"(aperture_distance {fmt_length(d)}); give z1 > aperture_distance.")
        half = min(camera.shape) // 2 * float(camera.dx)
        if lit_radius(camera, z_min, rho) > half:
            raise DiffcamError(
                f"the stop's shadow for a source {fmt_length(rho)} off axis at z1 = "
                f"{fmt_length(z_min)} reaches {fmt_length(lit_radius(camera, z_min, rho))} "
                f"from the axis, beyond the grid's half-width {fmt_length(half)}; use more "
                f"samples (shape) or move the source towards the axis.")
    if camera.acceptance_exponent is not None and camera.method == "scaling":
        dx, z2 = float(camera.dx), float(camera.z2)
        reach = (0.5 * float(jnp.hypot(*camera.out_shape)) + MARGIN) * dx + rho * z2 / z_min
        lam = min(wavelengths)
        if reach / (lam * (z_min + z2)) > 1 / (2 * dx):
            sampling_problem(
                f"the source's spherical wave at the sensor tilts by up to "
                f"{reach / (z_min + z2):.3g} rad about the PSF's centre, beyond the "
                f"sensor grid's Nyquist angle {lam / (2 * dx):.3g} rad, so the angular "
                f"response cannot be applied; use a smaller crop or farther sources",
                accept_undersampling)

