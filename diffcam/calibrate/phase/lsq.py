"""Least squares through the differentiable forward model (optimistix, the default).

The unknown is the diffuser phase θd (optionally on a coarser grid, upsampled); each
measured image k is modelled as s_k·I_k(θd) + b_k with a scale and a background that
are solved in closed form (weighted linear least squares) inside the residual function
(variable projection), which conditions the problem far better than fitting them
beside θd.
Residuals, per pixel and weighted by a mask (0 at saturated pixels); y is each image
normalised to unit mean:

- ``"intensity"``  s·I + b − y         (smooth, but its curvature scales with the
  intensity, so the bright centre of a far field dominates it and the phase detail that
  scatters light to the dim tails converges very slowly: from a flat start on a 128²
  near/far problem it stalls at a phase Pearson of 0.35)
- ``"weighted_intensity"``  (s·I + b − y)/√(y + 1): intensity residuals over the
  shot-noise standard deviation √y (Neyman's χ²), its variance floored at the image's
  mean (1). Near the solution, where y ≫ 1, it equals 2(√(s·I + b) − √y): the
  amplitude loss's even curvature over bright and dim pixels, but smooth where I → 0.
  s and b minimise this same weighted sum, so (variable projection) the gradient
  does not flow through them. The default: it solves that 128² problem from a flat
  start.
- ``"amplitude"``  √(s·I + b) − √y    (the error GS reduces)
- ``"poisson"``    the deviance residual sign(μ − y)·√(2(μ − y − y·log(μ/y))),
  μ = s·I + b: the sum of squares is the Poisson deviance, so Poisson maximum
  likelihood runs through the same solvers (give y in photon counts).

Solvers (``solver=``) are objects: any optimistix minimiser or least-squares solver
(``optx.LBFGS(rtol=0, atol=0)``, ``optx.GaussNewton(..., linear_solver=lx.LSMR(...))``),
or `JaxoptLBFGS` (jaxopt, optional, imported lazily); the names in
`SOLVERS` are shortcuts for the usual ones. Each runs a fixed number of steps
inside one ``lax.scan`` and records the loss ½Σr² after every step; the result's
``stats["status"]`` says whether the loss converged, was still falling, or stalled
(then a `ConvergenceWarning` says what to try).

Everything the fit depends on is a pytree (the forward model, the phase grid, the data,
the start, the regularisation weights), compiled once by ``eqx.filter_jit`` per
structure: a second fit of the same shapes with new data, a new start or new weights
reuses the compiled program. Arrays keep their dtype: float64 inputs under
``jax_enable_x64`` fit in float64.

Optional regularisers on the phase inside the aperture, wrap-safe through e^{jθ}:
``smoothness`` · Σ|e^{jθ(x+1)} − e^{jθ(x)}|² and ``tv`` · Σ(|Δ_y|² + |Δ_x|² + ε)^{½}.
"""

from __future__ import annotations

import time
import warnings
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax import Array
from jaxtyping import Float

from diffcam.calibrate.phase.near_far import (CalibrationGeometry, NearFarModel, check_captures,
                                        check_far_pitch)
from diffcam.calibrate.phase.projections import initial_phase, retrieve_projections
from diffcam.calibrate.phase.result import RetrievalResult
from diffcam.core.options import Options
from diffcam.core.errors import (ConvergenceWarning, DiffcamError, ShapeError, check_field,
                                 real_array)
from diffcam.core.progress import progress_bar, tick
from diffcam.core.grid import crop_to, pad_to
from diffcam.core.phasor import expj

__all__ = ["FitOptions", "fit_phase", "retrieve_lsq", "near_far_model", "PhaseGrid", "JaxoptLBFGS",
           "ConvergenceWarning", "fit_status", "warn_if_stalled", "LOSSES", "SOLVERS"]

LOSSES = ("amplitude", "intensity", "weighted_intensity", "poisson")
_EPS = 1e-6
# variance floor of the "weighted_intensity" loss, in units of the image's mean intensity
_VARIANCE_FLOOR = 1.0


class JaxoptLBFGS(eqx.Module):
    """jaxopt's L-BFGS as a solver object (optional backend: ``pip install
    'diffcam[jaxopt]'``; jaxopt is unmaintained upstream)."""

    history_size: int = 10


