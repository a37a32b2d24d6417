"""Alternating projections between the near- and far-field amplitudes (paper Fig. 4).

The iterate u is the field in the **near-capture plane** (``near_distance`` behind the
diffuser). Free-space propagation is a pure phase e^{jφ(f)} on the spectrum, so the
Fourier-lens amplitude |FT(diffuser field)| equals |FT(u)| for any near distance: the
far-field projection P_M is one FFT pair whatever the distance, and the distance enters
only to start (diffuser → near plane) and to return θd at the diffuser. (Imposing the
aperture as a support at the diffuser plane as well costs two more FFT pairs per
iteration and, measured on the scaled Fig. 3 problem 0.33 mm behind the diffuser, stalls
RAAR at 0.87 where the near amplitude alone reaches 1.0: it is not offered.)

Projections (Marchesini 2007 notation, P_S the near-amplitude projection):

- ``"gs"``    Gerchberg–Saxton / error reduction   u ← P_S P_M u  (stagnates)
- ``"hio"``   hybrid input–output (Fienup)        u ← u + P_S((1+β)P_M u − u) − β P_M u
- ``"raar"``  relaxed averaged alternating reflections (Luke 2005)
              u ← β u + β P_S(2 P_M u − u) + (1 − 2β) P_M u

Extra intensity planes (``planes=``, `diffcam.calibrate.phase.planes`, e.g. a captured
PSF) each add a projection P_k: propagate to the plane, impose its amplitude where it was
measured, propagate back. P_M then averages P_far and the P_k (averaged projections),
and the schemes above run unchanged: on the Fig. 6 random diffuser, whose phase spans
many 2π, near/far RAAR stalls at a phase Pearson of 0.67 and with one PSF plane it
reaches 0.999 from a flat start (1024², 300 iterations).

Each projection onto a measured amplitude A is u·(A/|u|) with a safe divide (about 3×
cheaper than A·exp(j·angle(u))). Arrays are kept in FFT order (``ifftshift``-ed once)
with unitary FFTs, so the loop has no shifts; the far amplitude is scaled to the near
field's energy (Parseval), which also absorbs any exposure difference.
"""

from __future__ import annotations

import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.backend import fft2, ifft2

from diffcam.core.options import Options
from diffcam.core.errors import DiffcamError, ShapeError, check_finite
from diffcam.core.progress import progress_bar, tick
from diffcam.core.phasor import expj
from diffcam.optics.propagation import apply_transfer, transfer_function
from diffcam.calibrate.phase.near_far import CalibrationGeometry, check_captures, check_far_pitch
from diffcam.calibrate.phase.planes import check_planes
from diffcam.calibrate.phase.result import RetrievalResult

__all__ = ["retrieve_projections", "ProjectionOptions", "gerchberg_saxton", "hio", "raar", "initial_phase",
           "fit_amplitude", "METHODS"]

METHODS = ("gs", "hio", "raar")
_AXES = (-2, -1)


def _to_fft_order(a):
    return jnp.fft.ifftshift(a, axes=_AXES)


def _to_centred(a):
    return jnp.fft.fftshift(a, axes=_AXES)


def fit_amplitude(u, amplitude):
    """u·(A/|u|), 0 where |u| = 0 (the safe divide keeps gradients and values finite)."""
    m = jnp.abs(u)
    return u * jnp.where(m > 0, amplitude / jnp.where(m > 0, m, 1.0), 0.0)


def _operators(near_amp, far_amp, planes):
    """P_S and P_M on FFT-ordered near-plane fields. With extra planes, P_M is the
    average of the far-field projection and each plane's (averaged projections: the
    measurement constraints of a product space, reflected together by RAAR/HIO)."""

    def p_near(u):
        return fit_amplitude(u, near_amp)

    def p_far(u):
        return ifft2(fit_amplitude(fft2(u, norm="ortho"), far_amp),
                             norm="ortho")

    def p_plane(u, amp, mask, H):
        v = apply_transfer(u, H)
        v = jnp.where(mask > 0, fit_amplitude(v, amp), v)
        return apply_transfer(v, jnp.conj(H))

    def p_measured(u):
        if planes is None:
            return p_far(u)
        amps, masks, kernels = planes
        total = p_far(u)
        for k in range(amps.shape[0]):
            total = total + p_plane(u, amps[k], masks[k], kernels[k])
        return total / (1 + amps.shape[0])

    return p_near, p_measured


@partial(jax.jit, static_argnames=("method", "iterations"))
def _iterate(u0, near_amp, far_amp, planes, beta, *, method, iterations):
    """Run one projection algorithm from the near-plane field ``u0`` (FFT order);
    ``planes`` is ``None`` or (amplitudes, masks, kernels), each (k, ny, nx)."""
    p_near, p_far = _operators(near_amp, far_amp, planes)
    norm = jnp.linalg.norm(near_amp)

    def step(u, k):
        tick(k)
        pm = p_far(u)
        err = jnp.linalg.norm(jnp.abs(pm) - near_amp) / norm
        if method == "gs":
            u = p_near(pm)
        elif method == "hio":
            u = u + p_near((1 + beta) * pm - u) - beta * pm
        else:
            u = beta * u + beta * p_near(2 * pm - u) + (1 - 2 * beta) * pm
        return u, err

    u, history = jax.lax.scan(step, u0, jnp.arange(iterations))
    return p_near(p_far(u)), history


