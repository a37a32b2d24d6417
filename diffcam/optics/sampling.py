"""The sampling planner: is a diffuser-camera simulation sampled, before anything runs?

`plan_sampling` takes the geometry of paper Eq. 7 (point source at depth z1 and
lateral offset ρ1, aperture of radius R with a diffuser, sensor at z2) and the grid
(N samples of pitch dx), and reports, with margins:

- the Fresnel number N_F = R²/(λz) of the aperture seen from the sensor (z = z2) and
  from the scaling theorem's effective distance z_eff = z1·z2/(z1 + z2);
- whether the point-source chirp plus the diffuser's own bandwidth is sampled at the
  aperture edge: local frequency (R + ρ1)/(λ·z1) + max|∇θd|/(2π) against Nyquist
  1/(2·dx), and the smallest z1 the direct path can take;
- whether a transfer function (|z| ≤ N·dx²/λ) or the impulse response samples the
  propagation by z2 (and by z_eff);
- the zero padding needed so the PSF's footprint does not wrap around the grid;
- the recommended path: direct, or the Fresnel scaling theorem.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from diffcam.core.errors import (DiffcamError, ShapeError, check_finite, check_positive,
                                 fmt_length, sampling_problem)
from diffcam.core.grid import pitch_yx
from diffcam.optics.propagation import effective_distance, magnification

__all__ = ["SamplingPlan", "plan_sampling", "phase_bandwidth", "point_source_max_frequency",
           "check_point_source_sampling"]


def phase_bandwidth(phase, dx, mask=None, quantile: float = 1.0) -> float:
    """Largest local frequency max|∇θ|/(2π) of a phase screen θ (radians), cycles/m.

    Wrapped phase is handled by differencing e^{jθ}. ``quantile < 1`` ignores the
    steepest fraction of samples (e.g. 0.999, for isolated phase-wrap artefacts).
    """
    theta = np.asarray(phase, dtype=np.float64)
    if theta.ndim != 2:
        raise ShapeError(f"phase must be 2-D (ny, nx), got shape {theta.shape}.")
    check_finite("phase", theta)
    dy, dxx = (float(p) for p in pitch_yx(dx))
    e = np.exp(1j * theta)
    gy = np.angle(e[1:, :] * np.conj(e[:-1, :])) / dy
    gx = np.angle(e[:, 1:] * np.conj(e[:, :-1])) / dxx
    g = np.hypot(gy[:, :-1], gx[:-1, :])
    if mask is not None:
        g = g[np.asarray(mask)[:-1, :-1] > 0]
    if g.size == 0:
        return 0.0
    return float(np.quantile(g, quantile) / (2 * np.pi))


def point_source_max_frequency(wavelength, z1, radius, offset=0.0) -> float:
    """Largest local spatial frequency of the point-source chirp within ``radius`` (1/m).

    (radius + |offset|)/(λ·z1): the spherical wave from a source at lateral distance
    ``offset`` and depth ``z1``, seen at the edge of an aperture of ``radius`` (metres).
    """
    return (radius + abs(offset)) / (wavelength * z1)


def check_point_source_sampling(wavelength: float, z1: float, radius: float, offset: float,
                                dx: float, where: str, accept_undersampling: bool) -> None:
    """The one check of the point-source chirp (paper Eq. 2) against Nyquist 1/(2·dx):
    a `SamplingError` (or a warning if accepted) that says what to change.
    Lengths in metres; ``where`` names the radius checked ("at the aperture edge")."""
    f_max = point_source_max_frequency(wavelength, z1, radius, offset)
    nyquist = 1 / (2 * dx)
    if f_max > nyquist:
        sampling_problem(
            f"point-source chirp is undersampled {where} for z1 = {fmt_length(z1)}: local "
            f"frequency {f_max / 1e3:.0f} cycles/mm > Nyquist {nyquist / 1e3:.0f} cycles/mm; "
            f"use z1 ≥ {fmt_length(z1 * f_max / nyquist)}, dx ≤ {fmt_length(1 / (2 * f_max))}, "
            f"or the scaling-theorem PSF path (Camera(method='scaling'), the default), which "
            f"never samples this chirp", accept_undersampling)


@dataclass(frozen=True)
class SamplingPlan:
    """What `plan_sampling` found. Lengths in metres, frequencies in cycles/m."""

    wavelength: float
    dx: float
    n: int
    z1: float
    z2: float
    aperture_radius: float
    max_offset: float
    fresnel_number_z2: float
    fresnel_number_zeff: float
    z_eff: float
    magnification: float
    chirp_frequency: float
    diffuser_frequency: float
    nyquist: float
    chirp_margin: float
    direct_sampled: bool
    min_direct_z1: float
    critical_distance: float
    z2_method: str
    zeff_method: str
    pad_needed: int
    recommended_path: str
    notes: list = field(default_factory=list)

    def __str__(self) -> str:
        rows = [
            ("grid", f"{self.n} × {self.n} at {fmt_length(self.dx)} "
                     f"(width {fmt_length(self.n * self.dx)})"),
            ("Fresnel number R²/(λ·z2)", f"{self.fresnel_number_z2:.3g}"),
            ("Fresnel number R²/(λ·z_eff)", f"{self.fresnel_number_zeff:.3g} "
                                            f"(z_eff = {fmt_length(self.z_eff)}, "
                                            f"M = {self.magnification:.4g})"),
            ("point-source chirp at aperture edge", f"{self.chirp_frequency / 1e3:.1f} cycles/mm"),
            ("diffuser bandwidth", f"{self.diffuser_frequency / 1e3:.1f} cycles/mm"),
            ("Nyquist 1/(2·dx)", f"{self.nyquist / 1e3:.1f} cycles/mm"),
            ("direct path", ("sampled" if self.direct_sampled else "UNDERSAMPLED")
             + f" (margin ×{self.chirp_margin:.3g}; needs z1 ≥ {fmt_length(self.min_direct_z1)})"),
            ("N·dx²/λ", fmt_length(self.critical_distance)),
            ("propagation by z2", self.z2_method),
            ("propagation by z_eff", self.zeff_method),
            ("padding against wrap-around", f"{self.pad_needed} samples per side"),
            ("recommended", self.recommended_path),
        ]
        w = max(len(k) for k, _ in rows)
        lines = [f"{k:<{w}}  {v}" for k, v in rows] + [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


def _method_for(z: float, z_crit: float) -> str:
    if z <= z_crit:
        return f"transfer function / angular spectrum (z = {fmt_length(z)} ≤ N·dx²/λ)"
    return f"impulse response (z = {fmt_length(z)} > N·dx²/λ; a transfer function would alias)"


def _diffuser_bandwidth(diffuser, dx, notes) -> float:
    """The diffuser's bandwidth (cycles/m): measured from its phase (an array), or as
    given (a number); 0 with a note when ``None``."""
    if diffuser is not None and np.ndim(diffuser) >= 2:
        return phase_bandwidth(diffuser, dx)
    if diffuser is not None:
        check_positive("diffuser bandwidth", diffuser, "cycles/m", allow_zero=True)
        return float(diffuser)
    notes.append("no diffuser phase given: its bandwidth (a 1° diffuser adds about "
                 "16–33 cycles/mm) is not included")
    return 0.0


def _footprint(wavelength, z1, z2, aperture_radius, offset, diffuser_frequency) -> float:
    """Half-width (m) of the PSF on the sensor: the aperture's shadow magnified by M, plus
    the diffuser's deflection over z2 (tan of its largest angle), plus the source offset."""
    sin_d = min(wavelength * diffuser_frequency, 0.999)
    return (aperture_radius * magnification(z1, z2) + offset * z2 / z1
            + z2 * sin_d / math.sqrt(1 - sin_d ** 2))


