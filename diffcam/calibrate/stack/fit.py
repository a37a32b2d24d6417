"""Fit the wave model of a PSF stack to a few measured planes (`fit_stack`).

A DiffuserCam PSF stack is a set of caustics of one diffuser for point sources at
depths equally spaced in 1/z1. Given a few of its planes (two or more), the fitted
model (`diffcam.calibrate.stack.model.StackModel`) predicts the others
(`diffcam.calibrate.stack.result.StackFit.predict`) better than the scaling
baseline (`diffcam.evaluate.registration.scaling_baseline`), which magnifies the
nearest measured plane.

The fit (`fit_stack`): register the reference plane (the first given one) with
the given plane farthest from it; for each candidate ζ_ref run Gerchberg–Saxton between
the given planes, take the least-squares spline coefficients of its field, and keep
the best start; then Adam (optax) with per-group step sizes on
Σ_k (1 − Pearson over the training pixels of plane k). A fraction of the pixels of every
given plane (fixed seed) is held out for validation; the parameters with the best
validation Pearson are kept, and the fit stops when validation has not improved for
``patience`` steps or at ``max_steps``: the same steps, and the same model, on any
machine and under any load (a wall-clock ``time_budget`` is an option). Planes that are
not given never enter.

What is identifiable: ζ = λ·z_eff/dx² (and the magnification law, the centre, the
blur). z2 and the absolute magnification are not: under the Fresnel scaling theorem a
diffuser scaled by a, seen with magnification M·a from z2/a, gives the same PSFs at
every depth, so the planes fix z_eff(t) = z2/M(t) but not z2. With the pixel pitch the
result reports λ·z_eff; with the wavelength too, z_eff.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from typing import NamedTuple, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import scipy.ndimage as ndi
from jax import Array

from diffcam.core.backend import fft_size, transfer_step
from diffcam.core.errors import DiffcamError, real_number
from diffcam.core.options import Options
from diffcam.core.progress import new_bar
from diffcam.core.phasor import expj
from diffcam.calibrate.phase.projections import fit_amplitude
from diffcam.calibrate.stack.inputs import (check_physical, check_saturation, given_planes,
                                            prepare_planes, saturation_level)
from diffcam.calibrate.stack.model import (StackModel, coefficient_shape, coefficients_of,
                                           edge_taper, fresnel_kernel, identifiable,
                                           render_planes)
from diffcam.calibrate.stack import result as stack_result
from diffcam.calibrate.stack.result import StackFit
from diffcam.core.deprecation import renamed
from diffcam.evaluate.metrics import pearson
from diffcam.evaluate.registration import (Registration, magnification_from_light,
                                           magnify_about, register_magnification,
                                           relative_magnification_at)
from diffcam.io.preprocessing import plane_light

__all__ = ["StackFitOptions", "StackFitWarning", "fit_stack"]


class StackFitWarning(UserWarning):
    """A stack fit that ended worse than the scaling baseline on its validation pixels."""


# ----------------------------------------------------------------------------- options

_OPTIMISTIX = {"lbfgs": optx.LBFGS, "nonlinear_cg": optx.NonlinearCG}
OPTIMISERS = ("adam", *_OPTIMISTIX)
ZETA_START = 4.0
"""ζ_ref's start without physical inputs, pixel² (λ·z_eff/pitch²): the shipped stack's
scale. Two planes can leave the fit near its start (docs/stack_fit.md)."""


class StackFitOptions(Options):
    """How [`fit_stack`][diffcam.calibrate.stack.fit.fit_stack] runs. Lengths in fine
    samples (1/``oversample`` pixel).

    Attributes:
        max_steps: Adam steps at most.
        patience: stop after this many steps without a better validation Pearson.
        time_budget: an optional wall-clock limit of the fit, s (registration,
            initialisation, compilation and steps; checked after every step, so a fit
            may end about one step later). ``None`` (the default) or ``math.inf``: none,
            so the steps taken, and the model, do not depend on the machine's speed or
            load.
        validation_fraction: share of each given plane's pixels held out (0 < f < 0.5).
        seed: the validation split's and the GS start's seed.
        zetas: candidate ζ_ref for the GS start, fine samples² (λ·z_eff/dx_fine²).
            ``None``: the far-source value o²·λ·z2/pitch² when ``pixel_pitch``,
            ``wavelength`` and ``z2`` are given to
            [`fit_stack`][diffcam.calibrate.stack.fit.fit_stack], else o²·`ZETA_START` (4
            pixel², the shipped stack's scale). With several, each start descends
            ``scan_steps`` steps and the best validation Pearson is kept.
        scan_steps: steps each candidate of a ζ scan descends before one is chosen
            (the ranking of the starts themselves can differ from the ranking after
            descent: docs/stack_fit.md).
        gs_iterations: Gerchberg–Saxton sweeps per candidate.
        oversample: fine samples per pixel (2: the prototype's).
        pad: fine samples of field grid beyond the frame on each side.
        field_stride: fine samples between field coefficients (the field is a cubic
            B-spline: band-limited at one coefficient per ``field_stride`` samples).
        kappa: the depth-law exponent κ, ζ(t) = ζ_ref·s(t)^(−κ): 1 is the Fresnel
            scaling theorem (z_eff = z2/M).
        fit_kappa: fit κ (else it stays at ``kappa``).
        frozen: κ ≡ 0 (the frozen-distance ablation).
        sigma: start of the blur std, fine samples.
        amplitude_blur: std of the blur of the reference plane that gives the starting
            amplitude envelope, fine samples.
        dark_ring: width of the frame-border ring whose median is the dark level
            ([`prepare_planes`][diffcam.calibrate.stack.inputs.prepare_planes]), pixels.
        saturation: pixel value at or above which a given pixel is saturated (input
            units): ``"auto"`` is 0.999 × the full scale of an integer input and no
            check for float input; ``None`` skips the check. Saturated pixels raise.
        progress: show a progress bar over the steps.
        optimiser: ``"adam"`` (optax; per-group step sizes), or an optimistix minimiser
            on the same loss and validation stopping, ``"lbfgs"`` or ``"nonlinear_cg"``
            (both end lower on the shipped stack: docs/stack_fit.md, "Ablations").
        step_field, step_zeta, step_magnification, step_centre, step_blur, step_kappa:
            Adam step sizes of the field coefficients (of a field of unit mean
            intensity), log ζ, log s, centre (pixels), log σ and κ.
    """

    max_steps: int = 400
    patience: int = 40
    time_budget: float | None = None
    validation_fraction: float = 0.1
    seed: int = 0
    zetas: tuple[float, ...] | None = eqx.field(
        default=None,
        converter=lambda z: None if z is None else tuple(np.ravel(z).tolist()))
    scan_steps: int = 80
    gs_iterations: int = 30
    oversample: int = 2
    pad: int = 40
    field_stride: int = 2
    kappa: float = 1.0
    fit_kappa: bool = False
    frozen: bool = False
    sigma: float = 1.0
    amplitude_blur: float = 6.0
    dark_ring: int = 6
    step_field: float = 0.02
    step_zeta: float = 0.003
    step_magnification: float = 2e-5
    step_centre: float = 0.02
    step_blur: float = 0.01
    step_kappa: float = 0.01
    saturation: float | str | None = "auto"
    progress: bool = True
    optimiser: str = "adam"

    def __check_init__(self):
        for name in ("max_steps", "patience", "oversample", "field_stride", "scan_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise DiffcamError(f"{name} must be a positive int, got {v!r}.")
        for name in ("gs_iterations", "pad", "dark_ring", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise DiffcamError(f"{name} must be an int ≥ 0, got {v!r}.")
        if not 0 < real_number("validation_fraction", self.validation_fraction,
                               "a share in (0, 0.5)") < 0.5:
            raise DiffcamError(f"validation_fraction must be in (0, 0.5), got "
                               f"{self.validation_fraction!r}.")
        if self.optimiser not in OPTIMISERS:
            raise DiffcamError(f"optimiser must be one of {OPTIMISERS}, got "
                               f"{self.optimiser!r}.")
        if self.time_budget is not None and \
                not real_number("time_budget", self.time_budget, "seconds > 0") > 0:
            raise DiffcamError(f"time_budget must be > 0 s, got {self.time_budget!r}.")
        zetas = (ZETA_START,) if self.zetas is None else self.zetas
        what = "positive distances (fine samples², λ·z_eff/dx_fine²)"
        if not zetas or not all(0 < real_number("zetas", z, what) < math.inf for z in zetas):
            raise DiffcamError(f"zetas must be {what}, got {self.zetas!r}.")
        for name in ("sigma", "amplitude_blur"):
            if not 0 < real_number(name, getattr(self, name), "> 0 fine samples") < math.inf:
                raise DiffcamError(f"{name} must be a finite number > 0 (fine samples), "
                                   f"got {getattr(self, name)!r}.")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name.startswith("step_") and not (
                    0 <= real_number(f.name, v, "a finite step ≥ 0") < math.inf):
                raise DiffcamError(f"{f.name} must be a finite step ≥ 0, got {v!r}.")


    def to_dict(self) -> dict:
        return {f.name: (list(getattr(self, f.name)) if f.name == "zetas" and self.zetas
                         else getattr(self, f.name)) for f in dataclasses.fields(self)}


# -------------------------------------------------------------------- initialisation

def _training_only(img, train):
    """``img`` with its validation pixels (``train`` = 0) replaced by the mean of their
    training neighbours (a normalised Gaussian of 1 pixel): the start never sees them."""
    weight = ndi.gaussian_filter(train, 1.0)
    fill = ndi.gaussian_filter(img * train, 1.0) / np.maximum(weight, 1e-6)
    return np.where(train > 0, img, fill)


def _to_field_grid(img, s, centre, model: StackModel, order: int = 3):
    """A measured plane at magnification ``s`` (relative to the reference) resampled
    onto the field grid (at s = m0), spline ``order``: (intensity ≥ 0, where-measured
    mask)."""
    o, (h, w) = model.oversample, model.frame
    s = s / model.grid_magnification
    half = (o - 1) / 2.0
    py = (np.arange(model.grid[0]) - model.pad - half) / o
    px = (np.arange(model.grid[1]) - model.pad - half) / o
    sy = centre[0] + s * (py - centre[0])
    sx = centre[1] + s * (px - centre[1])
    yy, xx = np.meshgrid(sy, sx, indexing="ij")
    val = ndi.map_coordinates(img, [yy, xx], order=order, mode="constant", cval=0.0)
    known = (yy >= -0.5) & (yy <= h - 0.5) & (xx >= -0.5) & (xx <= w - 0.5)
    return np.clip(val, 0, None) * known, known


@jax.jit
def _gs(amp, mods, knowns, kernels, theta, n_iter):
    """Gerchberg–Saxton: amplitude ``amp`` at the diffuser, measured moduli at the
    planes (only where known), the planes visited in turn."""
    def body(_, th):
        for m, k, h in zip(mods, knowns, kernels):
            u = transfer_step(amp * expj(th), h)
            u = jnp.where(k, fit_amplitude(u, m), u)
            th = jnp.angle(transfer_step(u, jnp.conj(h)))
        return th
    return jax.lax.fori_loop(0, n_iter, body, theta)


def _initial_model(imgs, train, planes, reg: Registration, zeta, opts: StackFitOptions
                   ) -> StackModel:
    """Amplitude from the blurred reference plane, phase from GS between the planes
    on their training pixels (``train``: 1 there, per plane); the field's spline
    coefficients by least squares to A·e^{jθ}."""
    h, w = imgs[0].shape
    o, pad = opts.oversample, opts.pad
    grid = (fft_size(o * h + 2 * pad), fft_size(o * w + 2 * pad))
    stride = opts.field_stride
    coarse = coefficient_shape(grid, stride)
    ref, anchor = planes[0], max(planes[1:], key=lambda t: abs(t - planes[0]))
    kappa0 = 0.0 if opts.frozen else float(opts.kappa)
    ss = [float(relative_magnification_at(t, reg.magnification, ref, anchor)) for t in planes]
    shell = StackModel(
        field_real=jnp.zeros(coarse, jnp.float32),
        field_imag=jnp.zeros(coarse, jnp.float32),
        log_zeta=jnp.float32(np.log(zeta)), log_s=jnp.float32(np.log(reg.magnification)),
        centre=jnp.asarray(reg.centre, jnp.float32), log_sigma=jnp.float32(np.log(opts.sigma)),
        kappa=jnp.float32(kappa0), frame=(h, w), pad=pad, grid=grid, stride=stride,
        reference=ref, anchor=anchor, oversample=o, frozen=bool(opts.frozen),
        grid_magnification=float(np.sqrt(min(ss) * max(ss))))
    taper = np.outer(edge_taper(grid[0], pad), edge_taper(grid[1], pad))
    grids = [_to_field_grid(_training_only(img, m), s, reg.centre, shell)
             for img, m, s in zip(imgs, train, ss)]
    knowns = [k & (_to_field_grid(m, s, reg.centre, shell, order=0)[0] > 0.5)
              for (_, k), m, s in zip(grids, train, ss)]
    env = np.where(grids[0][1], ndi.gaussian_filter(grids[0][0], opts.amplitude_blur), 0.0)
    amp = np.sqrt(np.clip(env, 0, None)) * taper
    energy = (amp ** 2).sum()
    mods = [np.sqrt(i * energy / max(i.sum(), 1e-30)) for i, _ in grids]
    kernels = [fresnel_kernel(grid, jnp.float32(zeta * s ** (-kappa0))) for s in ss]
    th0 = (0.1 * np.random.default_rng(opts.seed).standard_normal(grid)).astype(np.float32)
    theta = _gs(jnp.asarray(amp, jnp.float32), [jnp.asarray(m, jnp.float32) for m in mods],
                [jnp.asarray(k) for k in knowns], kernels,
                jnp.asarray(th0), int(opts.gs_iterations))
    c = coefficients_of(jnp.asarray(amp, jnp.float32) * expj(theta), grid, stride)
    return dataclasses.replace(shell, field_real=c.real, field_imag=c.imag)


class _Data(eqx.Module):
    ys: Array       # (P, h, w) prepared given planes; the reference first
    train: Array    # (P, h, w) 1 on training pixels
    val: Array      # (P, h, w) 1 on validation pixels
    ts: Array       # (P,) plane indices


def _scores(model: StackModel, data: _Data):
    spec = model.spectrum()
    pred = jnp.stack([model.render_plane(spec, data.ts[k]) for k in range(data.ts.shape[0])])
    r_tr = pearson(pred, data.ys, mask=data.train)
    r_va = pearson(pred, data.ys, mask=data.val)
    return r_tr, r_va


def _loss(model, data):
    r_tr, r_va = _scores(model, data)
    return (1.0 - r_tr).sum(), (r_tr.mean(), jax.lax.stop_gradient(r_va.mean()))


@eqx.filter_jit
def _evaluate(model, data):
    return _loss(model, data)[1]


_ADAM = optax.scale_by_adam(b1=0.9, b2=0.999, eps=1e-12)
"""Adam's direction; each parameter group then takes its own step size
(`_step_sizes`). One transformation for every fit: the step compiles once per
model geometry."""


def _step_sizes(model: StackModel, opts: StackFitOptions):
    """The step size of each parameter group, as a pytree of the model's arrays."""
    kappa = opts.step_kappa if (opts.fit_kappa and not opts.frozen) else 0.0
    sizes = dict(field_real=opts.step_field, field_imag=opts.step_field,
                 log_zeta=opts.step_zeta, log_s=opts.step_magnification,
                 centre=opts.step_centre, log_sigma=opts.step_blur, kappa=kappa)
    params = eqx.filter(model, eqx.is_array)
    return dataclasses.replace(params, **{k: jnp.float32(v) for k, v in sizes.items()})


@eqx.filter_jit
def _step(model, state, data, steps):
    """One Adam step with per-group ``steps``; returns the new model and state and the
    (training, validation) Pearson of the model *before* the step."""
    (_, (r_tr, r_va)), grads = eqx.filter_value_and_grad(_loss, has_aux=True)(model, data)
    direction, state = _ADAM.update(grads, state)
    updates = jax.tree.map(lambda d, size: -size * d, direction, steps)
    return eqx.apply_updates(model, updates), state, r_tr, r_va


def _adam(model: StackModel, data: _Data, opts: StackFitOptions):
    """Adam with per-group step sizes, as ``advance(model) → (next model, training and
    validation Pearson of model)``."""
    steps = _step_sizes(model, opts)
    state = _ADAM.init(eqx.filter(model, eqx.is_array))

    def advance(m):
        nonlocal state
        new, state, r_tr, r_va = _step(m, state, data, steps)
        return new, r_tr, r_va
    return advance


def _optimistix(model: StackModel, data: _Data, opts: StackFitOptions):
    """``opts.optimiser`` from optimistix on the same loss, over the parameter groups
    with a non-zero step size, as ``advance`` (`_adam`)."""
    spec = jax.tree.map(lambda size: bool(size > 0), _step_sizes(model, opts))
    params, static = eqx.partition(model, spec)
    solver = _OPTIMISTIX[opts.optimiser](rtol=1e-9, atol=1e-9)

    def fn(p, _):
        return _loss(eqx.combine(p, static), data)

    f_struct, aux_struct = jax.eval_shape(fn, params, None)
    state = solver.init(fn, params, None, {}, f_struct, aux_struct, frozenset())
    step = eqx.filter_jit(lambda p, s: solver.step(fn, p, None, {}, s, frozenset())[:2])

    def advance(m):
        nonlocal state
        r_tr, r_va = _evaluate(m, data)
        p, state = step(eqx.filter(m, spec), state)
        return eqx.combine(p, static), r_tr, r_va
    return advance


def _validation_masks(shape, n, fraction, seed):
    """(train, val) float32 masks: ``fraction`` of the pixels of each plane, drawn
    independently per plane from ``seed``."""
    val = np.random.default_rng(seed).random((n,) + tuple(shape)) < fraction
    return (~val).astype(np.float32), val.astype(np.float32)


def fit_stack(stack, planes: Sequence[int], *, options: StackFitOptions | None = None,
              pixel_pitch: float | None = None, wavelength: float | None = None,
              z2: float | None = None, registration: Registration | None = None,
              **overrides) -> StackFit:
    """Fit the wave model to the given planes of a PSF stack.

    Only ``stack[planes]`` is read: the other planes never enter (predict them with
    [`StackFit.predict`][diffcam.calibrate.stack.result.StackFit.predict] and score them
    against the baseline).

    Args:
        stack: (n_planes, ny, nx) array (any gain and dark level: each given plane is
            prepared by [`prepare_planes`][diffcam.calibrate.stack.inputs.prepare_planes]),
            or ``{plane index: (ny, nx) image}``.
        planes: two or more distinct plane indices; the first is the reference.
        options: [`StackFitOptions`][diffcam.calibrate.stack.fit.StackFitOptions]; keywords
            named after its fields replace them (``saturation=``, ``progress=``,
            ``max_steps=``, ...).
        pixel_pitch, wavelength, z2: optional physical inputs, metres; together they
            start the distance (``zetas``); they turn ζ into z2·M(t) and, with z2, into
            z1(t) in ``identifiable``.
        registration: M(anchor)/M(reference) and the fixed point, if already known
            (the anchor is the given plane farthest from the reference).

    Returns:
        [`StackFit`][diffcam.calibrate.stack.result.StackFit]. A
        [`StackFitWarning`][diffcam.calibrate.stack.fit.StackFitWarning] is issued when the
        kept model is worse than the scaling baseline on the validation pixels.

    Raises:
        DiffcamError: before any compute, for planes out of range, fewer than 2 planes,
            repeated planes, NaN/Inf pixels, a constant (empty or dark) plane,
            saturated pixels (with their count); ShapeError for frames of different
            shapes or a stack that is not 3-D.
    """
    opts = StackFitOptions.of(options, **overrides)
    frames, planes, n_planes, dtype = given_planes(stack, planes)
    check_saturation(frames, planes, saturation_level(opts.saturation, dtype))
    phys = check_physical(pixel_pitch, wavelength, z2)
    t0 = time.perf_counter()
    imgs = [p.astype(np.float32) for p in prepare_planes(np.stack(frames), opts.dark_ring,
                                                          labels=planes)]
    ref = planes[0]
    anchor = max(planes[1:], key=lambda t: abs(t - ref))
    if registration is None:
        registration = register_magnification(imgs[0], imgs[planes.index(anchor)])
    train, val = _validation_masks(imgs[0].shape, len(planes), opts.validation_fraction,
                                   opts.seed)
    data = _Data(jnp.asarray(np.stack(imgs)), jnp.asarray(train), jnp.asarray(val),
                 jnp.asarray(planes, jnp.float32))
    model, scan = _start(imgs, planes, registration, data,
                         dataclasses.replace(opts, zetas=_zetas(opts, phys)), t0)
    run = _descend(model, data, opts, t0)
    render_planes(run.model, planes[:1])      # compiles the predictor inside the fit
    base = _baseline_validation(imgs, planes, registration, val, ref, anchor)
    ident = identifiable(phys, run.model, n_planes,
                         _light_magnification(frames, planes, anchor, run.model, opts))
    fit = StackFit(model=run.model, planes=tuple(planes), n_planes=n_planes,
                   registration=registration, history=np.asarray(run.train),
                   validation=np.asarray(run.validation), stop_reason=run.reason,
                   best_step=run.best_step, validation_score=run.best_validation,
                   baseline_validation=float(base),
                   worse_than_baseline=bool(run.best_validation < base), zeta_scan=scan,
                   identifiable=ident, physical=phys, options=opts.to_dict(),
                   seconds=time.perf_counter() - t0, measured=np.stack(imgs))
    if fit.worse_than_baseline:
        warnings.warn(f"the stack fit ends worse than the scaling baseline on its own "
                      f"validation pixels (Pearson {run.best_validation:.4f} < {base:.4f}): "
                      f"prefer the baseline for these planes, or fit more planes.",
                      StackFitWarning, stacklevel=2)
    return fit


def _zetas(opts: StackFitOptions, phys: dict) -> tuple[float, ...]:
    """The ζ_ref candidates: as given, else the far-source value o²·λ·z2/pitch² (fine
    samples²; M ≥ 1 makes the true one larger by M(ref)) when the physical inputs
    allow it, else `ZETA_START` pixel²."""
    if opts.zetas is not None:
        return opts.zetas
    if None in (phys["pixel_pitch"], phys["wavelength"], phys["z2"]):
        return (opts.oversample ** 2 * ZETA_START,)
    return (opts.oversample ** 2 * phys["wavelength"] * phys["z2"]
            / phys["pixel_pitch"] ** 2,)


def _start(imgs, planes, registration, data, opts: StackFitOptions, t0: float):
    """The GS start (on the training pixels only) for every candidate ζ_ref; with
    several, each descends ``scan_steps`` steps and the best validation Pearson wins.
    Returns (model, {ζ: its validation Pearson})."""
    train = np.asarray(data.train)
    starts = {float(z): _initial_model(imgs, train, planes, registration, float(z), opts)
              for z in opts.zetas}
    if len(starts) == 1:
        (zeta, model), = starts.items()
        return model, {zeta: float(_evaluate(model, data)[1])}
    short = dataclasses.replace(opts, max_steps=opts.scan_steps, progress=False)
    runs = {z: _descend(m, data, short, t0) for z, m in starts.items()}
    best = max(runs, key=lambda z: runs[z].best_validation)
    return runs[best].model, {z: r.best_validation for z, r in runs.items()}


class _Run(NamedTuple):
    model: StackModel        # the model of the best validation step
    best_step: int
    best_validation: float
    train: list              # mean training Pearson per step
    validation: list         # mean validation Pearson per step
    reason: str              # why it stopped


def _descend(model: StackModel, data: _Data, opts: StackFitOptions, t0: float) -> _Run:
    """The optimiser from ``model`` until validation stalls, ``max_steps`` or the time
    budget if one is set (counted from ``t0``, perf_counter seconds)."""
    advance = (_adam if opts.optimiser == "adam" else _optimistix)(model, data, opts)
    best_val, best_model, best_step = -np.inf, model, 0
    train_hist, val_hist = [], []
    reason = f"max_steps ({opts.max_steps})"
    with new_bar(opts.max_steps, "stack fit", unit="step", progress=opts.progress) as bar:
        for k in range(opts.max_steps):
            new_model, r_tr, r_va = advance(model)
            r_va = float(r_va)
            if not np.isfinite(r_va):
                reason = f"diverged (validation Pearson {r_va}) at step {k}"
                break
            train_hist.append(float(r_tr))
            val_hist.append(r_va)
            if r_va > best_val:
                best_val, best_model, best_step = r_va, model, k
            model = new_model
            bar.update(1)
            bar.set_postfix(val=f"{r_va:.4f}", best=f"{best_val:.4f}")
            if k - best_step >= opts.patience:
                reason = f"no validation improvement for {opts.patience} steps"
                break
            if opts.time_budget is not None and time.perf_counter() - t0 > opts.time_budget:
                reason = f"time budget ({opts.time_budget:g} s)"
                break
    return _Run(best_model, best_step, float(best_val), train_hist, val_hist, reason)


def _light_magnification(frames, planes, anchor, model: StackModel,
                         opts: StackFitOptions) -> float | None:
    """M(reference) from the reference's and the anchor's light (inverse-square law,
    `magnification_from_light`), or None where the light does not follow it."""
    light = plane_light(np.stack([frames[0], frames[planes.index(anchor)]]), opts.dark_ring)
    try:
        return magnification_from_light(*light, float(model.magnification(anchor)))
    except DiffcamError:
        return None


def _baseline_validation(imgs, planes, reg, val, ref, anchor) -> float:
    """Mean over the given planes of the Pearson, on that plane's validation pixels, of
    the scaling baseline from the nearest *other* given plane (the baseline at a given
    plane is the plane itself, so it must not see its own validation pixels)."""
    scores = []
    for n, t in enumerate(planes):
        others = [q for q in planes if q != t]
        k = min(others, key=lambda q: (abs(t - q), q))
        s = relative_magnification_at(t, reg.magnification, ref, anchor) / \
            relative_magnification_at(k, reg.magnification, ref, anchor)
        pred = magnify_about(imgs[planes.index(k)], float(s), reg.centre)
        scores.append(float(pearson(pred, imgs[n], mask=val[n] > 0)))
    return float(np.mean(scores))


load_stack_fit = renamed(stack_result.load_stack_fit, "diffcam.calibrate.stack_fit.load_stack_fit")
