"""Errors, warnings and the checks that public entry points run before tracing.

Every public numerical function validates its *concrete* arguments (shapes, signs,
NaN/Inf, sampling) before it calls its jitted core. When an argument is a JAX tracer
(the caller has wrapped diffcam in their own ``jit``/``grad``/``vmap``) the value check
is skipped: the caller has taken responsibility for it, and shapes are still checked.

This module does not import JAX (the command line's ``--help`` loads it without JAX): a
value can only be a JAX array or tracer once something has imported JAX, so the checks
look for JAX's types only then.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import warnings
from typing import Any

import numpy as np

__all__ = [
    "DiffcamError",
    "SamplingError",
    "ShapeError",
    "UndersamplingWarning",
    "GeometryWarning",
    "ConvergenceWarning",
    "is_concrete",
    "found_false",
    "check_positive",
    "check_finite",
    "environment_count",
    "check_field",
    "real_array",
    "real_number",
    "number_in",
    "whole_number",
    "sampling_problem",
]


class DiffcamError(ValueError):
    """Base class of diffcam's input errors (a ``ValueError``: the input is wrong)."""


class ShapeError(DiffcamError):
    """An array has the wrong number of axes, an empty axis, or mismatched shape."""


class SamplingError(DiffcamError):
    """A kernel or field would be undersampled (aliased) on the requested grid."""


class UndersamplingWarning(UserWarning):
    """Undersampling the caller accepted explicitly (``accept_undersampling=True``)."""


class GeometryWarning(UserWarning):
    """The captures disagree with the geometry they were resampled with: a pitch, a focal
    length or a wavelength is probably wrong (the result would be a confident wrong phase)."""


class ConvergenceWarning(UserWarning):
    """An iteration that did not settle: a fit whose loss stopped falling far above zero,
    or a regularised deconvolution whose objective rose (it oscillates)."""


_PLAIN = (int, float, complex, bool, str, np.ndarray, np.generic, type(None))


class _NoJax:
    """Stands for JAX's array and tracer types while JAX is not loaded: nothing is one."""


def _jax_types() -> tuple[type, type]:
    """``(jax.Array, jax.core.Tracer)``, or `_NoJax` twice before JAX is loaded."""
    jax = sys.modules.get("jax")
    return (_NoJax, _NoJax) if jax is None else (jax.Array, jax.core.Tracer)


def is_concrete(*values: Any) -> bool:
    """True if none of ``values`` is a JAX tracer (so their values can be inspected)."""
    if all(isinstance(v, _PLAIN) for v in values):  # the common case, without a tree walk
        return True
    jax = sys.modules.get("jax")
    return jax is None or not any(isinstance(v, jax.core.Tracer)
                                  for v in jax.tree_util.tree_leaves(values))


