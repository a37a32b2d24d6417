"""Predict a whole DiffuserCam PSF stack from two measured planes.

Two predictors, both fitted to planes ``i`` and ``j`` only:

* :func:`baseline_stack` -- the *scaling baseline*: the nearest given plane magnified
  about a fitted fixed point, the magnification of every plane linear in the plane
  index (fixed by the two given planes), cubic-spline resampling.
* :class:`WaveModel` / :func:`fit_wave` -- a thin-phase wave model: one complex
  diffuser field ``g = A exp(j theta)`` sampled 2x finer than the sensor pixel, Fresnel
  propagated by an effective distance ``zeta(t)`` and magnified by ``s(t)`` about a
  fitted centre (Fresnel scaling theorem), |.|^2, a small Gaussian blur, 2x2 binned to
  pixels.  Early stopping on held-out pixel blocks of the two given planes.

Everything is in pixel units; plane ``t`` is an integer index, planes equally spaced in
1/z1, so the magnification relative to the reference plane ``i`` is
``s(t) = (1 + c t) / (1 + c i)`` and ``zeta(t) = zeta_i / s(t)``.

Pure numpy / scipy / JAX; no dependency on the ``diffcam`` package.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.ndimage as ndi
import scipy.optimize as sopt

import jax
import jax.numpy as jnp

# ----------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------


def load_stack(path: str, key: str = "psf_stack") -> np.ndarray:
    """Load a uint16 PSF stack, scale to [0, 1], subtract a per-plane dark level.

    The dark level is the median of a 6-pixel ring at the frame border (the caustic
    does not reach the border in this data set; a median ignores a few bright pixels).
    Each plane is then divided by its mean so all planes have comparable scale.
    """
    raw = np.load(path)[key].astype(np.float64) / 65535.0
    return preprocess(raw)


def preprocess(stack: np.ndarray, ring: int = 6) -> np.ndarray:
    """Dark-subtract (border-ring median) and mean-normalise every plane."""
    out = np.empty_like(stack, dtype=np.float64)
    mask = np.zeros(stack.shape[1:], bool)
    mask[:ring] = mask[-ring:] = True
    mask[:, :ring] = mask[:, -ring:] = True
    for k, f in enumerate(stack):
        f = f - np.median(f[mask])
        out[k] = f / f.mean()
    return out


def transform_stack(stack: np.ndarray, kind: str, crop_frac: float = 0.8,
                    rng: np.random.Generator | None = None) -> np.ndarray:
    """Apply the same rotation/flip and a random crop (area ``crop_frac``) to all planes.

    ``kind`` is one of ``rot90``, ``rot180``, ``rot270``, ``flipud``, ``fliplr``,
    ``transpose`` or ``none``.  The crop keeps ``sqrt(crop_frac)`` of each side at a
    random offset drawn from ``rng``.
    """
    ops = {
        "none": lambda a: a,
        "rot90": lambda a: np.rot90(a, 1, axes=(1, 2)),
        "rot180": lambda a: np.rot90(a, 2, axes=(1, 2)),
        "rot270": lambda a: np.rot90(a, 3, axes=(1, 2)),
        "flipud": lambda a: a[:, ::-1, :],
        "fliplr": lambda a: a[:, :, ::-1],
        "transpose": lambda a: np.swapaxes(a, 1, 2),
    }
    a = np.ascontiguousarray(ops[kind](stack))
    if crop_frac >= 1.0:
        return a
    rng = rng or np.random.default_rng(0)
    h, w = a.shape[1:]
    ch, cw = int(round(h * np.sqrt(crop_frac))), int(round(w * np.sqrt(crop_frac)))
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    return np.ascontiguousarray(a[:, y0:y0 + ch, x0:x0 + cw])


def pearson(a, b, mask=None) -> float:
    """Pearson correlation of two images (optionally over a boolean mask)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if mask is not None:
        a, b = a[mask], b[mask]
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


# ----------------------------------------------------------------------------------
# magnification geometry (shared by the baseline and the wave model)
# ----------------------------------------------------------------------------------


def mag_slope(s_j: float, i: int, j: int) -> float:
    """Slope ``c`` of M(t) ∝ 1 + c t given the ratio s_j = M(j)/M(i)."""
    return (s_j - 1.0) / (j - s_j * i)


def rel_mag(t, s_j, i: int, j: int):
    """Magnification of plane ``t`` relative to plane ``i`` (works for numpy and JAX)."""
    c = (s_j - 1.0) / (j - s_j * i)
    return (1.0 + c * t) / (1.0 + c * i)


