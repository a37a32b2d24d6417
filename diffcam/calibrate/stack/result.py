"""A fitted PSF-stack model (`StackFit`): prediction of any plane, and its file.

Prediction (`StackFit.predict`) is the rendered plane plus the part of the
measured planes the model does not reproduce, carried along by the model's own
magnification law. For each given plane k, least squares gives raw_k = a_k·render(k) +
b_k + R_k; plane t is predicted as (Σ_k w_k a_k)·render(t) + Σ_k w_k·T_{k→t}(R_k), T
the magnification by s(t)/s(k) about the fitted centre (cubic B-splines, zero outside),
w_k linear in t between the two given planes that bracket t (1 at its own plane), and
the nearest given plane's weight 1 outside the given range
(`diffcam.evaluate.registration.bracket_weights`). At a given plane this is the
measurement; elsewhere the model supplies the change between planes, the residual the
sub-pixel detail the field cannot interpolate at unseen pixels. ``residual=False``
renders the model alone.

The file (`StackFit.save`, `load_stack_fit`) is one ``.npz``: the model's
arrays, the prepared given planes, and a JSON metadata entry with a format version.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from diffcam.core.errors import DiffcamError, number_in, whole_number
from diffcam.core import grid as core_grid
from diffcam.evaluate.registration import (Registration, bracket_weights, magnify_about,
                                           relative_magnification_at, spline_coefficients)
from diffcam.io import atomic_output, check_output_path, read_npz
from diffcam.calibrate.stack.model import StackModel, coefficient_shape, render_planes

__all__ = ["StackFit", "load_stack_fit", "FORMAT", "FORMAT_VERSION", "MAX_PLANES"]

FORMAT = "diffcam-stack-fit"
FORMAT_VERSION = 3
_ARRAYS = ("field_real", "field_imag", "log_zeta", "log_s", "centre", "log_sigma", "kappa")

MAX_PLANES = 4096
"""Most planes one `StackFit.predict` call returns (a 270×320 frame: 1.4 GB);
raise it for the session by assigning to this constant."""


KAPPA_LIMIT = 10
"""Largest |κ| of the depth law ζ(t) = ζ_ref·s(t)^(−κ) that `StackFit.predict`
renders and a fit file may hold (1 is the scaling theorem's; a κ of 10⁶ overflows)."""


def _check_count(n: int) -> None:
    if n < 1:
        raise DiffcamError(f"no planes to predict (asked for {n}).")
    if n > MAX_PLANES:
        raise DiffcamError(f"{n} planes asked for; one call predicts at most {MAX_PLANES} "
                           f"(diffcam.calibrate.stack.result.MAX_PLANES): ask for fewer, or "
                           f"raise the limit.")


def _magnifications(model: StackModel, planes) -> np.ndarray:
    """s(t) = M(t)/M(reference) of ``planes`` in float64 on the host (the law of
    `StackModel.magnification`, without a JAX dispatch per plane)."""
    return relative_magnification_at(np.asarray(planes, np.float64),
                                     float(np.exp(float(model.log_s))), model.reference,
                                     model.anchor)


def _plane_index(t) -> int:
    """A plane index: an int (not a bool, not a fraction or a string)."""
    if isinstance(t, (bool, np.bool_)) or not isinstance(t, (int, np.integer)):
        raise DiffcamError(f"plane indices must be integers, got {t!r}.")
    return int(t)




@dataclasses.dataclass(frozen=True)
class StackFit:
    """The result of [`fit_stack`][diffcam.calibrate.stack.fit.fit_stack].

    Attributes:
        model: the fitted [`StackModel`][diffcam.calibrate.stack.model.StackModel] (at the
            best validation step).
        planes: the given planes (the reference first).
        n_planes: planes in the stack (``None`` if unknown), the default of
            [`predict`][diffcam.calibrate.stack.result.StackFit.predict].
        registration: M(anchor)/M(reference) and the fixed point (pixels).
        history: mean training Pearson of the given planes, per step.
        validation: mean validation Pearson, per step (of the model before the step).
        stop_reason: why the fit stopped.
        best_step: the step whose model was kept.
        validation_score: the kept model's validation Pearson.
        baseline_validation: the scaling baseline's Pearson on the same validation
            pixels (each given plane predicted from the nearest other given plane).
        worse_than_baseline: ``validation_score < baseline_validation``.
        zeta_scan: ``{ζ candidate (fine samples²): validation Pearson of its GS start}``.
        identifiable: what the data fix: ζ_ref in pixel units; with the pixel pitch and
            wavelength z2·M at the reference plane and over the stack (m), with z2 too
            the magnifications and z1 over the stack (`_identifiable`).
        physical: the physical inputs given (pixel pitch, wavelength, z2; m or None).
        options: the [`StackFitOptions`][diffcam.calibrate.stack.fit.StackFitOptions] as a
            dict.
        seconds: wall time of the fit, s.
        measured: the given planes as fitted
            ([`prepare_planes`][diffcam.calibrate.stack.inputs.prepare_planes]), in
            ``planes`` order, float32 (P, H, W): the residuals
            [`predict`][diffcam.calibrate.stack.result.StackFit.predict] carries come from
            them (``None`` in files of format 1: rendering only).
    """

    model: StackModel
    planes: tuple[int, ...]
    n_planes: int | None
    registration: Registration
    history: np.ndarray
    validation: np.ndarray
    stop_reason: str
    best_step: int
    validation_score: float
    baseline_validation: float
    worse_than_baseline: bool
    zeta_scan: dict
    identifiable: dict
    physical: dict
    options: dict
    seconds: float
    measured: np.ndarray | None = None

    @property
    def steps(self) -> int:
        return int(len(self.history))

    def predict(self, planes=None, *, kappa: float | None = None, residual: bool = True,
                light: bool = False) -> np.ndarray:
        """Predicted planes, each normalised to unit mean (like
        [`prepare_planes`][diffcam.calibrate.stack.inputs.prepare_planes]), or carrying its
        light.

        Args:
            planes: plane indices (any ints, also outside the measured range), a count
                n (planes 0 … n−1), or ``None`` for every plane of the fitted stack.
            kappa: render with this depth-law exponent instead of the fitted one
                (``kappa=0``: the frozen-distance ablation of the same field).
            residual: carry the measured planes' residuals (the module docstring);
                ``False`` renders the model alone.
            light: plane t's mean is instead its light relative to the reference
                plane's, ((M(t) − 1)/(M(ref) − 1))² (inverse-square law, M from the
                given planes' light: ``identifiable``), as a measured stack's planes
                keep their relative brightness.

        Returns:
            float32 array (k, H, W).

        Raises:
            DiffcamError: ``light=True`` for a fit whose planes' light did not follow
                the law (or a file saved without it).
        """
        ts = self._plane_list(planes)
        if light:
            gain = self._light(ts)
        model = self.model
        if kappa is not None and not (isinstance(kappa, (int, float, np.number))
                                      and not isinstance(kappa, bool)
                                      and abs(float(kappa)) <= KAPPA_LIMIT):
            raise DiffcamError(f"kappa must be a number in [-{KAPPA_LIMIT}, {KAPPA_LIMIT}] "
                               f"(1: the scaling theorem's depth law, 0: frozen distance), "
                               f"got {kappa!r}.")
        if kappa is not None:
            model = eqx.tree_at(lambda m: m.kappa, model, jnp.float32(kappa))
            if model.frozen and kappa != 0:
                model = dataclasses.replace(model, frozen=False)
        if residual and self.measured is not None:
            out = self._with_residuals(model, ts)
        else:
            out = render_planes(model, ts)
        out /= out.mean(axis=(-2, -1), keepdims=True)
        if light:
            out *= gain[:, None, None]
        out = out.astype(np.float32)
        bad = [t for t, plane in zip(ts, out) if not np.isfinite(plane).all()]
        if bad:
            raise DiffcamError(f"the model renders plane(s) {bad[:5]} dark or as NaN/Inf "
                               f"(its values are outside what a fit gives there); predict "
                               f"planes nearer the fitted ones {list(self.planes)}.")
        return out

    def _light(self, ts) -> np.ndarray:
        """Each plane's light relative to the reference plane's (inverse-square law)."""
        m_ref = self.identifiable.get("magnification_reference_from_light")
        if m_ref is None:
            raise DiffcamError("this fit has no light law (its planes' light did not follow "
                               "the inverse-square law, or it was saved without it): predict "
                               "without light=True, or fit the stack again.")
        return ((_magnifications(self.model, ts) * m_ref - 1.0) / (m_ref - 1.0)) ** 2

    def _plane_list(self, planes) -> list[int]:
        """The planes to predict, checked: whole numbers, at most `MAX_PLANES`,
        none beyond where the fitted magnification law reaches zero."""
        if planes is None:
            if self.n_planes is None:
                raise DiffcamError("this fit does not know the stack's plane count; pass "
                                   "the planes to predict.")
            planes = self.n_planes
        if isinstance(planes, (bool, np.bool_, str, bytes, float, np.floating)):
            raise DiffcamError(f"planes must be a count or a sequence of plane indices "
                               f"(integers), got {planes!r}.")
        if isinstance(planes, (int, np.integer)):
            _check_count(int(planes))
            ts = list(range(int(planes)))
        else:
            ts = [_plane_index(t) for t in np.asarray(planes, dtype=object).reshape(-1)]
            _check_count(len(ts))
        bad = [t for t, s in zip(ts, _magnifications(self.model, ts)) if not s > 0]
        if bad:
            raise DiffcamError(f"plane(s) {bad[:5]} lie beyond where the fitted "
                               f"magnification law reaches zero (it is linear in the plane "
                               f"index through planes {self.model.reference} and "
                               f"{self.model.anchor}); predict planes nearer the fitted "
                               f"ones.")
        return ts

    def _with_residuals(self, model: StackModel, ts: list[int]) -> np.ndarray:
        """(Σ w_k a_k)·render(t) + Σ w_k T_{k→t}(R_k) for every t (module docstring)."""
        planes = sorted(set(self.planes) | set(ts))    # each plane rendered once
        rendered = dict(zip(planes, render_planes(model, planes)))
        s = dict(zip(planes, _magnifications(model, planes)))
        gain, coef = {}, {}
        for k, y in zip(self.planes, self.measured.astype(np.float64)):
            a, b = np.polyfit(rendered[k].ravel(), y.ravel(), 1)
            gain[k] = a
            coef[k] = spline_coefficients(y - a * rendered[k] - b)
        centre = tuple(float(c) for c in np.asarray(model.centre))
        out = np.empty((len(ts),) + rendered[ts[0]].shape)
        for n, t in enumerate(ts):
            weights = bracket_weights(t, self.planes)
            out[n] = sum(w * gain[k] for k, w in weights.items()) * rendered[t]
            for k, w in weights.items():
                out[n] += w * magnify_about(coef[k], s[t] / s[k], centre, prefiltered=True)
        return out

    def summary(self) -> dict:
        """The scalar facts of the fit, JSON-able."""
        m = self.model
        return {"planes": list(self.planes), "n_planes": self.n_planes,
                "stop_reason": self.stop_reason, "best_step": self.best_step,
                "steps": self.steps, "validation_score": self.validation_score,
                "baseline_validation": self.baseline_validation,
                "worse_than_baseline": self.worse_than_baseline,
                "zeta_reference_px2": m.zeta_pixels, "kappa": float(m.kappa),
                "frozen": m.frozen, "magnification": float(np.exp(float(m.log_s))),
                "grid_magnification": m.grid_magnification,
                "centre": [float(c) for c in np.asarray(m.centre)],
                "blur_sigma_fine": float(np.exp(float(m.log_sigma))),
                "seconds": self.seconds}

    def save(self, path: str | os.PathLike) -> Path:
        """Write the fit to one ``.npz`` file (arrays and a JSON metadata entry with a
        format version), atomically: a temporary file in the same folder, then
        ``os.replace``. Read it back with
        [`load_stack_fit`][diffcam.calibrate.stack.result.load_stack_fit]."""
        path = check_output_path(path, suffixes=(".npz",))
        m = self.model
        meta = {
            "format": FORMAT, "version": FORMAT_VERSION,
            "geometry": {"frame": list(m.frame), "pad": m.pad, "grid": list(m.grid),
                         "stride": m.stride, "reference": m.reference, "anchor": m.anchor,
                         "oversample": m.oversample, "frozen": m.frozen,
                         "grid_magnification": m.grid_magnification},
            "planes": list(self.planes), "n_planes": self.n_planes,
            "registration": dataclasses.asdict(self.registration),
            "stop_reason": self.stop_reason, "best_step": self.best_step,
            "validation_score": self.validation_score,
            "baseline_validation": self.baseline_validation,
            "worse_than_baseline": self.worse_than_baseline,
            "zeta_scan": {str(k): v for k, v in self.zeta_scan.items()},
            "identifiable": self.identifiable, "physical": self.physical,
            "options": self.options, "seconds": self.seconds,
        }
        arrays = {k: np.asarray(getattr(m, k)) for k in _ARRAYS}
        if self.measured is not None:
            arrays["measured"] = np.asarray(self.measured, np.float32)
        with atomic_output(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, metadata=np.array(json.dumps(meta)),
                         history=np.asarray(self.history, np.float64),
                         validation=np.asarray(self.validation, np.float64), **arrays)
        return path



def load_stack_fit(path: str | os.PathLike) -> StackFit:
    """Read a [`StackFit`][diffcam.calibrate.stack.result.StackFit] written by
    [`StackFit.save`][diffcam.calibrate.stack.result.StackFit.save].

    Raises:
        DiffcamError: missing, corrupt or truncated file, not a stack-fit file, another
            format version (an older one says to fit again), or arrays that do not match
            the recorded geometry.
    """
    what = "a diffcam stack-fit file"
    data = read_npz(path, ("metadata",), what=what)
    try:
        meta = json.loads(str(data["metadata"][()]))
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise DiffcamError(f"{path}: not {what} (format {meta.get('format')!r}).")
        version = meta.get("version")
        if not isinstance(version, int) or version > FORMAT_VERSION:
            raise DiffcamError(f"{path}: stack-fit format version {version!r}; this diffcam "
                               f"reads versions ≤ {FORMAT_VERSION}: upgrade diffcam.")
        if version < FORMAT_VERSION:
            raise DiffcamError(f"{path}: stack-fit format version {version} holds a "
                               f"per-sample phase model this diffcam no longer renders; "
                               f"fit the stack again (diffcam fit STACK --planes …).")
        data = read_npz(path, ("metadata", "history", "validation") + _ARRAYS, what=what)
        model = _model_from(data, meta["geometry"], path)
        planes, n_planes = _planes_from(path, meta, model)
        measured = _measured_from(path, meta, model)
        reg = meta["registration"]
        _real(path, "registration.magnification", reg["magnification"], 1e-3, 1e3)
        light = meta["identifiable"].get("magnification_reference_from_light")
        if light is not None:
            _real(path, "identifiable.magnification_reference_from_light", light,
                  1 + 1e-9, 1e9)
        return StackFit(
            model=model, planes=planes, n_planes=n_planes,
            registration=Registration(float(reg["magnification"]),
                                      tuple(float(c) for c in reg["centre"]),
                                      float(reg["pearson"]), float(reg.get("seconds", 0.0))),
            history=np.asarray(data["history"]), validation=np.asarray(data["validation"]),
            stop_reason=str(meta["stop_reason"]), best_step=int(meta["best_step"]),
            validation_score=float(meta["validation_score"]),
            baseline_validation=float(meta["baseline_validation"]),
            worse_than_baseline=bool(meta["worse_than_baseline"]),
            zeta_scan={float(k): v for k, v in meta["zeta_scan"].items()},
            identifiable=dict(meta["identifiable"]), physical=dict(meta["physical"]),
            options=dict(meta["options"]), seconds=float(meta["seconds"]),
            measured=measured)
    except DiffcamError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise DiffcamError(f"{path}: not a readable {what} ({type(err).__name__}: {err}); "
                           f"the metadata are missing or damaged.") from None


def _damaged(path, field: str, value, what: str) -> DiffcamError:
    """The one line for a value of a fit file that a fit cannot have written."""
    return DiffcamError(f"{path}: {field} = {value!r:.60} is not {what}; the file is damaged "
                        f"or was edited: fit the stack again (diffcam fit STACK --planes …).")


def _whole(path, field: str, value, low: int, high: float = math.inf) -> int:
    """A whole number of a fit file's metadata in ``low`` … ``high``."""
    try:
        return whole_number(field, value, low, high)
    except DiffcamError:
        raise _damaged(path, field, value, f"a whole number in {low} … {high}") from None


def _real(path, field: str, value, low: float, high: float) -> float:
    """A finite number of a fit file (metadata or a scalar array) in ``low`` … ``high``."""
    what = f"one finite number in {low:g} … {high:g}"
    try:
        return number_in(field, value, low, high, what)
    except DiffcamError:
        shown = value.item() if np.ndim(value) == 0 and hasattr(value, "item") else value
        raise _damaged(path, field, shown, what) from None


def _model_from(data, g: dict, path) -> StackModel:
    """The `StackModel` of a fit file, every value checked against the ranges a
    fit produces and its arrays against its recorded geometry (`_check_model`)."""
    side = math.isqrt(core_grid.MAX_GRID_SAMPLES)
    frame = g["frame"]
    if not isinstance(frame, list) or len(frame) != 2:
        raise _damaged(path, "geometry.frame", frame, "a [height, width] pair")
    frame = tuple(_whole(path, "geometry.frame", v, 1, side) for v in frame)
    pad = _whole(path, "geometry.pad", g["pad"], 0, side)
    stride = _whole(path, "geometry.stride", g["stride"], 1, side)
    oversample = _whole(path, "geometry.oversample", g["oversample"], 1, 16)
    reference = _whole(path, "geometry.reference", g["reference"], 0, MAX_PLANES - 1)
    anchor = _whole(path, "geometry.anchor", g["anchor"], 0, MAX_PLANES - 1)
    if anchor == reference:
        raise _damaged(path, "geometry.anchor", anchor, "a plane other than the reference")
    grid = g["grid"]
    need = [oversample * n + 2 * pad for n in frame]
    if not isinstance(grid, list) or len(grid) != 2 or not all(
            isinstance(v, int) and not isinstance(v, bool) and n <= v <= side
            for v, n in zip(grid, need)):
        raise _damaged(path, "geometry.grid", grid, f"a field grid that holds the "
                       f"oversampled frame and its pad ({need[0]}×{need[1]} or more)")
    if not isinstance(g["frozen"], bool):
        raise _damaged(path, "geometry.frozen", g["frozen"], "true or false")
    grid_magnification = _real(path, "geometry.grid_magnification",
                               g.get("grid_magnification", 1.0), 1e-3, 1e3)
    shapes = {k: () for k in ("log_zeta", "log_s", "log_sigma", "kappa")}
    shapes.update(field_real=coefficient_shape(tuple(grid), stride),
                  field_imag=coefficient_shape(tuple(grid), stride), centre=(2,))
    arrays = {}
    for k, shape in shapes.items():
        a = np.asarray(data[k])
        if a.shape != shape or a.dtype.kind not in "iuf" or not np.isfinite(a).all():
            raise DiffcamError(f"{path}: the array {k} ({a.dtype}, shape {a.shape}) is not "
                               f"finite real numbers of the recorded geometry's shape "
                               f"{shape}; the file is damaged: fit the stack again.")
        arrays[k] = a
    # ranges: a fit's own values lie far inside these; outside them a rendering
    # overflows float32 (ζ·s^−κ, the blur's exp) or samples nothing (a far centre)
    _real(path, "kappa", arrays["kappa"], -KAPPA_LIMIT, KAPPA_LIMIT)
    _real(path, "log_zeta", arrays["log_zeta"], -30.0, 30.0)
    _real(path, "log_s", arrays["log_s"], -math.log(1e3), math.log(1e3))
    _real(path, "log_sigma", arrays["log_sigma"], -30.0, math.log(max(grid)))
    reach = 100 * max(frame)
    if np.abs(arrays["centre"]).max() > reach:
        raise _damaged(path, "centre", arrays["centre"].tolist(),
                       f"within {reach} pixels of the frame")
    return StackModel(
        **{k: jnp.asarray(a, jnp.float32) for k, a in arrays.items()},
        frame=frame, pad=pad, grid=tuple(grid), stride=stride, reference=reference,
        anchor=anchor, oversample=oversample, frozen=g["frozen"],
        grid_magnification=grid_magnification)


def _planes_from(path, meta: dict, model: StackModel) -> tuple[tuple[int, ...], int | None]:
    """The given planes (two or more, distinct, the reference first, the anchor among
    them) and the stack's plane count (None or a whole number) of a fit file."""
    planes = meta["planes"]
    if not isinstance(planes, list):
        raise _damaged(path, "planes", planes, "a list of plane indices")
    planes = tuple(_whole(path, "planes", t, 0, MAX_PLANES - 1) for t in planes)
    if len(set(planes)) != len(planes) or len(planes) < 2 or \
            planes[0] != model.reference or model.anchor not in planes:
        raise _damaged(path, "planes", list(planes), f"two or more distinct planes "
                       f"starting with the reference {model.reference} and holding the "
                       f"anchor {model.anchor}")
    n = meta["n_planes"]     # its range is checked where the planes are rendered
    if n is not None and (isinstance(n, bool) or not isinstance(n, int)):
        raise _damaged(path, "n_planes", n, "a whole number or null")
    return planes, n


def _measured_from(path, meta: dict, model: StackModel) -> np.ndarray:
    """The prepared given planes stored by format ≥ 2, checked against the geometry."""
    measured = read_npz(path, ("measured",), what="a diffcam stack-fit file")["measured"]
    measured = np.asarray(measured, np.float32)
    if measured.shape != (len(meta["planes"]),) + model.frame or \
            not np.isfinite(measured).all():
        raise DiffcamError(f"{path}: the measured planes ({measured.shape}) do not match "
                           f"the recorded planes and frame or hold NaN/Inf; the file is "
                           f"damaged.")
    return measured


# ------------------------------------------------------------------------ input checks