def plain_numbers(*values: Any) -> bool:
    """True if every value is a Python number (not a bool) or a tuple of them: hashable,
    and fixed once passed, so a check that passed for them can be remembered."""
    return all(all(map(plain_numbers, v)) if isinstance(v, tuple)
               else isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def check_positive(name: str, value: Any, unit: str, *, allow_zero: bool = False,
                   allow_negative: bool = False) -> None:
    """Raise ``DiffcamError`` unless ``value`` (scalar or array) is finite and > 0.

    Tracers pass unchecked. ``unit`` is used in the message, e.g. ``"m"``.
    """
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        v = float(value)             # a plain number: no array machinery on the hot path
        finite, negative, zero = math.isfinite(v), v < 0, v == 0
    elif not is_concrete(value):
        return
    else:
        arr = _as_real(name, value, f"a real number in {unit}").astype(np.float64)
        if arr.size == 0:
            raise DiffcamError(f"{name} is empty; give at least one value in {unit}.")
        finite, negative, zero = (bool(np.all(np.isfinite(arr))), bool(np.any(arr < 0)),
                                  bool(np.any(arr == 0)))
    if not finite:
        raise DiffcamError(f"{name} must be finite, got {_show(value)} ({unit}).")
    if allow_negative or not (negative or (zero and not allow_zero)):
        return
    need = ">= 0" if allow_zero else "> 0"
    raise DiffcamError(
        f"{name} must be {need} (SI units: {unit}), got {_show(value)}. "
        f"diffcam takes metres and radians everywhere: 25 mm is 25e-3."
    )


def environment_count(name: str, when_unset: str) -> int | None:
    """The environment variable ``name`` as a whole number ≥ 1, or None when it is unset
    or blank.

    Raises:
        DiffcamError: it holds anything else; the message ends with ``when_unset``, what
            unsetting it does (``"to use every CPU"``).
    """
    text = os.environ.get(name, "").strip()
    if not text:
        return None
    if not (text.isascii() and text.isdigit() and int(text) > 0):
        raise DiffcamError(f"{name} must be a whole number, at least 1, not {text!r:.40}; "
                           f"unset it {when_unset}.")
    return int(text)


def _show(value: Any) -> str:
    """``value`` for a message: a NumPy or JAX scalar as the plain number it holds."""
    if np.ndim(value) == 0 and isinstance(value, (np.generic, np.ndarray, _jax_types()[0])):
        return repr(value.item())
    return repr(value)


@functools.cache
def _all_finite():
    """A jitted ``isfinite(a).all()`` (made on first use: JAX is loaded by then)."""
    import jax

    return jax.jit(lambda a: jax.numpy.isfinite(a).all())


def found_false(flag: Any) -> bool:
    """Whether a jitted call's boolean flag (a device scalar) came back False; False for
    a tracer, which cannot be read. Read with ``np.asarray``: 4 µs per fresh flag here,
    where ``is_concrete`` and ``bool()`` took 20 (about a fifth of the Python around an
    eager 128² propagation)."""
    return not isinstance(flag, _jax_types()[1]) and not np.asarray(flag)


def check_finite(name: str, arr: Any) -> None:
    """Raise ``DiffcamError`` if a concrete array holds NaN or Inf."""
    if not is_concrete(arr):
        return
    if isinstance(arr, _jax_types()[0]):  # one fused pass on the device, no copy to the host
        import jax

        with jax.ensure_compile_time_eval():  # concrete even inside someone's jit trace
            ok = bool(np.asarray(_all_finite()(arr)))
            n_bad = 0 if ok else int(arr.size - jax.numpy.isfinite(arr).sum())
    else:
        finite = np.isfinite(_as_real(name, arr, "numeric", complex_ok=True))
        ok = bool(finite.all())
        n_bad = 0 if ok else int(finite.size - np.count_nonzero(finite))
    if not ok:
        raise DiffcamError(
            f"{name} contains {n_bad} NaN/Inf value(s); clean the input "
            f"(e.g. np.nan_to_num) or mask those pixels before calling diffcam."
        )


def _as_real(name: str, value: Any, what: str, *, complex_ok: bool = False) -> np.ndarray:
    """``value`` as a NumPy array of numbers (no copy if it already is one), or a
    DiffcamError naming ``name``: object, text and (unless ``complex_ok``) complex data
    are refused, whatever they hold."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        raise DiffcamError(f"{name} must be {what}, got {value!r:.80}.") from None
    if arr.dtype.kind not in ("biufc" if complex_ok else "biuf"):
        held = "complex numbers" if arr.dtype.kind == "c" else f"dtype {arr.dtype}"
        raise DiffcamError(f"{name} must be {what}, got {held} ({value!r:.60}); convert it "
                           f"first, e.g. np.asarray(x, dtype=np.float32).")
    return arr


def real_array(name: str, value: Any) -> Any:
    """``value`` as an array of real floats, the one conversion every public function
    applies to an image, a PSF or a capture: bool, integer and float16 data become the
    float type that holds them (float32 at least: ``np.result_type(dtype, float32)``),
    float32 and float64 arrays pass as they are (a JAX array or tracer stays one).

    Raises:
        DiffcamError: complex numbers (an intensity is real: a cast would drop the
            imaginary part), object or text data; the message names ``name``.
    """
    if not isinstance(value, (np.ndarray, np.generic, *_jax_types())):
        value = _as_real(name, value, "an array of real numbers")
    dtype = np.dtype(value.dtype)
    if dtype.kind == "c":
        raise DiffcamError(f"{name} must be real, got complex numbers ({dtype}), whose "
                           f"imaginary part a cast would drop: pass np.abs(x)**2 of a field "
                           f"(its intensity), or x.real if the imaginary part is rounding.")
    if dtype.kind not in "biuf":
        _as_real(name, value, "an array of real numbers")    # raises, naming the dtype
    if dtype.kind == "f" and dtype.itemsize >= 4:
        return value
    target = np.result_type(dtype, np.float32)
    if isinstance(value, _jax_types()):     # JAX holds float64 only with x64 on
        target = sys.modules["jax"].dtypes.canonicalize_dtype(target)
    return value.astype(target)


def real_number(name: str, value: Any, what: str) -> float:
    """``value`` as one Python float: a real number (or an array holding one), not a
    bool, text or several values; NaN and Inf pass (the caller checks the range).

    Raises:
        DiffcamError: anything else, saying ``name`` must be ``what`` (``"a step ≥ 0"``).
    """
    arr = _as_real(name, value, what)
    if arr.dtype.kind == "b" or arr.size != 1:
        raise DiffcamError(f"{name} must be {what}, got {value!r:.60}.")
    return float(arr.reshape(()))


def number_in(name: str, value: Any, low: float, high: float, what: str) -> float:
    """``value`` as a float in ``low`` … ``high`` (ends included), or a DiffcamError
    saying ``name`` must be ``what`` (``"a share of the peak in 0 … 1"``)."""
    v = real_number(name, value, what)
    if not low <= v <= high:
        raise DiffcamError(f"{name} must be {what}, got {value!r:.60}.")
    return v


def whole_number(name: str, value: Any, low: int, high: float = math.inf) -> int:
    """``value`` as an int in ``low`` … ``high``: a Python or NumPy integer, not a bool
    or a float, or a DiffcamError naming ``name``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or not low <= value <= high:
        span = f"≥ {low}" if high == math.inf else f"in {low} … {high}"
        raise DiffcamError(f"{name} must be a whole number {span}, got {value!r:.60}.")
    return int(value)


def check_field(field: Any, name: str = "field", *, finite: bool | str = True) -> None:
    """Check that ``field`` has at least two (space) axes, none of them empty, and holds
    no NaN/Inf (``finite=True``; ``"host"`` checks only a NumPy array, for a caller that
    checks a device array inside its own jitted call; ``False`` not at all)."""
    shape = np.shape(field)
    if len(shape) < 2:
        raise ShapeError(
            f"{name} must have at least 2 axes (..., ny, nx), got shape {shape}; "
            f"a 1-D profile can be given as field[None, :]."
        )
    if 0 in shape:
        raise ShapeError(f"{name} has an empty axis: shape {shape}.")
    if finite is True or (finite == "host" and not isinstance(field, _jax_types()[0])):
        check_finite(name, field)


def sampling_problem(message: str, accept_undersampling: bool) -> None:
    """Raise ``SamplingError(message)``, or warn if the caller accepted undersampling."""
    if accept_undersampling:
        warnings.warn(message, UndersamplingWarning, stacklevel=3)
    else:
        raise SamplingError(message + " (pass accept_undersampling=True to run anyway.)")


def fmt_length(x: float) -> str:
    """Format a length in metres with a readable unit (used in messages)."""
    ax = abs(x)
    if ax == 0 or not math.isfinite(ax):
        return f"{x} m"
    for unit, scale in (("m", 1.0), ("mm", 1e-3), ("µm", 1e-6), ("nm", 1e-9)):
        if ax >= scale:
            return f"{x / scale:.4g} {unit}"
    return f"{x:.3g} m"
