"""A far capture resampled at a wrong Fourier-lens pitch (f, λ or the sensor pitch wrong)
is flagged by its speckle: its grain must be λf/D for the lit diffuser width D that the
near capture shows."""

import re
import warnings

import jax
import numpy as np
import pytest

from diffcam.calibrate import (CalibrationGeometry, paper_simulation, prepare_captures,
                               synthetic_captures)
from diffcam.calibrate.phase.near_far import (SPECKLE_RATIO_RANGE, check_far_speckle,
                                        far_speckle_ratio)
from diffcam.core.errors import GeometryWarning

N, SENSOR, F = 128, 3.45e-6, 6e-3   # as tests/test_retrieval_captures.py: far pitch 4.99 µm


def geometry(focal_length=F):
    return CalibrationGeometry(dx=5e-6, wavelength=532e-9, focal_length=focal_length)


@pytest.fixture(scope="module")
def raw():
    """Noisy 12-bit captures (10⁴ photons at the peak) of the scaled cameraman diffuser."""
    sim = paper_simulation(N, 64)
    return synthetic_captures(sim.phase, sim.aperture, geometry(), jax.random.key(5),
                              sensor_pitch=SENSOR, sensor_shape=(184, 184))


def prepare(raw, focal_length):
    return prepare_captures(*raw, geometry(focal_length), (N, N), sensor_pitch=SENSOR,
                            background=(82, 82), saturation=4095)


@pytest.mark.slow
def test_the_right_pitch_gives_no_warning(raw):
    with warnings.catch_warnings():
        warnings.simplefilter("error", GeometryWarning)
        p = prepare(raw, F)
    lo, hi = SPECKLE_RATIO_RANGE
    assert lo < far_speckle_ratio(p.near, p.far) < hi


def test_the_exact_simulation_passes():
    sim = paper_simulation(N, 64)
    with warnings.catch_warnings():
        warnings.simplefilter("error", GeometryWarning)
        ratio = check_far_speckle(sim.near, sim.far, sim.geometry)
    assert 0.8 < ratio < 1.0


@pytest.mark.parametrize("factor, too", [(10.0, "large"), (0.1, "small")])
def test_a_focal_length_off_by_10x_warns(raw, factor, too):
    """f 10× too long puts the far pitch 10× too large (speckle finer than a sample), 10×
    too short 10× too small (speckle 10× coarser): one GeometryWarning naming what to check,
    with the measured and the expected grain."""
    with pytest.warns(GeometryWarning) as record:
        prepare(raw, F * factor)
    assert len(record) == 1
    message = str(record[0].message)
    assert record[0].filename == __file__   # points at the caller of prepare_captures
    for part in ("speckle grain", "λf/D", f"too {too}", "focal length", "wavelength",
                 "sensor pixel pitch = 3.45 µm"):
        assert part in message, part
    looks = float(re.search(r"looks ([0-9.]+)×", message).group(1))
    if factor < 1:   # coarser speckle is measured: the factor itself
        assert 7 < looks < 13
    else:            # finer than a sample is capped by the grid: "or more"
        assert looks > 1.5 and "or more too large" in message


def test_a_uniform_stray_light_level_drops_out(raw):
    """10 % of the peak added to either capture leaves the ratio as it was."""
    p = prepare(raw, F)
    near, far = np.asarray(p.near), np.asarray(p.far)
    ratio = far_speckle_ratio(near, far)
    assert far_speckle_ratio(near + 0.1 * near.max(), far) == pytest.approx(ratio)
    assert far_speckle_ratio(near, far + 0.1 * far.max()) == pytest.approx(ratio)
