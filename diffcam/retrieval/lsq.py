"""Least squares through the differentiable forward model (optimistix, the default).

The unknown is the diffuser phase θd (optionally on a coarser grid, upsampled); each
measured image k is modelled as s_k·I_k(θd) + b_k with a scale and a background that
are solved in closed form (weighted linear least squares) inside the residual function
(variable projection), which conditions the problem far better than fitting them
beside θd.
Residuals, per pixel and weighted by a mask (0 at saturated pixels); y is each image
normalised to unit mean:

- ``"intensity"``  s·I + b − y         (the default of :func:`fit_phase`: smooth, but its
  curvature scales with the intensity, so the bright centre of a far field dominates
  it and the phase detail that scatters light to the dim tails converges very slowly)
- ``"weighted_intensity"``  (s·I + b − y)/√(y + 1): intensity residuals over the
  shot-noise standard deviation √y (Neyman's χ²), its variance floored at the image's
  mean (1). Near the solution, where y ≫ 1, it equals 2(√(s·I + b) − √y): the
  amplitude loss's even curvature over bright and dim pixels, but smooth where I → 0.
  s and b minimise this same weighted sum, so (variable projection) the gradient
  does not flow through them. The default of :func:`diffcam.retrieval.fit_to_psfs`
  with near/far captures.
- ``"amplitude"``  √(s·I + b) − √y    (the error GS reduces)
- ``"poisson"``    the deviance residual sign(μ − y)·√(2(μ − y − y·log(μ/y))),
  μ = s·I + b: the sum of squares is the Poisson deviance, so Poisson maximum
  likelihood runs through the same solvers (give y in photon counts).

Solvers (``solver=``), all matrix-free, so they scale to 512² unknowns and beyond:
``"lbfgs"`` (optimistix L-BFGS, the default), ``"ncg"`` (nonlinear conjugate gradient),
``"gauss_newton"`` (inner LSMR on the Jacobian, through jvp/vjp only), ``"jaxopt_lbfgs"``
(jaxopt, optional, imported lazily). Each runs a fixed number of steps inside one
``lax.scan`` and records the loss ½Σr² after every step.

Optional regularisers on the phase inside the aperture, wrap-safe through e^{jθ}:
``smoothness`` · Σ|e^{jθ(x+1)} − e^{jθ(x)}|² and ``tv`` · Σ(|Δ_y|² + |Δ_x|² + ε)^{½}.
"""

from __future__ import annotations

import time
import warnings
from functools import partial
from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax import Array
from jaxtyping import Float

from ..errors import DiffcamError, ShapeError, check_field
from ..grid import crop_to, fft2c, pad_to
from ..propagate import apply_transfer, transfer_function
from .geometry import CalibrationGeometry, check_captures, check_far_pitch
from .projections import initial_phase
from .result import RetrievalResult

__all__ = ["fit_phase", "retrieve_lsq", "near_far_model", "PhaseGrid", "LOSSES", "SOLVERS"]

LOSSES = ("amplitude", "intensity", "weighted_intensity", "poisson")
SOLVERS = ("lbfgs", "ncg", "gauss_newton", "jaxopt_lbfgs")
_EPS = 1e-6
# variance floor of the "weighted_intensity" loss, in units of the image's mean intensity
_VARIANCE_FLOOR = 1.0


