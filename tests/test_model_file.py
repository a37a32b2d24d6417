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


# ------------------------------------------------- crafted files of the current format

@pytest.fixture(scope="module")
def fit_path(tmp_path_factory):
    """A small stack-fit file, built without fitting (a 12×12 frame, planes 0 and 3)."""
    import jax.numpy as jnp

    from diffcam.calibrate.stack.model import StackModel, coefficient_shape
    from diffcam.calibrate.stack.result import StackFit
    from diffcam.evaluate.registration import Registration

    rng = np.random.default_rng(0)
    grid, stride = (32, 32), 2
    coarse = coefficient_shape(grid, stride)
    model = StackModel(
        field_real=jnp.asarray(rng.normal(size=coarse), jnp.float32),
        field_imag=jnp.asarray(rng.normal(size=coarse), jnp.float32),
        log_zeta=jnp.float32(np.log(40.0)), log_s=jnp.float32(0.05),
        centre=jnp.asarray([5.5, 5.5], jnp.float32), log_sigma=jnp.float32(0.0),
        kappa=jnp.float32(1.0), frame=(12, 12), pad=4, grid=grid, stride=stride,
        reference=0, anchor=3, oversample=2, grid_magnification=1.02)
    fit = StackFit(model=model, planes=(0, 3), n_planes=4,
                   registration=Registration(1.05, (5.5, 5.5), 0.9, 0.0),
                   history=np.zeros(2), validation=np.zeros(2), stop_reason="test",
                   best_step=1, validation_score=0.9, baseline_validation=0.8,
                   worse_than_baseline=False, zeta_scan={}, identifiable={}, physical={},
                   options={}, seconds=0.0,
                   measured=rng.random((2, 12, 12)).astype(np.float32) + 0.5)
    path = tmp_path_factory.mktemp("fit") / "fit.npz"
    fit.save(path)
    return path


def _crafted(path, folder, *, meta=None, arrays=None):
    """A copy of the fit file at ``path`` with ``meta(metadata)`` and ``arrays(dict)``
    applied (each edits in place)."""
    import json

    with np.load(path) as f:
        contents = dict(f)
    metadata = json.loads(str(contents["metadata"][()]))
    (meta or (lambda m: None))(metadata)
    (arrays or (lambda a: None))(contents)
    contents["metadata"] = np.array(json.dumps(metadata))
    out = folder / "crafted.npz"
    np.savez(out, **contents)
    return out


def _geometry(key, value):
    return lambda m: m["geometry"].__setitem__(key, value)


def _array(key, value):
    return lambda a: a.__setitem__(key, np.asarray(value, np.float32))


CRAFTED = {   # field named in the message: how the file was edited
    "kappa": dict(arrays=_array("kappa", 1e6)),          # SVD did not converge in predict
    "geometry.oversample": dict(meta=_geometry("oversample", 0)),  # ZeroDivisionError
    "geometry.oversample ": dict(meta=_geometry("oversample", 2.5)),
    "geometry.stride": dict(meta=_geometry("stride", 0)),
    "geometry.pad": dict(meta=_geometry("pad", -4)),
    "geometry.frame": dict(meta=_geometry("frame", [12, True])),
    "geometry.grid": dict(meta=_geometry("grid", [16, 32])),     # smaller than the frame
    "geometry.anchor": dict(meta=_geometry("anchor", 0)),        # the reference again
    "geometry.frozen": dict(meta=_geometry("frozen", "no")),
    "geometry.grid_magnification": dict(meta=_geometry("grid_magnification", -1.0)),
    "log_zeta": dict(arrays=_array("log_zeta", 300.0)),
    "log_s": dict(arrays=_array("log_s", -40.0)),
    "log_sigma": dict(arrays=_array("log_sigma", 50.0)),
    "centre": dict(arrays=_array("centre", [1e30, 0.0])),
    "field_real": dict(arrays=_array("field_real", np.zeros((5, 5)))),
    "log_zeta ": dict(arrays=_array("log_zeta", [1.0, 2.0])),
    "planes": dict(meta=lambda m: m.__setitem__("planes", [0, 0])),
    "n_planes": dict(meta=lambda m: m.__setitem__("n_planes", "four")),
    "registration.magnification": dict(
        meta=lambda m: m["registration"].__setitem__("magnification", float("nan"))),
    "identifiable.magnification_reference_from_light": dict(
        meta=lambda m: m["identifiable"].__setitem__(
            "magnification_reference_from_light", 1.0)),
}


