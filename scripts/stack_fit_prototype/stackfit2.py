"""Wave model v2: both given planes rendered through the same resampling.

Changes against :mod:`stackfit` (which still provides data loading, registration, the
scaling baseline and the shared numerical helpers):

* **Field grid at an intermediate magnification.**  In v1 the field grid *was* the fine
  sensor grid of the reference plane ``i`` (plane ``i`` rendered by slicing, plane
  ``j`` by cubic resampling), so the per-sample phase could reproduce plane ``i``'s
  noise texture exactly.  Here the field grid is the fine sensor grid of a virtual
  plane with magnification ``m0`` relative to plane ``i`` (default: the geometric mean
  ``sqrt(s_j)``), so *every* plane, ``i`` and ``j`` included, is rendered through the
  same cubic-convolution resampling (plane ``i`` magnified by ``1/m0``, plane ``j`` by
  ``s_j/m0``: mirror images of each other).
* **Prediction = model + carried residual** (:func:`predict_hybrid`): the part of
  each measured plane the model does not reproduce (raw - gain * render - offset) is
  magnified to every other plane with the model's own magnification law and added,
  weighted linearly between the two given planes (1 at its own plane, 0 at the other;
  the nearest plane's residual with weight 1 outside [i, j]).  The model supplies the
  change between planes, the measurement the sub-pixel detail the model cannot
  represent at unseen pixels (validation r ~0.96-0.97 against training r ~0.99).
* The zeta scan is scored with the chunked renderer, so the renderer used for
  prediction is compiled inside the fit (prediction needs no compile).
* optional (off by default, did not help) **high-frequency penalty** on the diffuser
  field spectrum and **refit on all pixels** for the validation-chosen step count.

Everything else (GS initialisation, Adam, per-pixel validation split, stop rule) is the
same as v1.  Defaults used in the benchmark: ``bench2.FIT``.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sparse

import jax
import jax.numpy as jnp

import stackfit as sf
from stackfit import (FitResult, Registration, _adam_step, _freq2, _gauss_blur, _gs,
                      _good_size, block_masks, masked_pearson, rel_mag, sample_magnified,
                      taper2d)


@dataclasses.dataclass(frozen=True)
class Geometry:
    """Static sizes of the wave model (hashable: used as a jit static argument).

    Field sample n <-> pixel coordinate (n - pad - 0.5) / 2 of the *virtual* plane whose
    magnification relative to plane i is ``m0``; plane t is that grid magnified by
    s(t) / m0 about the fitted centre."""
    h: int
    w: int
    pad: int
    ny: int
    nx: int
    stride: int
    i: int
    j: int
    m0: float = 1.0
    frozen: bool = False
    taps: int = 4

    @property
    def coarse(self):
        return (-(-self.ny // self.stride) + 1, -(-self.nx // self.stride) + 1)


def make_geometry(h, w, i, j, m0=1.0, pad=40, stride=4, frozen=False) -> Geometry:
    return Geometry(h, w, pad, _good_size(2 * h + 2 * pad), _good_size(2 * w + 2 * pad),
                    stride, i, j, float(m0), frozen)


def amplitude(params, g: Geometry, taper):
    la = jax.image.resize(params["logamp"], (g.ny, g.nx), "cubic")
    return jnp.exp(la) * taper


def spectrum(params, g: Geometry, taper):
    return jnp.fft.fft2(amplitude(params, g, taper) * jnp.exp(1j * params["theta"]))


def plane_scalars(params, t, g: Geometry):
    """Magnification of plane t relative to plane i, and its effective distance."""
    s = rel_mag(t, jnp.exp(params["log_s"]), g.i, g.j)
    kappa = 0.0 if g.frozen else params["kappa"]
    zeta = jnp.exp(params["log_zeta"]) * s ** (-kappa)
    return s, zeta


def render_plane(params, spec, t, g: Geometry, f2):
    """Predicted pixel image of plane t: propagate, resample (magnification s(t)/m0
    relative to the field grid), |.|^2, Gaussian blur, 2x2 bin."""
    s, zeta = plane_scalars(params, t, g)
    u = jnp.fft.ifft2(spec * jnp.exp(-1j * jnp.pi * zeta * f2))
    v = sample_magnified(u, s / g.m0, params["centre"], g)
    inten = jnp.real(v) ** 2 + jnp.imag(v) ** 2
    inten = _gauss_blur(inten, jnp.exp(params["log_sigma"]))
    return inten.reshape(g.h, 2, g.w, 2).mean(axis=(1, 3))


def render(params, ts, g: Geometry, taper, f2):
    spec = spectrum(params, g, taper)
    return jax.lax.map(lambda t: render_plane(params, spec, t, g, f2),
                       jnp.asarray(ts, jnp.float32))


def hf_weight(g: Geometry, f_cut: float):
    """Weight of the high-frequency penalty: (|f| / f_cut)^4 above f_cut, 0 below
    (f in cycles per fine sample, Nyquist 0.5)."""
    f = np.sqrt(np.asarray(_freq2(g)))
    return jnp.asarray((np.clip(f / f_cut, 1.0, None) ** 4 - 1.0).astype(np.float32))


# ----------------------------------------------------------------------------------
# initialisation (as v1, but both planes resampled onto the intermediate grid)
# ----------------------------------------------------------------------------------


def init_params(imgs, reg: Registration, g: Geometry, zeta, n_gs=30, amp_blur=6.0,
                sigma=1.0, seed=0, kappa=0.0):
    taper = taper2d(g)
    ii, ki = sf.to_field_grid(imgs[0], 1.0 / g.m0, reg.centre, g)
    ij, kj = sf.to_field_grid(imgs[1], reg.s_j / g.m0, reg.centre, g)
    env = np.where(ki, ndi.gaussian_filter(ii, amp_blur), 0.0)
    amp = np.sqrt(np.clip(env, 0, None)) * taper
    e = (amp ** 2).sum()
    mods = [np.sqrt(ii * e / ii.sum()), np.sqrt(ij * e / ij.sum())]
    f2 = np.asarray(_freq2(g))
    # distances of planes i and j (the field grid's own distance is irrelevant for GS:
    # only the relative propagation between the planes and the diffuser matters)
    zi = zeta
    zj = zeta if g.frozen else zeta * reg.s_j ** (-kappa)
    hs = [np.exp(-1j * np.pi * z * f2).astype(np.complex64) for z in (zi, zj)]
    rng = np.random.default_rng(seed)
    th0 = (0.1 * rng.standard_normal((g.ny, g.nx))).astype(np.float32)
    theta = _gs(jnp.asarray(amp, jnp.float32), [jnp.asarray(m, jnp.float32) for m in mods],
                [jnp.asarray(ki), jnp.asarray(kj)], [jnp.asarray(h) for h in hs],
                jnp.asarray(th0), n_gs)
    env_c = jax.image.resize(jnp.asarray(env, jnp.float32), g.coarse, "linear",
                             antialias=True)
    logamp = 0.5 * jnp.log(jnp.clip(env_c, 1e-3 * env.max(), None))
    return {
        "theta": theta,
        "logamp": logamp,
        "log_zeta": jnp.float32(np.log(zeta)),
        "log_s": jnp.float32(np.log(reg.s_j)),
        "centre": jnp.asarray(reg.centre, jnp.float32),
        "log_sigma": jnp.float32(np.log(sigma)),
        "kappa": jnp.float32(kappa),
    }


# ----------------------------------------------------------------------------------
# fitting
# ----------------------------------------------------------------------------------

DEFAULT_LR = dict(sf.DEFAULT_LR)


def make_step(g: Geometry, lr: dict, hf=0.0, f_cut=0.25):
    taper = jnp.asarray(taper2d(g))
    f2 = _freq2(g)
    wf = hf_weight(g, f_cut)
    ts = jnp.asarray([g.i, g.j], jnp.float32)

    def loss_fn(params, ys, mtr, mva):
        spec = spectrum(params, g, taper)
        pred = jnp.stack([render_plane(params, spec, t, g, f2) for t in ts])
        r_tr = jax.vmap(masked_pearson)(pred, ys, mtr)
        r_va = jax.vmap(masked_pearson)(pred, ys, mva)
        loss = (1.0 - r_tr).sum()
        if hf:
            p = jnp.real(spec) ** 2 + jnp.imag(spec) ** 2
            loss = loss + hf * (wf * p).sum() / p.sum()
        return loss, (r_tr.mean(), jax.lax.stop_gradient(r_va.mean()))

    @jax.jit
    def step(params, state, ys, mtr, mva):
        (loss, (rtr, rva)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, ys, mtr, mva)
        params, state = _adam_step(params, grads, state, lr)
        return params, state, rtr, rva

    return step


def _run_adam(step, params, ys, mtr, mva, max_steps, patience, t0, time_budget,
              track_val=True):
    zeros = jax.tree.map(jnp.zeros_like, params)
    state = (zeros, zeros, jnp.int32(0))
    best_val, best_params, best_step = -np.inf, params, 0
    vh, th = [], []
    reason = "max_steps"
    for k in range(max_steps):
        new_params, state, rtr, rva = step(params, state, ys, mtr, mva)
        rva = float(rva)
        vh.append(rva)
        th.append(float(rtr))
        if not track_val or rva > best_val:
            best_val, best_params, best_step = rva, params, k
        params = new_params
        if track_val and k - best_step >= patience:
            reason = f"no val improvement for {patience} steps"
            break
        if time.time() - t0 > time_budget:
            reason = f"time budget {time_budget}s"
            break
    if not track_val and reason == "max_steps":
        best_params, best_step = params, max_steps
    return best_params, best_step, vh, th, reason


def fit_wave(imgs, i, j, reg: Registration, frozen=False, zetas=(32., 64., 128.),
             m0="geomean", pad=40, stride=4, n_gs=30, max_steps=400, patience=40,
             time_budget=55.0, lr=None, seed=0, kappa=0.0, fit_kappa=True,
             val_frac=0.10, hf=0.0, f_cut=0.25, refit=False, refit_budget=None
             ) -> FitResult:
    """Fit the wave model to planes i < j.

    ``m0``: magnification of the field grid relative to plane i (``"geomean"`` =
    sqrt(s_j) from the registration, 1.0 = v1's layout but plane i interpolated too).
    ``hf``: weight of the field-spectrum penalty above ``f_cut`` cycles/fine sample.
    ``refit``: after the validation run, restart from the same initialisation and run
    the validation-chosen number of steps on *all* pixels (time permitting).
    """
    t0 = time.time()
    h, w = imgs[0].shape
    if m0 == "geomean":
        m0 = float(np.sqrt(reg.s_j))
    g = make_geometry(h, w, i, j, m0=m0, pad=pad, stride=stride, frozen=frozen)
    lr = dict(DEFAULT_LR, **(lr or {}))
    if not fit_kappa or frozen:
        lr["kappa"] = 0.0
    mtr, mva = block_masks((h, w), block=1, frac=val_frac, seed=seed)
    ys = jnp.asarray(np.stack(imgs), jnp.float32)
    mtr, mva = jnp.asarray(mtr), jnp.asarray(mva)
    step = make_step(g, lr, hf=hf, f_cut=f_cut)

    scan = {}
    best = None
    mtr_np = np.asarray(mtr) > 0
    for z in zetas:
        p = init_params(imgs, reg, g, z, n_gs=n_gs, seed=seed, kappa=kappa)
        # scored with the chunked renderer: this also compiles it for predict_stack
        pr = render_planes(p, [i, j], g)
        rtr = np.mean([sf.pearson(pr[k], imgs[k], mtr_np[k]) for k in (0, 1)])
        scan[float(z)] = float(rtr)
        if best is None or rtr > best[0]:
            best = (rtr, p)
    p_init = best[1]
    params, best_step, vh, th, reason = _run_adam(
        step, p_init, ys, mtr, mva, max_steps, patience, t0, time_budget)
    n_steps = len(vh)
    if refit:
        # same number of steps on all pixels (validation pixels now in the loss)
        elapsed = time.time() - t0
        per_step = (elapsed - 0.0) / max(n_steps, 1)
        budget = refit_budget if refit_budget is not None else time_budget
        if elapsed + best_step * per_step * 0.9 < budget + 5.0:
            ones = jnp.ones_like(mtr)
            params, _, _, _, r2 = _run_adam(step, p_init, ys, ones, mva, best_step,
                                           10 ** 9, t0, budget + 5.0, track_val=False)
            reason += f"; refit {best_step} steps on all pixels ({r2})"
        else:
            reason += "; refit skipped (time)"
    return FitResult(params, g, best_step, n_steps, reason, vh, th,
                     time.time() - t0, scan)


CHUNK = 4     # planes per call of the compiled renderer


@functools.partial(jax.jit, static_argnums=(2,))
def _render_jit(params, ts, g: Geometry):
    return render(params, ts, g, jnp.asarray(taper2d(g)), _freq2(g))


def render_planes(params, ts, g: Geometry) -> np.ndarray:
    """Rendered planes ``ts`` (arbitrary gain), ``CHUNK`` planes per call so one
    compiled function (compiled during the fit) serves every prediction."""
    ts = np.asarray(ts, np.float32)
    n = len(ts)
    padded = np.concatenate([ts, np.full((-n) % CHUNK, ts[-1], np.float32)])
    out = [np.asarray(_render_jit(params, jnp.asarray(padded[k:k + CHUNK]), g))
           for k in range(0, len(padded), CHUNK)]
    return np.concatenate(out)[:n]


def predict_stack(fit: FitResult, n_planes: int) -> np.ndarray:
    """Rendered planes 0..n_planes-1 (arbitrary gain)."""
    return render_planes(fit.params, np.arange(n_planes), fit.geometry)


# ----------------------------------------------------------------------------------
# prediction with the measured residual carried along ("model + residual transfer")
# ----------------------------------------------------------------------------------


def residual_weights(t, i: int, j: int):
    """Weights of the residuals of planes i and j at plane t: linear in t between the
    given planes (1 at its own plane, 0 at the other), the nearest plane's residual
    with weight 1 outside [i, j].  No tuned constants."""
    if t <= i:
        return 1.0, 0.0
    if t >= j:
        return 0.0, 1.0
    b = (t - i) / (j - i)
    return 1.0 - b, b


def _bspline_matrix(n: int, q: np.ndarray):
    """Sparse (len(q), n) matrix evaluating cubic-spline coefficients of a length-n
    signal at fractional positions ``q``; rows outside [-0.5, n - 0.5] are zero."""
    q0 = np.floor(q)
    u = q - q0
    wts = np.stack([(1 - u) ** 3 / 6, (3 * u ** 3 - 6 * u ** 2 + 4) / 6,
                    (-3 * u ** 3 + 3 * u ** 2 + 3 * u + 1) / 6, u ** 3 / 6])
    idx = q0.astype(int)[None, :] + np.arange(-1, 3)[:, None]
    rows = np.broadcast_to(np.arange(len(q)), idx.shape)
    ok = (idx >= 0) & (idx < n) & ((q >= -0.5) & (q <= n - 0.5))[None, :]
    return sparse.csr_matrix((wts[ok], (rows[ok], idx[ok])), shape=(len(q), n))


def transport(coef: np.ndarray, s: float, centre) -> np.ndarray:
    """Magnify an image given by its cubic-spline coefficients by ``s`` about
    ``centre`` (zero outside the frame): separable, two sparse matrix products."""
    h, w = coef.shape
    my = _bspline_matrix(h, centre[0] + (np.arange(h) - centre[0]) / s)
    mx = _bspline_matrix(w, centre[1] + (np.arange(w) - centre[1]) / s)
    return np.asarray((mx @ (my @ coef).T).T)


def predict_hybrid(fit: FitResult, imgs, n_planes: int, model_stack=None) -> np.ndarray:
    """Rendered planes plus the residuals of the two measured planes carried to every
    plane by the model's own magnification.

    For each given plane k: raw_k = a_k * render(k) + b_k + R_k (least squares a_k, b_k).
    Plane t: (w_i a_i + w_j a_j) render(t) + w_i T_{i->t}(R_i) + w_j T_{j->t}(R_j),
    T = magnification by s(t)/s(k) about the fitted centre (cubic splines, zero
    outside), w from :func:`residual_weights`.  At t = i, j this reproduces the
    measurement; elsewhere the model supplies the change between planes and the
    residual supplies the detail the model could not represent.
    """
    g = fit.geometry
    i, j = g.i, g.j
    P = predict_stack(fit, n_planes) if model_stack is None else model_stack
    s_j = float(np.exp(fit.params["log_s"]))
    centre = [float(c) for c in np.asarray(fit.params["centre"])]
    gain, coef = {}, {}
    for k, y in zip((i, j), imgs):
        a, b = np.polyfit(P[k].ravel().astype(np.float64), y.ravel(), 1)
        gain[k] = a
        coef[k] = ndi.spline_filter(y - (a * P[k] + b), order=3)
    out = np.empty(P.shape, np.float32)
    for t in range(n_planes):
        w = dict(zip((i, j), residual_weights(t, i, j)))
        acc = (w[i] * gain[i] + w[j] * gain[j]) * P[t].astype(np.float64)
        for k in (i, j):
            if w[k]:
                s = rel_mag(t, s_j, i, j) / rel_mag(k, s_j, i, j)
                acc += w[k] * transport(coef[k], s, centre)
        out[t] = acc
    return out


def blended_baseline(given: dict, reg: Registration, n_planes: int) -> np.ndarray:
    """Scaling baseline with the same linear blend between the two given planes (for
    comparison only: how much of the hybrid's gain is the blend itself)."""
    i, j = sorted(given)
    filt = {k: ndi.spline_filter(given[k], order=3) for k in (i, j)}
    out = np.empty((n_planes,) + given[i].shape)
    for t in range(n_planes):
        acc = 0.0
        for k, wk in zip((i, j), residual_weights(t, i, j)):
            if wk:
                s = rel_mag(t, reg.s_j, i, j) / rel_mag(k, reg.s_j, i, j)
                acc = acc + wk * sf.magnify(filt[k], s, reg.centre, prefiltered=True)
        out[t] = acc
    return out