def initial_phase(init, shape, key=None, restarts: int = 1) -> Float[Array, "restarts ny nx"]:
    """Starting diffuser phases (radians), one per restart.

    ``init`` is ``"random"`` (uniform on [−π, π), one draw per restart from
    ``jax.random.split(key, restarts)``), ``"flat"`` (zeros) or a phase array (ny, nx).
    """
    if isinstance(init, str):
        if init == "random":
            if key is None:
                raise DiffcamError("init='random' needs key=jax.random.key(<seed>) "
                                   "(diffcam takes randomness only from explicit keys).")
            keys = jax.random.split(key, restarts)
            return jax.vmap(lambda k: jax.random.uniform(k, shape[-2:], minval=-jnp.pi,
                                                         maxval=jnp.pi))(keys)
        if init == "flat":
            if restarts != 1:
                raise DiffcamError("restarts > 1 needs init='random' (flat starts are identical).")
            return jnp.zeros((1,) + tuple(shape[-2:]), jnp.float32)
        raise DiffcamError(f"init must be 'random', 'flat' or a phase array, got {init!r}.")
    phase = jnp.asarray(init, jnp.float32)
    if phase.shape != tuple(shape[-2:]):
        raise ShapeError(f"init phase has shape {phase.shape}, the captures {tuple(shape[-2:])}.")
    check_finite("init phase", phase)
    if restarts != 1:
        raise DiffcamError("restarts > 1 needs init='random' (a given start is deterministic).")
    return phase[None]


class ProjectionOptions(Options):
    """How alternating projections run.

    Attributes:
        method: ``"gs"``, ``"hio"`` or ``"raar"``.
        iterations: number of iterations (one FFT pair each).
        beta: HIO / RAAR relaxation, in (0, 1].
        restarts: independent random starts, run batched with ``vmap`` (memory grows
            with it); the run with the smallest final error is returned. ``None``: 1 here;
            in [`retrieve_phase`][diffcam.calibrate.phase.pipeline.retrieve_phase] 4, or 1 with
            extra planes.
        init: ``"random"``, ``"flat"`` or a diffuser-plane phase (ny, nx), radians (the
            starting field is the near amplitude times e^{j·init}, carried to the near
            plane when ``near_distance > 0``). ``None``: ``"flat"`` with extra planes and
            one start (it converges; random starts can stall on a slightly inconsistent
            plane), else ``"random"``.
        key: ``jax.random`` key for random starts.
        planes: extra intensities,
            [`DefocusedPlane`][diffcam.calibrate.phase.planes.DefocusedPlane] (a captured PSF
            through [`psf_plane`][diffcam.calibrate.phase.planes.psf_plane]): each adds a
            projection (one FFT pair) averaged with the far-field one; they break the twin
            and un-stall strongly scattering diffusers.
        far_pitch: the far capture's pitch (m), checked against λf/(N·dx) if given.
        progress: a progress bar for runs over 2 s
            ([`diffcam.core.progress`][diffcam.core.progress]).
    """

    method: str = "raar"
    iterations: int = 300
    beta: float = 0.9
    restarts: int | None = None
    init: object = None
    key: object = None
    planes: tuple = ()
    far_pitch: float | None = None
    progress: bool = True

    def __check_init__(self):
        if self.method not in METHODS:
            raise DiffcamError(f"method must be one of {METHODS}, got {self.method!r}.")
        if not isinstance(self.iterations, (int, np.integer)) or self.iterations < 1:
            raise DiffcamError(f"iterations must be a positive int, got {self.iterations!r}.")
        if self.restarts is not None and (not isinstance(self.restarts, (int, np.integer))
                                          or self.restarts < 1):
            raise DiffcamError(f"restarts must be a positive int, got {self.restarts!r}.")
        if not 0 < float(self.beta) <= 1:
            raise DiffcamError(f"beta must be in (0, 1] (0.9 is usual), got {self.beta!r}.")