@pytest.mark.parametrize("field", CRAFTED)
def test_a_crafted_fit_file_names_the_field(fit_path, tmp_path, field):
    """Each value a fit cannot have written, through the loaders the commands use: one
    DiffcamError line naming the file and the field and saying what to do."""
    from diffcam.calibrate import load_stack_fit

    path = _crafted(fit_path, tmp_path, **CRAFTED[field])
    for load in (load_stack_fit, load_model):
        with pytest.raises(DiffcamError) as err:
            load(path)
        message = str(err.value)
        assert "\n" not in message and str(path) in message, message
        assert field.strip() in message and "fit the stack again" in message, message


def test_the_small_fit_file_loads(fit_path):
    """The file the crafted ones are made from is valid (what they fail on is the edit)."""
    fit = load_model(fit_path)
    assert fit.planes == (0, 3) and fit.model.oversample == 2


@pytest.mark.parametrize("edit, field", [
    (lambda m: m.__setitem__("depths", [25e-3, -1e-3]), "depths"),
    (lambda m: m.__setitem__("pitch", 0.0), "pitch"),
    (lambda m: m.__setitem__("wavelengths", [float("nan")]), "wavelengths"),
    (lambda m: m.__setitem__("weights", [1.0, 1.0]), "weights"),
    (lambda m: m.__setitem__("offsets", [[0.0, float("inf")]]), "offsets")])
def test_a_crafted_psf_stack_names_the_field(tmp_path, edit, field):
    """A PSF stack file whose metadata hold a depth, pitch, wavelength, weight or offset
    no camera has: one line naming the file and the field."""
    import json

    from diffcam.model.stack import StackMeta, load_stack, save_stack

    meta = StackMeta(depths=np.array([25e-3, 30e-3]), offsets=np.zeros((1, 2)),
                     pitch=5e-6, wavelengths=np.array([532e-9]), weights=np.array([1.0]),
                     camera={})
    good = tmp_path / "stack.npz"
    save_stack(good, np.ones((2, 1, 4, 4), np.float32), meta)
    with np.load(good) as f:
        contents = dict(f)
    recorded = json.loads(str(contents["meta"]))
    edit(recorded)
    contents["meta"] = np.array(json.dumps(recorded))
    bad = tmp_path / "bad.npz"
    np.savez(bad, **contents)
    assert load_stack(good)[0].shape == (2, 1, 4, 4)
    with pytest.raises(DiffcamError) as err:
        load_stack(bad)
    assert "\n" not in str(err.value) and str(bad) in str(err.value)
    assert field in str(err.value)


def test_a_crafted_fit_file_through_the_command_line(fit_path, tmp_path, capsys):
    """``diffcam predict`` and ``diffcam psf`` of the κ = 10⁶ file: exit 2, one line
    naming the field, the existing output kept (it was an SVD traceback)."""
    from diffcam.apps.cli import main

    path = _crafted(fit_path, tmp_path, **CRAFTED["kappa"])
    out = tmp_path / "out.tif"
    out.write_bytes(b"old")
    for argv in (["predict", str(path), "-o", str(out)],
                 ["psf", str(path), "--planes", "0:3", "-o", str(out)]):
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "kappa" in err, err
        assert "Traceback" not in err and out.read_bytes() == b"old"