_EXACT = dict(rtol=0.0, atol=0.0)
# built when asked for: building GaussNewton starts JAX's backend, which an importer may
# still have to set up first (jax.distributed.initialize())
_SOLVERS = {
    "lbfgs": lambda: optx.LBFGS(**_EXACT, history_length=10),
    "ncg": lambda: optx.NonlinearCG(**_EXACT),
    "gauss_newton": lambda: optx.GaussNewton(**_EXACT, linear_solver=lx.LSMR(
        rtol=1e-3, atol=1e-3, max_steps=20)),
    "jaxopt_lbfgs": JaxoptLBFGS,
}
SOLVERS = tuple(_SOLVERS)


def solver_object(solver):
    """The solver object for ``solver`` (an object, or a name in `SOLVERS`)."""
    if isinstance(solver, str):
        if solver not in SOLVERS:
            raise DiffcamError(f"solver must be one of {SOLVERS} or an optimistix solver "
                               f"object, got {solver!r}.")
        return _SOLVERS[solver]()
    if not isinstance(solver, (optx.AbstractMinimiser, optx.AbstractLeastSquaresSolver,
                               JaxoptLBFGS)):
        raise DiffcamError(f"solver must be an optimistix minimiser or least-squares solver "
                           f"(e.g. optx.LBFGS(rtol=0, atol=0)) or one of {SOLVERS}; got "
                           f"{type(solver).__name__}.")
    return solver


