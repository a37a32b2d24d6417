"""diffcam.calibrate.model_file: one door for both kinds of camera-model file."""

import numpy as np
import pytest

from diffcam.calibrate import PhaseFile, load_model, load_phase, model_kind, save_phase
from diffcam.calibrate.model_file import MODEL_FILES, load_stack_model
from diffcam.core.errors import DiffcamError


@pytest.fixture
def phase_path(tmp_path):
    path = tmp_path / "phase.npz"
    rng = np.random.default_rng(0)
    save_phase(path, PhaseFile(rng.uniform(-np.pi, np.pi, (32, 48)), 3.45e-6, 532e-9,
                               0.05e-3, {"solver": "raar"}))
    return path


def test_a_phase_file_reads_as_what_load_phase_reads(phase_path):
    assert model_kind(phase_path) == "phase"
    model, direct = load_model(phase_path), load_phase(phase_path)
    assert isinstance(model, PhaseFile)
    np.testing.assert_array_equal(model.phase, direct.phase)
    assert (model.dx, model.wavelength, model.info) == (direct.dx, direct.wavelength,
                                                         direct.info)


def test_where_plane_indices_are_needed_a_phase_file_says_what_to_do(phase_path):
    with pytest.raises(DiffcamError, match=r"diffcam psf .*phase\.npz --z1") as err:
        load_stack_model(phase_path)
    assert "\n" not in str(err.value)


def test_files_of_neither_kind(tmp_path):
    """Other arrays, a PSF stack, another suffix, a missing file: not models (kind None)
    and one line naming both kinds; a damaged .npz is a DiffcamError too."""
    other = tmp_path / "other.npz"
    np.savez(other, stack=np.zeros((2, 3, 3)), metadata=np.array('{"format": "x"}'))
    tif = tmp_path / "psf.tif"
    tif.write_bytes(b"II*\x00")
    for path in (other, tif, tmp_path / "missing.npz"):
        assert model_kind(path) is None
        with pytest.raises(DiffcamError, match=MODEL_FILES.replace("`", ".")) as err:
            load_model(path)
        assert "\n" not in str(err.value)
    damaged = tmp_path / "damaged.npz"
    damaged.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(DiffcamError, match="damaged.npz"):
        model_kind(damaged)