def plan_sampling(wavelength: float, dx: float, n: int, z1: float, z2: float,
                  aperture_radius: float, max_offset: float = 0.0,
                  diffuser=None) -> SamplingPlan:
    """Check the sampling of the PSF model of paper Eq. 7 before running it.

    Args:
        wavelength: metres.
        dx: grid pitch at the diffuser, metres per sample.
        n: samples per side of the (square) simulation grid.
        z1: smallest source depth that will be simulated, metres.
        z2: diffuser-to-sensor distance, metres.
        aperture_radius: metres.
        max_offset: largest lateral source offset √(x1² + y1²), metres.
        diffuser: optional: the diffuser phase (a 2-D array, radians, pitch ``dx``),
            whose bandwidth adds to the chirp's, or that bandwidth in cycles/m (a number,
            e.g. tan(1°)/λ ≈ 33 cycles/mm for a 1° diffuser at 532 nm).

    Returns:
        A `SamplingPlan`; ``print(plan)`` gives a readable report.
    """
    for name, v in (("wavelength", wavelength), ("dx", dx), ("z1", z1), ("z2", z2),
                    ("aperture_radius", aperture_radius)):
        check_positive(name, v, "m")
    check_positive("max_offset", max_offset, "m", allow_zero=True)
    if not isinstance(n, (int, np.integer)) or n < 2:
        raise DiffcamError(f"n must be an int ≥ 2 (samples per side), got {n!r}.")
    lam, dx, z1, z2, R = map(float, (wavelength, dx, z1, z2, aperture_radius))
    rho = float(max_offset)
    half_width = (n // 2) * dx
    if R > half_width:
        raise DiffcamError(f"aperture radius {fmt_length(R)} exceeds the grid half-width "
                           f"{fmt_length(half_width)}; use more samples.")
    notes = []
    f_diff = _diffuser_bandwidth(diffuser, dx, notes)
    nyquist = 1 / (2 * dx)
    f_chirp = point_source_max_frequency(lam, z1, R, rho)
    total = f_chirp + f_diff
    margin = nyquist / total if total > 0 else math.inf
    room = nyquist - f_diff
    min_z1 = (R + rho) / (lam * room) if room > 0 else math.inf
    if room <= 0:
        notes.append("the diffuser alone exceeds Nyquist: refine dx")
    z_eff, m = effective_distance(z1, z2), magnification(z1, z2)
    z_crit = n * dx * dx / lam
    pad = max(0, math.ceil((_footprint(lam, z1, z2, R, rho, f_diff) - half_width) / dx))
    direct = total <= nyquist
    if direct:
        path = "direct (point-source chirp sampled); the scaling theorem also works"
    else:
        path = (f"scaling theorem (the direct path aliases for z1 < {fmt_length(min_z1)}): "
                f"propagate the diffuser field by z_eff = {fmt_length(z_eff)}, magnify by "
                f"M = {m:.4g}")
    return SamplingPlan(
        wavelength=lam, dx=dx, n=int(n), z1=z1, z2=z2, aperture_radius=R, max_offset=rho,
        fresnel_number_z2=R * R / (lam * z2), fresnel_number_zeff=R * R / (lam * z_eff),
        z_eff=z_eff, magnification=m, chirp_frequency=f_chirp, diffuser_frequency=f_diff,
        nyquist=nyquist, chirp_margin=margin, direct_sampled=direct, min_direct_z1=min_z1,
        critical_distance=z_crit, z2_method=_method_for(z2, z_crit),
        zeff_method=_method_for(z_eff, z_crit), pad_needed=pad, recommended_path=path,
        notes=notes)