class PhaseGrid:
    """Where the phase unknowns live: a ``box``×``box`` centred crop of the N×N grid (the
    aperture's bounding square), sampled ``factor`` times coarser and upsampled
    (cubic) to the full pitch. ``factor=1`` puts one unknown on every sample."""

    def __init__(self, shape: Sequence[int], box: int, factor: int = 1):
        if box > min(shape[-2:]) or box < 2:
            raise DiffcamError(f"phase box {box} must be within 2 … {min(shape[-2:])} samples.")
        if not isinstance(factor, int) or factor < 1 or box % factor:
            raise DiffcamError(f"coarse factor must be a positive int dividing the box "
                               f"({box} samples), got {factor!r}.")
        self.shape, self.box, self.factor = tuple(shape[-2:]), box, factor

    @classmethod
    def for_aperture(cls, aperture, factor: int = 1) -> "PhaseGrid":
        """The smallest centred square (a multiple of ``factor``) holding ``aperture > 0``."""
        if not isinstance(factor, int) or factor < 1:
            raise DiffcamError(f"coarse factor must be a positive int, got {factor!r}.")
        a = np.asarray(aperture) > 0
        if not a.any():
            raise DiffcamError("the aperture is zero everywhere; nothing transmits.")
        ny, nx = a.shape
        iy, ix = np.nonzero(a)
        half = int(max(np.abs(iy - ny // 2).max(), np.abs(ix - nx // 2).max())) + 1
        box = min(-(-2 * half // factor) * factor, (min(ny, nx) // factor) * factor)
        return cls(a.shape, box, factor)

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
        theta = crop_to(jnp.asarray(phase, jnp.float32), (self.box, self.box))
        if self.factor > 1:
            m, f = self.box // self.factor, self.factor
            theta = theta.reshape(m, f, m, f).mean(axis=(1, 3))
        return theta


def near_far_model(aperture: Float[Array, "ny nx"], geometry: CalibrationGeometry
                   ) -> Callable[[Array], tuple[Array, Array]]:
    """θd (full grid) → (near, far) intensities in energy units (each sums to Σ|C|²).

    The far field is the unitary centred DFT of the diffuser field: it differs from
    :func:`diffcam.propagate.fourier_lens` by a constant factor only, which the fitted
    scale absorbs.
    """
    C = jnp.asarray(aperture, jnp.complex64)
    shape = C.shape
    n = float(np.sqrt(shape[-2] * shape[-1]))
    z = float(geometry.near_distance)
    H = None if z == 0 else transfer_function(shape, geometry.dx, geometry.wavelength, z)

    def predict(phase):
        u = C * jnp.exp(1j * phase)
        near = u if H is None else apply_transfer(u, H)
        far = fft2c(u) / n
        return jnp.abs(near) ** 2, jnp.abs(far) ** 2

    return predict


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
    e = jnp.exp(1j * phase)
    dy = (e[1:, :] - e[:-1, :]) * (support[1:, :] * support[:-1, :])
    dx = (e[:, 1:] - e[:, :-1]) * (support[:, 1:] * support[:, :-1])
    return dy[:, :-1], dx[:-1, :]


def _regulariser_residuals(phase, support, smoothness, tv):
    dy, dx = _phase_diffs(phase, support)
    out = []
    if smoothness:
        out += [jnp.sqrt(smoothness) * jnp.concatenate([d.real, d.imag]) for d in (dy, dx)]
    if tv:
        mag2 = jnp.abs(dy) ** 2 + jnp.abs(dx) ** 2
        out.append(jnp.sqrt(tv) * (mag2 + 1e-6) ** 0.25)
    return tuple(out)


def _optimistix_solver(solver, inner_steps):
    tol = dict(rtol=0.0, atol=0.0)
    if solver == "lbfgs":
        return optx.LBFGS(**tol, history_length=10), False
    if solver == "ncg":
        return optx.NonlinearCG(**tol), False
    if solver == "gauss_newton":
        return optx.GaussNewton(**tol, linear_solver=lx.LSMR(rtol=1e-3, atol=1e-3,
                                                             max_steps=inner_steps)), True
    raise DiffcamError(f"solver must be one of {SOLVERS}, got {solver!r}.")


def _scan_optimistix(fn_res, params, solver, iterations, inner_steps):
    """Run ``iterations`` optimistix steps in a scan, recording ½Σr² after each."""
    opt, least_squares = _optimistix_solver(solver, inner_steps)

    def loss_of(res):
        return 0.5 * sum(jnp.sum(r ** 2) for r in jax.tree_util.tree_leaves(res))

    if least_squares:
        fn = lambda y, args: (fn_res(y), loss_of(fn_res(y)))  # noqa: E731
    else:
        fn = lambda y, args: (loss_of(fn_res(y)), None)  # noqa: E731
    f_struct, aux_struct = jax.eval_shape(lambda: fn(params, None))
    state = opt.init(fn, params, None, {}, f_struct, aux_struct, frozenset())
    # the state holds jaxprs beside arrays: carry only the arrays through the scan
    dynamic, static = eqx.partition(state, eqx.is_array)

    def body(carry, _):
        y, dynamic = carry
        state = eqx.combine(dynamic, static)
        y, state, _ = opt.step(fn, y, None, {}, state, frozenset())
        return (y, eqx.filter(state, eqx.is_array)), loss_of(fn_res(y))

    (params, _), history = jax.lax.scan(body, (params, dynamic), None, length=iterations)
    return params, history


def _scan_jaxopt(fn_res, params, iterations):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            import jaxopt
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise DiffcamError("solver='jaxopt_lbfgs' needs jaxopt: pip install "
                               "'diffcam[jaxopt]' (or use the default optimistix solvers).") from e
    loss = lambda y: 0.5 * sum(jnp.sum(r ** 2) for r in jax.tree_util.tree_leaves(fn_res(y)))  # noqa: E731
    opt = jaxopt.LBFGS(fun=loss, maxiter=iterations, tol=0.0, history_size=10)
    state = opt.init_state(params)

    def body(carry, _):
        y, state = carry
        y, state = opt.update(y, state)
        return (y, state), state.value

    (params, _), history = jax.lax.scan(body, (params, state), None, length=iterations)
    return params, history


def fit_phase(predict: Callable, measured: Sequence[Array], theta0: Float[Array, "my mx"],
              phase_grid: PhaseGrid, *, support=None, masks=None, loss: str = "intensity",
              solver: str = "lbfgs", iterations: int = 200, smoothness: float = 0.0,
              tv: float = 0.0, fit_background: bool = True, extra0=None,
              inner_steps: int = 20) -> RetrievalResult:
    """Fit the phase (and per-image scale and background) to measured intensities.

    The engine under :func:`retrieve_lsq` and :mod:`.psf_fit`.

    Args:
        predict: ``predict(phase, extra) -> tuple`` of K predicted intensities from the
            full-grid phase (radians) and the extra fitted parameters (a pytree, e.g.
            geometry); pure and differentiable. ``extra`` is ``None`` without ``extra0``.
        measured: K measured intensities, shapes matching ``predict``'s outputs.
        theta0: starting unknowns, shape ``phase_grid.param_shape`` (radians).
        phase_grid: the phase parameterisation.
        support: (ny, nx) mask where the regularisers act (default: everywhere).
        masks: K weight images (0 = ignore, e.g. saturated pixels), or ``None``.
        loss: one of :data:`LOSSES` (see the module docstring).
        solver: one of :data:`SOLVERS`.
        iterations: solver steps.
        smoothness, tv: regularisation weights (per unit residual², dimensionless).
        fit_background: fit b_k (else b_k = 0).
        extra0: starting extra parameters passed to ``predict`` (fitted too).
        inner_steps: LSMR steps per Gauss–Newton step.
    """
    if loss not in LOSSES:
        raise DiffcamError(f"loss must be one of {LOSSES}, got {loss!r}.")
    if solver not in SOLVERS:
        raise DiffcamError(f"solver must be one of {SOLVERS}, got {solver!r}.")
    measured = tuple(jnp.asarray(m, jnp.float32) for m in measured)
    masks = tuple(jnp.ones_like(m) for m in measured) if masks is None else \
        tuple(jnp.asarray(m, jnp.float32) for m in masks)
    if len(masks) != len(measured):
        raise ShapeError(f"{len(masks)} masks for {len(measured)} measured images.")
    for i, (m, w) in enumerate(zip(measured, masks)):
        check_field(m, f"measured image {i}")
        if w.shape != m.shape:
            raise ShapeError(f"mask {i} {w.shape} and measured image {i} {m.shape} differ.")
    if tuple(np.shape(theta0)) != phase_grid.param_shape:
        raise ShapeError(f"theta0 {np.shape(theta0)} must have the phase grid's shape "
                         f"{phase_grid.param_shape}.")
    support = jnp.ones(phase_grid.shape, jnp.float32) if support is None else \
        jnp.asarray(support, jnp.float32)
    t0 = time.perf_counter()
    # each image is normalised to unit mean, so that the K images weigh alike
    norms = jnp.stack([jnp.sum(w * m) / jnp.sum(w) for m, w in zip(measured, masks)])
    params = {"theta": jnp.asarray(theta0, jnp.float32), "extra": extra0}
    history, params, scale, background = _fit_jit(
        predict, phase_grid, measured, masks, norms, support, params, loss=loss,
        solver=solver, iterations=iterations, smoothness=float(smoothness), tv=float(tv),
        fit_background=fit_background, inner_steps=inner_steps)
    phase = jnp.angle(jnp.exp(1j * phase_grid.expand(params["theta"])))
    phase.block_until_ready()
    stats = {"method": f"lsq/{solver}/{loss}", "iterations": iterations,
             "scale": scale * norms, "background": background * norms,
             "extra": params["extra"],
             "wall_time": time.perf_counter() - t0}
    return RetrievalResult(phase, support * jnp.exp(1j * phase), history, stats)


@partial(jax.jit, static_argnames=("predict", "phase_grid", "loss", "solver", "iterations",
                                   "smoothness", "tv", "fit_background", "inner_steps"))
def _fit_jit(predict, phase_grid, measured, masks, norms, support, params, *, loss, solver,
             iterations, smoothness, tv, fit_background, inner_steps):
    def scales(preds):
        """Per-image (s_k, b_k) by weighted linear least squares (variable projection).

        For ``"weighted_intensity"`` they minimise the loss itself, whose derivative in
        (s_k, b_k) is then zero: the gradient in θ is the same without differentiating
        through them (Gauss–Newton then uses Kaufman's variable-projection Jacobian),
        and float32 cancellation in that path cannot spoil it."""
        out = []
        for pred, y, w, n in zip(preds, measured, masks, norms):
            y = y / n
            if loss == "weighted_intensity":
                v = w * w / (y + _VARIANCE_FLOOR)
                out.append(jax.lax.stop_gradient(_linear_fit(pred, y, v, fit_background)))
            else:
                out.append(_linear_fit(pred, y, w, fit_background))
        return out

    def residuals(p):
        phase = phase_grid.expand(p["theta"])
        preds = predict(phase, p["extra"])
        data = tuple(_residual(s * pred + b, y / n, w, loss) for (s, b), pred, y, w, n in
                     zip(scales(preds), preds, measured, masks, norms))
        return data + _regulariser_residuals(phase, support, smoothness, tv)

    if solver == "jaxopt_lbfgs":
        params, history = _scan_jaxopt(residuals, params, iterations)
    else:
        params, history = _scan_optimistix(residuals, params, solver, iterations, inner_steps)
    sb = scales(predict(phase_grid.expand(params["theta"]), params["extra"]))
    return (history, params, jnp.stack([s for s, _ in sb]), jnp.stack([b for _, b in sb]))


def retrieve_lsq(near: Float[Array, "ny nx"], far: Float[Array, "ny nx"],
                 geometry: CalibrationGeometry, aperture: Float[Array, "ny nx"], *,
                 init="flat", key=None, coarse: int = 1, far_pitch=None, masks=None,
                 **options) -> RetrievalResult:
    """Diffuser phase from near/far intensities by least squares through the forward model.

    Args:
        near, far: intensities as for :func:`diffcam.retrieval.retrieve_projections`.
        geometry: the set-up, SI units.
        aperture: the diffuser-plane amplitude C (ny, nx) (e.g.
            :func:`diffcam.optics.circular_aperture`).
        init: ``"flat"``, ``"random"`` (with ``key``) or a full-grid phase (radians), e.g.
            ``raar(...).phase`` for a warm start.
        coarse: phase unknowns every ``coarse`` samples, upsampled (cubic).
        far_pitch: the far capture's pitch (m), checked against λf/(N·dx) if given.
        masks: ``(near_mask, far_mask)`` weights, 0 at saturated or bad pixels.
        **options: passed to :func:`fit_phase` (``loss``, ``solver``, ``iterations``,
            ``smoothness``, ``tv``, ``fit_background``).
    """
    check_captures(near, far)
    shape = np.shape(near)
    if np.shape(aperture) != shape:
        raise ShapeError(f"aperture {np.shape(aperture)} and captures {shape} differ in shape.")
    if far_pitch is not None:
        check_far_pitch(far_pitch, geometry, shape)
    grid = PhaseGrid.for_aperture(aperture, coarse)
    start = initial_phase(init, shape, key)[0]
    theta0 = grid.restrict(start)
    model = near_far_model(aperture, geometry)
    predict = _NearFar(model)
    result = fit_phase(predict, (near, far), theta0, grid, support=jnp.asarray(aperture) > 0,
                       masks=masks, **options)
    return result


class _NearFar:
    """Hashable wrapper so the model can be a static argument of the jitted fit."""

    def __init__(self, model):
        self.model = model

    def __call__(self, phase, extra):
        return self.model(phase)