def magnify(img: np.ndarray, s: float, centre, order: int = 3,
            prefiltered: bool = False) -> np.ndarray:
    """``out(p) = img(centre + (p - centre) / s)``: magnify ``img`` by ``s`` about
    ``centre`` (pixel coordinates (y, x)), cubic splines, zero outside the frame."""
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    cy, cx = centre
    coords = np.stack([cy + (yy - cy) / s, cx + (xx - cx) / s])
    return ndi.map_coordinates(img, coords, order=order, mode="constant", cval=0.0,
                               prefilter=not prefiltered)


# ----------------------------------------------------------------------------------
# registration: magnification + fixed point between the two given planes
# ----------------------------------------------------------------------------------


@dataclasses.dataclass
class Registration:
    s_j: float          # M(j) / M(i)
    centre: tuple       # fixed point (y, x), pixels
    r: float            # Pearson of the registered pair
    seconds: float


def _moments(img):
    w = np.clip(img, 0, None)
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    m = w.sum()
    cy, cx = (w * yy).sum() / m, (w * xx).sum() / m
    rg = np.sqrt((w * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum() / m)
    return np.array([cy, cx]), rg


def register(img_i: np.ndarray, img_j: np.ndarray) -> Registration:
    """Fit ``img_j ≈ magnify(img_i, s_j, centre)`` by maximising Pearson.

    Initial guess from intensity moments (centroid and radius of gyration: under a
    magnification about p0 both scale about p0), then Nelder-Mead on the images blurred
    by 2 px, then on the raw images (cubic splines throughout).  Nothing assumes the
    centre is the frame centre.
    """
    t0 = time.time()
    ci, ri = _moments(img_i)
    cj, rj = _moments(img_j)
    s0 = rj / ri
    if abs(1 - s0) > 0.01:
        p0 = (cj - s0 * ci) / (1 - s0)
    else:
        p0 = cj
    h, w = img_i.shape
    p0 = np.clip(p0, [-h, -w], [2 * h, 2 * w])
    x = np.array([np.log(s0), p0[0], p0[1]])
    for sigma in (2.0, 0.0):
        a = ndi.gaussian_filter(img_i, sigma) if sigma else img_i
        b = ndi.gaussian_filter(img_j, sigma) if sigma else img_j
        a_f = ndi.spline_filter(a, order=3)

        def cost(p):
            return -pearson(magnify(a_f, np.exp(p[0]), (p[1], p[2]), prefiltered=True), b)

        simplex = np.array([x, x + [0.01, 0, 0], x + [0, 15, 0], x + [0, 0, 15]])
        res = sopt.minimize(cost, x, method="Nelder-Mead",
                            options=dict(initial_simplex=simplex, xatol=1e-4,
                                         fatol=1e-7, maxiter=600))
        x = res.x
    return Registration(float(np.exp(x[0])), (float(x[1]), float(x[2])), float(-res.fun),
                        time.time() - t0)


# ----------------------------------------------------------------------------------
# the scaling baseline
# ----------------------------------------------------------------------------------


def baseline_stack(given: dict, reg: Registration, n_planes: int) -> np.ndarray:
    """Scaling baseline: each plane t = nearest given plane magnified about the fitted
    fixed point by M(t)/M(nearest), M linear in t (from the two planes), cubic splines.

    ``given`` maps plane index -> image (exactly two entries, i < j).
    """
    i, j = sorted(given)
    filt = {k: ndi.spline_filter(given[k], order=3) for k in (i, j)}
    out = np.empty((n_planes,) + given[i].shape)
    for t in range(n_planes):
        k = i if abs(t - i) <= abs(t - j) else j
        s = rel_mag(t, reg.s_j, i, j) / rel_mag(k, reg.s_j, i, j)
        out[t] = magnify(filt[k], s, reg.centre, prefiltered=True)
    return out


# ----------------------------------------------------------------------------------
# the wave model
# ----------------------------------------------------------------------------------
#
# Coordinates.  Pixel k of the frame has its centre at k (pixel units).  The field is
# sampled twice per pixel: fine sensor sample a sits at pixel coordinate (a - 0.5) / 2.
# The field grid adds ``pad`` fine samples on every side (plus FFT-friendly rounding at
# the end): field sample n <-> pixel coordinate (n - pad - 0.5) / 2 *of plane i*, the
# reference plane (s = 1, no interpolation needed).  Plane t sees the field
# magnified by s(t) about ``centre``: sensor point y samples the field at
# centre + (y - centre) / s(t).


def _good_size(n: int) -> int:
    """Smallest m >= n whose prime factors are 2, 3, 5, 7 (fast FFT sizes)."""
    m = n
    while True:
        k = m
        for p in (2, 3, 5, 7):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


@dataclasses.dataclass(frozen=True)
class Geometry:
    """Static sizes of the wave model (hashable: used as a jit static argument)."""
    h: int               # frame height, pixels
    w: int               # frame width, pixels
    pad: int             # fine samples added before the frame on each axis
    ny: int              # field grid, fine samples
    nx: int
    stride: int          # amplitude coarse-grid stride, fine samples
    i: int               # reference plane (s = 1)
    j: int               # the other given plane
    frozen: bool = False  # frozen-distance ablation: zeta(t) = zeta_i for all t
    taps: int = 4        # Gaussian blur half-width, fine samples

    @property
    def coarse(self):
        return (-(-self.ny // self.stride) + 1, -(-self.nx // self.stride) + 1)


def make_geometry(h, w, i, j, pad=40, stride=4, frozen=False) -> Geometry:
    return Geometry(h, w, pad, _good_size(2 * h + 2 * pad), _good_size(2 * w + 2 * pad),
                    stride, i, j, frozen)


def _taper(n: int, pad: int) -> np.ndarray:
    """1 inside, smooth (raised cosine) to 0 over the outer ``pad // 2`` samples: keeps
    energy off the grid edge so the FFT's periodic wrap-around never matters."""
    x = np.ones(n)
    r = max(pad // 2, 2)
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(r) / r)
    x[:r] = ramp
    x[n - r:] = ramp[::-1]
    x[:2] = 0
    x[-2:] = 0
    return x


def taper2d(g: Geometry) -> np.ndarray:
    return np.outer(_taper(g.ny, g.pad), _taper(g.nx, g.pad)).astype(np.float32)


def _keys_weights(u):
    """Keys cubic-convolution (a = -0.5) weights of taps -1, 0, 1, 2 at offset u∈[0,1)."""
    a = -0.5
    def near(x):
        return (a + 2) * x ** 3 - (a + 3) * x ** 2 + 1
    def far(x):
        return a * x ** 3 - 5 * a * x ** 2 + 8 * a * x - 4 * a
    return jnp.stack([far(1 + u), near(u), near(1 - u), far(2 - u)])


def _interp_axis0(f, q):
    """Sample ``f`` (n, m) at fractional row positions ``q`` (k,) -> (k, m); cubic
    convolution, zero outside the grid.  Gathers whole rows: cheap, differentiable in q."""
    n = f.shape[0]
    q0 = jnp.floor(q)
    wts = _keys_weights(q - q0)                        # (4, k)
    idx = q0.astype(jnp.int32)[None, :] + jnp.arange(-1, 3)[:, None]
    wts = jnp.where((idx >= 0) & (idx < n), wts, 0.0)
    rows = f[jnp.clip(idx, 0, n - 1)]                 # (4, k, m)
    return jnp.einsum("tk,tkm->km", wts.astype(f.real.dtype), rows)


def sample_magnified(u, s, centre, g: Geometry):
    """Field ``u`` on the field grid -> the fine sensor grid of a plane magnified by
    ``s`` about ``centre`` (pixels).  Separable cubic convolution."""
    ay = (jnp.arange(2 * g.h) - 0.5) / 2.0             # pixel coordinates of fine samples
    ax = (jnp.arange(2 * g.w) - 0.5) / 2.0
    qy = 2.0 * (centre[0] + (ay - centre[0]) / s) + 0.5 + g.pad
    qx = 2.0 * (centre[1] + (ax - centre[1]) / s) + 0.5 + g.pad
    v = _interp_axis0(u, qy)                           # (2h, nx)
    return _interp_axis0(v.T, qx).T                    # (2h, 2w)


def _gauss_blur(img, sigma, margin=8):
    """Gaussian blur (std ``sigma`` fine samples) by FFT on a grid zero-padded by
    ``margin`` so nothing wraps around."""
    p = jnp.pad(img, margin)
    fy = np.fft.fftfreq(p.shape[0])[:, None]
    fx = np.fft.rfftfreq(p.shape[1])[None, :]
    f2 = jnp.asarray((fy ** 2 + fx ** 2).astype(np.float32))
    out = jnp.fft.irfft2(jnp.fft.rfft2(p) * jnp.exp(-2 * np.pi ** 2 * sigma ** 2 * f2),
                         s=p.shape)
    return out[margin:-margin, margin:-margin]


def _freq2(g: Geometry):
    fy = np.fft.fftfreq(g.ny)[:, None]
    fx = np.fft.fftfreq(g.nx)[None, :]
    return jnp.asarray((fy ** 2 + fx ** 2).astype(np.float32))


def amplitude(params, g: Geometry, taper):
    """Smooth amplitude: exp(coarse log-amplitude, cubic-upsampled) times the edge taper."""
    la = jax.image.resize(params["logamp"], (g.ny, g.nx), "cubic")
    return jnp.exp(la) * taper


def spectrum(params, g: Geometry, taper):
    """FFT of the diffuser field g = A exp(j theta), computed once for all planes."""
    a = amplitude(params, g, taper)
    return jnp.fft.fft2(a * jnp.exp(1j * params["theta"]))


def plane_scalars(params, t, g: Geometry):
    """Magnification s(t) relative to plane i, and zeta(t)."""
    s = rel_mag(t, jnp.exp(params["log_s"]), g.i, g.j)
    zeta_i = jnp.exp(params["log_zeta"])
    kappa = 0.0 if g.frozen else params["kappa"]
    zeta = zeta_i * s ** (-kappa)
    return s, zeta


def render_plane(params, spec, t, g: Geometry, f2, ref=False):
    """Predicted pixel image of plane ``t`` (arbitrary gain, no background).

    ``ref=True`` (only for t = i, where s = 1 exactly) skips the interpolation: the
    fine sensor grid *is* the field grid there."""
    s, zeta = plane_scalars(params, t, g)
    u = jnp.fft.ifft2(spec * jnp.exp(-1j * jnp.pi * zeta * f2))
    if ref:
        v = u[g.pad:g.pad + 2 * g.h, g.pad:g.pad + 2 * g.w]
    else:
        v = sample_magnified(u, s, params["centre"], g)
    inten = jnp.real(v) ** 2 + jnp.imag(v) ** 2
    inten = _gauss_blur(inten, jnp.exp(params["log_sigma"]))
    return inten.reshape(g.h, 2, g.w, 2).mean(axis=(1, 3))


def render(params, ts, g: Geometry, taper, f2):
    """Predicted pixel images of the planes ``ts`` (sequential map: bounded memory)."""
    spec = spectrum(params, g, taper)
    return jax.lax.map(lambda t: render_plane(params, spec, t, g, f2),
                       jnp.asarray(ts, jnp.float32))


def masked_pearson(p, y, m):
    """Pearson correlation of p and y over weights m (same shape), JAX."""
    n = m.sum()
    pm = (m * p).sum() / n
    ym = (m * y).sum() / n
    dp = (p - pm) * m
    dy = (y - ym) * m
    return (dp * dy).sum() / jnp.sqrt((dp * dp).sum() * (dy * dy).sum() + 1e-30)


# ----------------------------------------------------------------------------------
# initialisation: measured planes on the field grid + Gerchberg-Saxton
# ----------------------------------------------------------------------------------


def to_field_grid(img, s, centre, g: Geometry):
    """Resample a measured plane (magnification ``s`` relative to plane i) onto the
    field grid (un-magnified, 2x finer).  Returns (intensity >= 0, known-mask)."""
    n_y = np.arange(g.ny)
    n_x = np.arange(g.nx)
    py = (n_y - g.pad - 0.5) / 2.0                     # plane-i pixel coordinates
    px = (n_x - g.pad - 0.5) / 2.0
    sy = centre[0] + s * (py - centre[0])              # sensor coordinates of plane
    sx = centre[1] + s * (px - centre[1])
    yy, xx = np.meshgrid(sy, sx, indexing="ij")
    val = ndi.map_coordinates(img, [yy, xx], order=3, mode="constant", cval=0.0)
    known = (yy >= -0.5) & (yy <= g.h - 0.5) & (xx >= -0.5) & (xx <= g.w - 0.5)
    return np.clip(val, 0, None) * known, known


@jax.jit
def _gs(amp, mods, knowns, hs, theta, n_iter):
    """Gerchberg-Saxton with a known (smooth) amplitude at the diffuser and measured
    moduli at the planes (only where ``knowns``); planes visited in turn."""
    def body(_, th):
        for m, k, h in zip(mods, knowns, hs):
            gfield = amp * jnp.exp(1j * th)
            u = jnp.fft.ifft2(jnp.fft.fft2(gfield) * h)
            u = jnp.where(k, m * jnp.exp(1j * jnp.angle(u)), u)
            th = jnp.angle(jnp.fft.ifft2(jnp.fft.fft2(u) * jnp.conj(h)))
        return th
    return jax.lax.fori_loop(0, n_iter, body, theta)


def init_params(imgs, reg: Registration, g: Geometry, zeta, n_gs=30, amp_blur=6.0,
                sigma=1.0, seed=0, kappa=1.0):
    """Initial parameters: amplitude from the blurred reference plane (its envelope is
    the diffuser's illumination: geometric optics conserves local energy), phase from
    ``n_gs`` Gerchberg-Saxton sweeps between the two planes at effective distance
    ``zeta`` (plane i) and ``zeta / s_j`` (plane j; ``zeta`` for the frozen ablation)."""
    taper = taper2d(g)
    ii, ki = to_field_grid(imgs[0], 1.0, reg.centre, g)
    ij, kj = to_field_grid(imgs[1], reg.s_j, reg.centre, g)
    env = ndi.gaussian_filter(ii, amp_blur)
    env = np.where(ki, env, 0.0)
    amp = np.sqrt(np.clip(env, 0, None)) * taper
    e = (amp ** 2).sum()
    mods = [np.sqrt(ii * e / ii.sum()), np.sqrt(ij * e / ij.sum())]
    f2 = np.asarray(_freq2(g))
    zj = zeta if g.frozen else zeta * reg.s_j ** (-kappa)
    hs = [np.exp(-1j * np.pi * z * f2).astype(np.complex64) for z in (zeta, zj)]
    rng = np.random.default_rng(seed)
    th0 = (0.1 * rng.standard_normal((g.ny, g.nx))).astype(np.float32)
    theta = _gs(jnp.asarray(amp, jnp.float32), [jnp.asarray(m, jnp.float32) for m in mods],
                [jnp.asarray(ki), jnp.asarray(kj)], [jnp.asarray(h) for h in hs],
                jnp.asarray(th0), n_gs)
    # coarse log-amplitude: area-average of the envelope, floored (soft support)
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
# fitting: Adam, early stopping on held-out pixel blocks of the two given planes
# ----------------------------------------------------------------------------------


def block_masks(shape, n_planes=2, block=8, frac=0.15, seed=0):
    """Validation masks: a random ``frac`` of ``block``x``block`` pixel blocks, drawn
    independently for each given plane.  Returns (train, val) float32 arrays."""
    rng = np.random.default_rng(seed)
    h, w = shape
    by, bx = -(-h // block), -(-w // block)
    val = rng.random((n_planes, by, bx)) < frac
    val = np.repeat(np.repeat(val, block, 1), block, 2)[:, :h, :w]
    return (~val).astype(np.float32), val.astype(np.float32)


DEFAULT_LR = {"theta": 0.005, "logamp": 0.01, "log_zeta": 0.003, "log_s": 2e-5,
              "centre": 0.02, "log_sigma": 0.01, "kappa": 0.01}


@dataclasses.dataclass
class FitResult:
    params: dict
    geometry: Geometry
    best_step: int
    steps: int
    stop_reason: str
    val_history: list          # (step, val r) every step
    train_history: list
    seconds: float
    zeta_scan: dict


def _adam_step(params, grads, state, lr, b1=0.9, b2=0.999, eps=1e-12):
    m, v, k = state
    k = k + 1
    m = jax.tree.map(lambda a, g_: b1 * a + (1 - b1) * g_, m, grads)
    v = jax.tree.map(lambda a, g_: b2 * a + (1 - b2) * g_ * g_, v, grads)
    c1 = 1 - b1 ** k
    c2 = 1 - b2 ** k
    new = {key: params[key] - lr[key] * (m[key] / c1) / (jnp.sqrt(v[key] / c2) + eps)
           for key in params}
    return new, (m, v, k)


def make_step(g: Geometry, lr: dict):
    taper = jnp.asarray(taper2d(g))
    f2 = _freq2(g)
    ts = jnp.asarray([g.i, g.j], jnp.float32)

    def loss_fn(params, ys, mtr, mva):
        spec = spectrum(params, g, taper)
        pred = jnp.stack([render_plane(params, spec, ts[0], g, f2, ref=True),
                          render_plane(params, spec, ts[1], g, f2)])
        r_tr = jax.vmap(masked_pearson)(pred, ys, mtr)
        r_va = jax.vmap(masked_pearson)(pred, ys, mva)
        return (1.0 - r_tr).sum(), (r_tr.mean(), jax.lax.stop_gradient(r_va.mean()))

    @jax.jit
    def step(params, state, ys, mtr, mva):
        (loss, (rtr, rva)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, ys, mtr, mva)
        params, state = _adam_step(params, grads, state, lr)
        return params, state, rtr, rva

    @jax.jit
    def evaluate(params, ys, mtr, mva):
        return loss_fn(params, ys, mtr, mva)[1]

    return step, evaluate


def fit_wave(imgs, i, j, reg: Registration, frozen=False, zetas=(4., 8., 16., 32., 64.),
             pad=40, stride=4, n_gs=30, max_steps=400, patience=60, time_budget=50.0,
             lr=None, seed=0, verbose=False, callback=None, cb_every=20, kappa=1.0,
             fit_kappa=False, val_block=8, val_frac=0.15) -> FitResult:
    """Fit the wave model to planes i < j (``imgs`` = [img_i, img_j], preprocessed).

    1. zeta scan: for every candidate effective distance run the GS initialisation and
       keep the one whose rendered planes best match the *training* pixels.
    2. Adam on all parameters; the validation Pearson (held-out blocks) is recorded at
       every step; the parameters with the best validation score are returned.
       Stops at ``max_steps``, after ``patience`` steps without validation
       improvement, or when the wall-clock ``time_budget`` (s, incl. init) is spent.
    """
    t0 = time.time()
    h, w = imgs[0].shape
    g = make_geometry(h, w, i, j, pad=pad, stride=stride, frozen=frozen)
    lr = dict(DEFAULT_LR, **(lr or {}))
    if not fit_kappa:
        lr["kappa"] = 0.0
    mtr, mva = block_masks((h, w), block=val_block, frac=val_frac, seed=seed)
    ys = jnp.asarray(np.stack(imgs), jnp.float32)
    mtr, mva = jnp.asarray(mtr), jnp.asarray(mva)
    step, evaluate = make_step(g, lr)

    scan = {}
    best = None
    for z in zetas:
        p = init_params(imgs, reg, g, z, n_gs=n_gs, seed=seed, kappa=kappa)
        rtr, rva = evaluate(p, ys, mtr, mva)
        scan[float(z)] = (float(rtr), float(rva))
        if verbose:
            extra = callback(p) if callback is not None else ""
            print(f"  zeta {z:6.1f}: train r {float(rtr):.4f}  val r {float(rva):.4f}"
                  f"  ({time.time() - t0:.1f}s) {extra}")
        if best is None or float(rtr) > best[0]:
            best = (float(rtr), p)
    params = best[1]

    zeros = jax.tree.map(jnp.zeros_like, params)
    state = (zeros, zeros, jnp.int32(0))
    best_val, best_params, best_step = -np.inf, params, 0
    vh, th = [], []
    reason = "max_steps"
    for k in range(max_steps):
        new_params, state, rtr, rva = step(params, state, ys, mtr, mva)
        rva = float(rva)                    # score of `params` (before this update)
        vh.append(rva)
        th.append(float(rtr))
        if rva > best_val:
            best_val, best_params, best_step = rva, params, k
        params = new_params
        if verbose and k % cb_every == 0:
            extra = callback(params) if callback is not None else ""
            print(f"  step {k:4d}: train r {float(rtr):.5f}  val r {rva:.5f}"
                  f"  ({time.time() - t0:.1f}s) {extra}")
        if k - best_step >= patience:
            reason = f"no val improvement for {patience} steps"
            break
        if time.time() - t0 > time_budget:
            reason = f"time budget {time_budget}s"
            break
    return FitResult(best_params, g, best_step, len(vh), reason, vh, th,
                     time.time() - t0, scan)


def predict_stack(fit: FitResult, n_planes: int) -> np.ndarray:
    """Render all planes 0..n_planes-1 with the fitted model."""
    g = fit.geometry
    fn = jax.jit(lambda p, ts: render(p, ts, g, jnp.asarray(taper2d(g)), _freq2(g)))
    return np.asarray(fn(fit.params, jnp.arange(n_planes, dtype=jnp.float32)))
