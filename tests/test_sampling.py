"""The sampling planner (diffcam/sampling.py) against docs/design.md's numbers."""

import numpy as np
import pytest

from diffcam.core.errors import DiffcamError
from diffcam.optics.sampling import phase_bandwidth, plan_sampling


def test_paper_simulation_limits():
    """Paper's simulation (R = 1.2 mm, λ = 532 nm, dx = 5 µm): on-axis chirp reaches
    Nyquist at z1 = 22.56 mm, so 22 mm is undersampled and the planner recommends the
    scaling theorem; z_eff and M follow z1·z2/(z1 + z2) and (z1 + z2)/z1."""
    plan = plan_sampling(532e-9, 5e-6, 4000, 22e-3, 1e-3, 1.2e-3)
    assert np.isclose(plan.min_direct_z1, 22.556e-3, rtol=1e-4)
    assert not plan.direct_sampled and "scaling theorem" in plan.recommended_path
    assert np.isclose(plan.z_eff, 22e-3 * 1e-3 / 23e-3)
    assert np.isclose(plan.magnification, 23 / 22)
    assert np.isclose(plan.fresnel_number_z2, (1.2e-3) ** 2 / (532e-9 * 1e-3))
    assert "transfer function" in plan.z2_method
    assert "UNDERSAMPLED" in str(plan)


def test_real_camera_limit_and_offsets():
    """Real camera (R = 2.3 mm, 3.45 µm): every z1 < 29.8 mm is undersampled
    (docs/design.md); a lateral offset raises the limit by (R + ρ)/R."""
    plan = plan_sampling(532e-9, 3.45e-6, 4096, 30e-3, 1e-3, 2.3e-3)
    assert np.isclose(plan.min_direct_z1, 29.83e-3, rtol=1e-3) and plan.direct_sampled
    off = plan_sampling(532e-9, 3.45e-6, 4096, 30e-3, 1e-3, 2.3e-3, max_offset=0.23e-3)
    assert np.isclose(off.min_direct_z1, 1.1 * plan.min_direct_z1)


def test_diffuser_bandwidth_adds_to_chirp():
    """A linear phase ramp of 20 cycles/mm has bandwidth 20 cycles/mm, which lowers the
    chirp's room below Nyquist: z1_min = (R + ρ)/(λ (f_N − f_d))."""
    n, dx = 256, 5e-6
    x = (np.arange(n) - n // 2) * dx
    ramp = 2 * np.pi * 20e3 * np.broadcast_to(x, (n, n))
    assert np.isclose(phase_bandwidth(ramp, dx), 20e3, rtol=1e-6)
    plan = plan_sampling(532e-9, dx, n, 30e-3, 1e-3, 0.6e-3, diffuser=ramp)
    assert np.isclose(plan.min_direct_z1, 0.6e-3 / (532e-9 * (1e5 - 20e3)), rtol=1e-6)


def test_padding_and_method_choice():
    """A large z2 on a small grid: the PSF footprint R·M exceeds the half-width, so the
    planner asks for padding; beyond N·dx²/λ it names the impulse response."""
    plan = plan_sampling(532e-9, 5e-6, 512, 25e-3, 20e-3, 1.2e-3)
    assert plan.pad_needed == int(np.ceil((1.2e-3 * 45 / 25 - 256 * 5e-6) / 5e-6))
    assert "transfer function" in plan.z2_method  # N·dx²/λ = 24 mm > 20 mm
    far = plan_sampling(532e-9, 5e-6, 512, 25e-3, 50e-3, 0.5e-3)
    assert "impulse response" in far.z2_method


def test_planner_bad_input():
    """Non-positive distances, an aperture wider than the grid, a bad n."""
    with pytest.raises(DiffcamError, match="z1"):
        plan_sampling(532e-9, 5e-6, 512, 0.0, 1e-3, 1e-3)
    with pytest.raises(DiffcamError, match="half-width"):
        plan_sampling(532e-9, 5e-6, 100, 25e-3, 1e-3, 1e-3)
    with pytest.raises(DiffcamError, match="n must be"):
        plan_sampling(532e-9, 5e-6, 1.5, 25e-3, 1e-3, 1e-4)
