"""Old names still import and give the new function's result; each warns once."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core import deprecation
from diffcam.core.backend import separable_factor, vector
from diffcam.evaluate.baseline import magnify_psf, scale_psf
from diffcam.optics import lens, propagation


@pytest.mark.parametrize("old, new, args", [
    (vector, separable_factor, (lambda i: jnp.cos(0.1 * i), 37)),
    (propagation.fourier_lens, lens.fourier_lens, (np.ones((8, 8), np.complex64), 5e-6,
                                                  532e-9, 0.05)),
    (scale_psf, magnify_psf, (np.outer(np.hanning(32), np.hanning(32)), 20e-3, 30e-3, 1e-3,
                              2e-6)),
])
def test_renamed_functions_warn_once_and_agree(old, new, args, monkeypatch):
    monkeypatch.setattr(deprecation, "_warned", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first, second = old(*args), old(*args)
    messages = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(messages) == 1 and new.__name__ in messages[0]
    for a, b in ((first, new(*args)), (second, first)):
        for x, y in zip(*(v if isinstance(v, tuple) else (v,) for v in (a, b))):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_moved_modules_import_from_their_old_paths_and_warn_once(monkeypatch):
    monkeypatch.setattr(deprecation, "_warned", set())
    for old in ("diffcam.calibrate.stack_fit", "diffcam.calibrate.phase_io"):
        monkeypatch.delitem(__import__("sys").modules, old, raising=False)
    from diffcam.calibrate.phase import file
    from diffcam.calibrate.stack import fit
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from diffcam.calibrate.stack_fit import StackFitOptions, fit_stack
        import diffcam.calibrate.stack_fit as again
        from diffcam.calibrate.phase_io import load_phase
    messages = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(messages) == 2 and "diffcam.calibrate.stack.fit" in messages[0]
    assert (fit_stack, StackFitOptions, load_phase) == (fit.fit_stack, fit.StackFitOptions,
                                                        file.load_phase)
    assert again.fit_stack is fit.fit_stack and "fit_stack" in dir(again)
    with pytest.raises(ImportError):
        from diffcam.calibrate.stack_fit import no_such_name  # noqa: F401