class PhaseGrid(eqx.Module):
    """Where the phase unknowns live: a ``box``×``box`` centred crop of the ``shape`` grid
    (the aperture's bounding square), sampled ``factor`` times coarser and upsampled
    (cubic) to the full pitch. ``factor=1`` puts one unknown on every sample. All fields
    are static (hashable): a grid is part of a fit's structure, not its data."""

    shape: tuple[int, int] = eqx.field(static=True)
    box: int = eqx.field(static=True)
    factor: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if self.box > min(self.shape[-2:]) or self.box < 2:
            raise DiffcamError(f"phase box {self.box} must be within 2 … "
                               f"{min(self.shape[-2:])} samples.")
        if not isinstance(self.factor, int) or self.factor < 1 or self.box % self.factor:
            raise DiffcamError(f"coarse factor must be a positive int dividing the box "
                               f"({self.box} samples), got {self.factor!r}.")

    @classmethod
    def for_aperture(cls, aperture, factor: int = 1) -> "PhaseGrid":
        """The smallest centred square (a multiple of ``factor``) holding ``aperture > 0``."""
        if not isinstance(factor, (int, np.integer)) or factor < 1:
            raise DiffcamError(f"coarse factor must be a positive int, got {factor!r}.")
        factor = int(factor)
        a = np.asarray(aperture) > 0
        if not a.any():
            raise DiffcamError("the aperture is zero everywhere; nothing transmits.")
        ny, nx = a.shape
        iy, ix = np.nonzero(a)
        half = int(max(np.abs(iy - ny // 2).max(), np.abs(ix - nx // 2).max())) + 1
        box = min(-(-2 * half // factor) * factor, (min(ny, nx) // factor) * factor)
        return cls((int(ny), int(nx)), box, factor)

    @property
    def param_shape(self) -> tuple[int, int]:
        return self.box // self.factor, self.box // self.factor

    def expand(self, theta: Float[Array, "my mx"]) -> Float[Array, "ny nx"]:
        """Unknowns → full-grid phase (radians)."""
        if self.factor > 1:
            theta = jax.image.resize(theta, (self.box, self.box), "cubic")
        return pad_to(theta, self.shape)

    def restrict(self, phase: Float[Array, "ny nx"]) -> Float[Array, "my mx"]:
        """Full-grid phase → unknowns (crop, then area-average; for warm starts use a
        smooth or unwrapped phase when ``factor > 1``)."""
        theta = crop_to(jnp.asarray(phase), (self.box, self.box))
        if self.factor > 1:
            m, f = self.box // self.factor, self.factor
            theta = theta.reshape(m, f, m, f).mean(axis=(1, 3))
        return theta


def near_far_model(aperture: Float[Array, "ny nx"], geometry: CalibrationGeometry
                   ) -> NearFarModel:
    """θd (full grid) → (near, far) intensities in energy units: the
    [`NearFarModel`][diffcam.calibrate.phase.near_far.NearFarModel] of ``geometry``."""
    return NearFarModel.build(aperture, geometry)


def _residual(pred, y, w, loss):
    if loss == "weighted_intensity":
        return w * (pred - y) * jax.lax.rsqrt(y + _VARIANCE_FLOOR)
    if loss == "amplitude":
        return w * (jnp.sqrt(jnp.maximum(pred, 0.0) + _EPS) - jnp.sqrt(y + _EPS))
    if loss == "intensity":
        return w * (pred - y)
    mu = jnp.maximum(pred, _EPS)
    dev = 2 * (mu - y - jnp.where(y > 0, y * jnp.log(jnp.where(y > 0, y, 1.0) / mu), 0.0))
    return w * jnp.sign(mu - y) * jnp.sqrt(jnp.maximum(dev, 0.0) + _EPS)


def _linear_fit(pred, y, v, fit_background):
    """Scale s and background b minimising Σ v·(s·pred + b − y)² (closed form, with sums
    centred on the weighted means so that float32 does not cancel)."""
    if not fit_background:
        s = jnp.sum(v * pred * y) / jnp.sum(v * pred * pred)
        return s, jnp.zeros_like(s)
    sv = jnp.sum(v)
    pred_mean, y_mean = jnp.sum(v * pred) / sv, jnp.sum(v * y) / sv
    dp = pred - pred_mean
    s = jnp.sum(v * dp * (y - y_mean)) / jnp.sum(v * dp * dp)
    return s, y_mean - s * pred_mean


def _phase_diffs(phase, support):
    """Wrap-safe finite differences e^{jθ(x+1)} − e^{jθ(x)} inside the support."""
    e = expj(phase)
    dy = (e[1:, :] - e[:-1, :]) * (support[1:, :] * support[:-1, :])
    dx = (e[:, 1:] - e[:, :-1]) * (support[:, 1:] * support[:, :-1])
    return dy[:, :-1], dx[:-1, :]


class _Problem(eqx.Module):
    """One least-squares problem as a pytree: the model and everything it is fitted to.

    Arrays (data, masks, the regularisation weights, the model's own arrays) are leaves,
    so a new problem of the same structure reuses the compiled fit; ``loss``,
    ``fit_background`` and which regularisers are on are static.
    """

    model: eqx.Module
    grid: PhaseGrid
    measured: tuple
    masks: tuple
    norms: Array
    support: Array
    smoothness: Array
    tv: Array
    loss: str = eqx.field(static=True)
    fit_background: bool = eqx.field(static=True)
    regularisers: tuple[bool, bool] = eqx.field(static=True)

    def scales(self, preds):
        """Per-image (s_k, b_k) by weighted linear least squares (variable projection).

        For ``"weighted_intensity"`` they minimise the loss itself, whose derivative in
        (s_k, b_k) is then zero: the gradient in θ is the same without differentiating
        through them (Gauss–Newton then uses Kaufman's variable-projection Jacobian),
        and float32 cancellation in that path cannot spoil it."""
        out = []
        for pred, y, w, n in zip(preds, self.measured, self.masks, self.norms):
            y = y / n
            if self.loss == "weighted_intensity":
                v = w * w / (y + _VARIANCE_FLOOR)
                out.append(jax.lax.stop_gradient(_linear_fit(pred, y, v, self.fit_background)))
            else:
                out.append(_linear_fit(pred, y, w, self.fit_background))
        return out

    def residuals(self, params):
        phase = self.grid.expand(params["theta"])
        preds = self.model(phase, params["extra"])
        data = tuple(_residual(s * pred + b, y / n, w, self.loss)
                     for (s, b), pred, y, w, n in zip(self.scales(preds), preds,
                                                      self.measured, self.masks, self.norms))
        return data + self._regulariser_residuals(phase)

    def _regulariser_residuals(self, phase):
        use_smoothness, use_tv = self.regularisers
        if not (use_smoothness or use_tv):
            return ()
        dy, dx = _phase_diffs(phase, self.support)
        out = ()
        if use_smoothness:
            out += tuple(jnp.sqrt(self.smoothness) * jnp.concatenate([d.real, d.imag])
                         for d in (dy, dx))
        if use_tv:
            mag2 = jnp.abs(dy) ** 2 + jnp.abs(dx) ** 2
            out += (jnp.sqrt(self.tv) * (mag2 + 1e-6) ** 0.25,)
        return out


def _half_sum_squares(res):
    return 0.5 * sum(jnp.sum(r ** 2) for r in jax.tree_util.tree_leaves(res))


def _scan_optimistix(problem, params, opt, iterations):
    """Run ``iterations`` optimistix steps in a scan, recording ½Σr² after each."""
    least_squares = isinstance(opt, optx.AbstractLeastSquaresSolver)

    def fn(y, args):
        res = problem.residuals(y)
        return (res, _half_sum_squares(res)) if least_squares else (_half_sum_squares(res),
                                                                     None)

    f_struct, aux_struct = jax.eval_shape(lambda: fn(params, None))
    state = opt.init(fn, params, None, {}, f_struct, aux_struct, frozenset())
    # the state holds jaxprs beside arrays: carry only the arrays through the scan
    dynamic, static = eqx.partition(state, eqx.is_array)

    def body(carry, k):
        tick(k)
        y, dynamic = carry
        y, state, _ = opt.step(fn, y, None, {}, eqx.combine(dynamic, static), frozenset())
        return (y, eqx.filter(state, eqx.is_array)), _half_sum_squares(problem.residuals(y))

    (params, _), history = jax.lax.scan(body, (params, dynamic), jnp.arange(iterations))
    return params, history


def _scan_jaxopt(problem, params, opt, iterations):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            import jaxopt
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise DiffcamError("JaxoptLBFGS needs jaxopt: pip install 'diffcam[jaxopt]' (or "
                               "use the default optimistix solvers).") from e
    solver = jaxopt.LBFGS(fun=lambda y: _half_sum_squares(problem.residuals(y)),
                          maxiter=iterations, tol=0.0, history_size=opt.history_size)
    state = solver.init_state(params)

    def body(carry, k):
        tick(k)
        y, state = carry
        y, state = solver.update(y, state)
        return (y, state), state.value

    (params, _), history = jax.lax.scan(body, (params, state), jnp.arange(iterations))
    return params, history


@eqx.filter_jit
def _run_fit(problem: _Problem, params, opt, iterations: int):
    start = _half_sum_squares(problem.residuals(params))
    run = _scan_jaxopt if isinstance(opt, JaxoptLBFGS) else _scan_optimistix
    params, history = run(problem, params, opt, iterations)
    sb = problem.scales(problem.model(problem.grid.expand(params["theta"]), params["extra"]))
    return (start, history, params, jnp.stack([s for s, _ in sb]),
            jnp.stack([b for _, b in sb]))


def fit_status(start: float, history: np.ndarray) -> str:
    """``"converged"`` (the loss fell to ≤ 10⁻⁴ of its start), ``"improving"`` (the last
    quarter of the steps still took > 1 % of the total decrease: more steps would help),
    ``"stalled"`` (it stopped falling well above zero), or ``"diverged"`` (NaN/Inf)."""
    h = np.asarray(history, np.float64)
    if not (np.isfinite(start) and np.all(np.isfinite(h))):
        return "diverged"
    final = h[-1]
    if final <= 1e-4 * start:
        return "converged"
    quarter = h[-max(1, h.size // 4) - 1] if h.size > 1 else start
    if quarter - final > 0.01 * max(start - final, 0.0):
        return "improving"
    return "stalled"


def warn_if_stalled(result: RetrievalResult, init) -> RetrievalResult:
    """Issue a `ConvergenceWarning` when a fit started cold (``init`` "flat" or
    "random") stalled: that is where least squares stagnates in a local minimum. (A warm
    start that levels off is being polished, and its plateau is the data's noise floor.)"""
    cold = isinstance(init, str) and init in ("flat", "random")
    if cold and result.stats["status"] == "stalled":
        h = np.asarray(result.history)
        warnings.warn(
            f"least squares from a {init} start stalled: after {h.size} steps the loss "
            f"stopped falling at {h[-1] / result.stats['start_loss']:.3g} of its start. "
            f"Unless that is your data's noise floor it is a local minimum: start from "
            f"projections (init='raar', or init=raar(...).phase) or use "
            f"loss='weighted_intensity'.", ConvergenceWarning, stacklevel=3)
    return result


def _real_dtype(*arrays):
    """float64 if any input is float64 and x64 is on, else float32."""
    wide = any(jnp.asarray(a).dtype == jnp.float64 for a in arrays if a is not None)
    return jnp.float64 if wide and jax.config.jax_enable_x64 else jnp.float32


class FitOptions(Options):
    """How a least-squares fit runs (the settings shared by every fit in diffcam).

    Attributes:
        loss: one of `LOSSES` (see the module docstring).
        solver: an optimistix solver object, `JaxoptLBFGS`, or a name in
            `SOLVERS`.
        iterations: solver steps.
        smoothness, tv: regularisation weights (per unit residual², dimensionless, ≥ 0).
        fit_background: fit the per-image background b_k (else b_k = 0).
        coarse: phase unknowns every ``coarse`` samples, upsampled (cubic).
        key: ``jax.random`` key of a ``"random"`` start.
        warm_start_iterations: RAAR iterations of the ``"raar"`` start of
            [`retrieve_lsq`][diffcam.calibrate.phase.lsq.retrieve_lsq].
        far_pitch: the far capture's pitch (m), checked against λf/(N·dx) if given.
        progress: a progress bar for fits over 2 s
            ([`diffcam.core.progress`][diffcam.core.progress]; ``DIFFCAM_PROGRESS=0`` turns
            every bar off).
    """

    loss: str = "weighted_intensity"
    solver: object = "lbfgs"
    iterations: int = 200
    smoothness: float = 0.0
    tv: float = 0.0
    fit_background: bool = True
    coarse: int = 1
    key: object = None
    warm_start_iterations: int = 30
    far_pitch: float | None = None
    progress: bool = True

    def __check_init__(self):
        if self.loss not in LOSSES:
            raise DiffcamError(f"loss must be one of {LOSSES}, got {self.loss!r}.")
        if not isinstance(self.iterations, (int, np.integer)) or self.iterations < 1:
            raise DiffcamError(f"iterations must be a positive int, got {self.iterations!r}.")
        for name in ("smoothness", "tv"):
            w = getattr(self, name)
            if not (np.isfinite(float(w)) and float(w) >= 0):
                raise DiffcamError(f"{name} must be a finite weight ≥ 0, got {w!r}.")



def fit_phase(model, measured: Sequence[Array], theta0: Float[Array, "my mx"],
              phase_grid: PhaseGrid, *, support=None, masks=None,
              options: FitOptions = FitOptions(), extra0=None) -> RetrievalResult:
    """Fit the phase (and per-image scale and background) to measured intensities.

    The engine under [`retrieve_lsq`][diffcam.calibrate.phase.lsq.retrieve_lsq] and
    [`diffcam.calibrate.fit_to_psfs`][diffcam.calibrate.phase.psf_fit.fit_to_psfs].

    Args:
        model: an ``equinox.Module``, ``model(phase, extra) -> tuple`` of K predicted
            intensities from the full-grid phase (radians) and the extra fitted
            parameters (a pytree, e.g. geometry; ``None`` without ``extra0``); pure and
            differentiable (e.g. [`NearFarModel`][diffcam.calibrate.phase.near_far.NearFarModel]).
        measured: K measured intensities, shapes matching ``model``'s outputs.
        theta0: starting unknowns, shape ``phase_grid.param_shape`` (radians).
        phase_grid: the phase parameterisation.
        support: (ny, nx) mask where the regularisers act (default: everywhere).
        masks: K weight images (0 = ignore, e.g. saturated pixels), or ``None``.
        options: [`FitOptions`][diffcam.calibrate.phase.lsq.FitOptions] (loss, solver, iterations,
            regularisation, progress).
        extra0: starting extra parameters passed to ``model`` (fitted too).

    Returns:
        [`RetrievalResult`][diffcam.calibrate.phase.result.RetrievalResult]; ``stats["status"]``
        is `fit_status` of the run.
    """
    loss, solver, iterations = options.loss, options.solver, options.iterations
    smoothness, tv, fit_background = options.smoothness, options.tv, options.fit_background
    opt = solver_object(solver)
    dtype = _real_dtype(theta0, *measured)
    measured = tuple(jnp.asarray(m, dtype) for m in measured)
    masks = tuple(jnp.ones_like(m) for m in measured) if masks is None else \
        tuple(jnp.asarray(m, dtype) for m in masks)
    if len(masks) != len(measured):
        raise ShapeError(f"{len(masks)} masks for {len(measured)} measured images.")
    for i, (m, w) in enumerate(zip(measured, masks)):
        real_array(f"measured image {i}", m)
        check_field(m, f"measured image {i}")
        if w.shape != m.shape:
            raise ShapeError(f"mask {i} {w.shape} and measured image {i} {m.shape} differ.")
    if tuple(np.shape(theta0)) != phase_grid.param_shape:
        raise ShapeError(f"theta0 {np.shape(theta0)} must have the phase grid's shape "
                         f"{phase_grid.param_shape}.")
    support = jnp.ones(phase_grid.shape, dtype) if support is None else \
        jnp.asarray(support, dtype)
    t0 = time.perf_counter()
    # each image is normalised to unit mean, so that the K images weigh alike
    norms = jnp.stack([jnp.sum(w * m) / jnp.sum(w) for m, w in zip(measured, masks)])
    problem = _Problem(model, phase_grid, measured, masks, norms, support,
                       jnp.asarray(smoothness, dtype), jnp.asarray(tv, dtype), loss,
                       bool(fit_background), (float(smoothness) > 0, float(tv) > 0))
    params = {"theta": jnp.asarray(theta0, dtype),
              "extra": jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), extra0)}
    with progress_bar(int(iterations), "least squares", options.progress):
        start, history, params, scale, background = jax.block_until_ready(
            _run_fit(problem, params, opt, int(iterations)))
    phase = jnp.angle(expj(phase_grid.expand(params["theta"])))
    phase.block_until_ready()
    status = fit_status(float(start), np.asarray(history))
    name = solver if isinstance(solver, str) else type(opt).__name__
    stats = {"method": f"lsq/{name}/{loss}", "iterations": int(iterations),
             "status": status, "start_loss": float(start),
             "scale": scale * norms, "background": background * norms,
             "extra": params["extra"], "wall_time": time.perf_counter() - t0}
    return RetrievalResult(phase, support * expj(phase), history, stats)


def retrieve_lsq(near: Float[Array, "ny nx"], far: Float[Array, "ny nx"],
                 geometry: CalibrationGeometry, aperture: Float[Array, "ny nx"], *,
                 init="raar", masks=None, options: FitOptions | None = None,
                 **overrides) -> RetrievalResult:
    """Diffuser phase from near/far intensities by least squares through the forward model.

    Args:
        near, far: intensities as for
            [`diffcam.calibrate.retrieve_projections`][diffcam.calibrate.phase.projections.retrieve_projections].
        geometry: the set-up, SI units.
        aperture: the diffuser-plane amplitude C (ny, nx) (e.g.
            [`diffcam.optics.elements.circular_aperture`][diffcam.optics.elements.circular_aperture]).
        init: ``"raar"`` (default: ``warm_start_iterations`` RAAR projections from a flat
            start, which puts the fit in the right basin: from a flat start a 128² near/far
            fit can stall at a phase Pearson of 0.82, from 30 RAAR iterations it reaches
            1.000), ``"flat"``, ``"random"`` (with ``key``) or a full-grid phase (radians).
        masks: ``(near_mask, far_mask)`` weights, 0 at saturated or bad pixels.
        options: [`FitOptions`][diffcam.calibrate.phase.lsq.FitOptions]; keyword ``**overrides``
            replace its fields (``loss=``, ``iterations=``, ``coarse=``, ``key=``,
            ``far_pitch=``, ...).
    """
    opts = FitOptions.of(options, **overrides)
    check_captures(near, far)
    shape = np.shape(near)
    if np.shape(aperture) != shape:
        raise ShapeError(f"aperture {np.shape(aperture)} and captures {shape} differ in shape.")
    if opts.far_pitch is not None:
        check_far_pitch(opts.far_pitch, geometry, shape)
    grid = PhaseGrid.for_aperture(aperture, opts.coarse)
    dtype = _real_dtype(near, far)
    if isinstance(init, str) and init == "raar":
        init = retrieve_projections(near, far, geometry, method="raar", init="flat",
                                    iterations=opts.warm_start_iterations,
                                    progress=opts.progress).phase
    theta0 = grid.restrict(initial_phase(init, shape, opts.key)[0].astype(dtype))
    model = near_far_model(jnp.asarray(aperture, dtype), geometry)
    return warn_if_stalled(fit_phase(model, (near, far), theta0, grid,
                                     support=jnp.asarray(aperture) > 0, masks=masks,
                                     options=opts), init)