def retrieve_projections(near: Float[Array, "ny nx"], far: Float[Array, "ny nx"],
                         geometry: CalibrationGeometry, *,
                         options: ProjectionOptions | None = None,
                         **overrides) -> RetrievalResult:
    """Retrieve the diffuser phase from near- and far-field intensities by projections.

    Args:
        near: near-field intensity at ``geometry.near_distance`` behind the diffuser,
            pitch ``geometry.dx`` (any scale).
        far: far-field intensity at the Fourier-lens pitch λf/(N·dx) (any scale; it is
            matched to the near field's energy).
        geometry: the set-up, SI units.
        options: [`ProjectionOptions`][diffcam.calibrate.phase.projections.ProjectionOptions]
            (method, iterations, beta, restarts, init, key, extra planes, far_pitch,
            progress); ``**overrides`` replace its fields (``method=``, ``iterations=``,
            ``key=``, ``planes=``, ...).

    Returns:
        [`RetrievalResult`][diffcam.calibrate.phase.result.RetrievalResult];
        ``stats["restart_errors"]`` holds each run's final error.
    """
    check_captures(near, far)
    shape = np.shape(near)
    o = ProjectionOptions.of(options, **overrides)
    method, iterations, beta, init = o.method, int(o.iterations), o.beta, o.init
    restarts = 1 if o.restarts is None else int(o.restarts)
    key, planes, progress = o.key, tuple(o.planes), o.progress
    if o.far_pitch is not None:
        check_far_pitch(o.far_pitch, geometry, shape)
    t0 = time.perf_counter()
    near_amp = jnp.sqrt(jnp.asarray(near, jnp.float32))
    far_amp = jnp.sqrt(jnp.asarray(far, jnp.float32))
    far_amp = far_amp * jnp.linalg.norm(near_amp) / jnp.linalg.norm(far_amp)
    z = float(geometry.near_distance)
    H = None if z == 0 else transfer_function(shape, geometry.dx, geometry.wavelength, z)
    if init is None:  # with a plane one flat start converges; random ones can stall
        init = "flat" if planes and restarts == 1 else "random"
    phases = initial_phase(init, shape, key, restarts)
    fields = _to_fft_order(near_amp * expj(phases))
    if H is not None:
        fields = jax.vmap(apply_transfer, (0, None))(fields, H)
    near_f, far_f = _to_fft_order(near_amp), _to_fft_order(far_amp)
    extra = _plane_operands(check_planes(planes, shape), near_amp, geometry, z)
    run = partial(_iterate, method=method, iterations=iterations)
    with progress_bar(iterations, method.upper(), progress):
        u, histories = jax.block_until_ready(jax.vmap(run, (0, None, None, None, None))(
            fields, near_f, far_f, extra, jnp.float32(beta)))
    best = int(jnp.argmin(histories[:, -1]))
    u = u[best]
    if H is not None:
        u = apply_transfer(u, jnp.conj(H))
    field = _to_centred(u)
    phase = jnp.angle(field)
    phase.block_until_ready()
    stats = {"method": method, "iterations": iterations, "beta": float(beta),
             "restarts": restarts, "best": best, "restart_errors": histories[:, -1],
             "planes": len(planes),
             "wall_time": time.perf_counter() - t0}
    return RetrievalResult(phase, field, histories[best], stats)


def _plane_operands(planes, near_amp, geometry, near_distance):
    """(amplitudes, masks, kernels) in FFT order, each (k, ny, nx), or ``None``: the
    amplitudes matched to the near field's energy (Parseval), the Fresnel kernels from
    the near-capture plane to each plane (the PSF model's propagator)."""
    if not planes:
        return None
    shape = np.shape(near_amp)
    norm = jnp.linalg.norm(near_amp)
    amps, masks, kernels = [], [], []
    for plane in planes:
        amp = jnp.sqrt(jnp.asarray(plane.intensity, jnp.float32))
        amps.append(_to_fft_order(amp * norm / jnp.linalg.norm(amp)))
        masks.append(_to_fft_order(jnp.asarray(plane.mask, jnp.float32)))
        kernels.append(transfer_function(shape, geometry.dx, geometry.wavelength,
                                         float(plane.distance) - near_distance,
                                         "fresnel_tf"))
    return jnp.stack(amps), jnp.stack(masks), jnp.stack(kernels)


def gerchberg_saxton(near, far, geometry, **options) -> RetrievalResult:
    """Gerchberg–Saxton between near and far amplitudes (paper Fig. 4); see
    [`retrieve_projections`][diffcam.calibrate.phase.projections.retrieve_projections] for the
    arguments. Stagnates from random starts: use
    [`raar`][diffcam.calibrate.phase.projections.raar] or
    [`hio`][diffcam.calibrate.phase.projections.hio] (or restarts) when the error history flattens
    early."""
    return retrieve_projections(near, far, geometry, method="gs", **options)


def hio(near, far, geometry, **options) -> RetrievalResult:
    """Fienup's hybrid input–output; arguments as
    [`retrieve_projections`][diffcam.calibrate.phase.projections.retrieve_projections]."""
    return retrieve_projections(near, far, geometry, method="hio", **options)


def raar(near, far, geometry, **options) -> RetrievalResult:
    """Relaxed averaged alternating reflections; arguments as
    [`retrieve_projections`][diffcam.calibrate.phase.projections.retrieve_projections]."""
    return retrieve_projections(near, far, geometry, method="raar", **options)
