"""ADMM with total variation for the DiffuserCam crop model (Antipa et al., Optica 5,
1, 2018), in 2-D and for a PSF stack (3-D).

The problem, for a sensor image ``b``, crop ``C`` and convolution ``H`` (the sum over
depths for a volume)::

    min_v  ½ ||C H v - b||²  +  tau ||Ψ v||₁    subject to  v >= 0

with ``Ψ`` anisotropic finite differences: circular along y and x (diagonal under the
FFT, as in the DiffuserCam reference), and, for a volume with ``tv_axial=True``,
Neumann (non-periodic) along depth (diagonal under the DCT-II). ADMM splits
``x = H v`` (so the crop is a pixel-wise division), ``u = Ψ v`` (soft threshold) and
``w = v`` (projection onto ``w >= 0``), with penalties ``mu1``, ``mu2``, ``mu3`` and
scaled duals. The ``v`` update solves ``(mu1 HᵀH + mu2 ΨᵀΨ + mu3) v = r`` exactly: per
lateral frequency, ``HᵀH`` over depth is the rank-one ``conj(h) hᵀ``, so
Sherman–Morrison turns it into two applications of the (diagonal) TV-and-identity part.
Everything that depends only on the PSF and the penalties is computed once, before the
loop.

Scaling: like the DiffuserCam code (2-D tutorial and 3-D solver), the PSF (the whole
stack for a volume) is divided by its L2 norm, so the penalties ``mu1..mu3`` do not
depend on the PSF's units nor on the image's (every term of the augmented Lagrangian
scales with ``||b||²``); ``tau`` does scale with the image: the tutorial's ``tau = 1e-4``
is for an L2-normalised image (:func:`diffcam.io.normalise_l2`), the 3-D solver's
``tau = 6e-4`` for raw counts minus the bias. The estimate is returned in the units of
``image / psf`` (so ``A x ≈ b`` with the PSF as given); the objective history is in
units of the image squared, for the normalised PSF.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
from jax.scipy.fft import dct, idct
from jaxtyping import ArrayLike

from diffcam.core.backend import irfft2, rfft2

from diffcam.core.errors import DiffcamError, is_concrete
from diffcam.core.progress import progress_bar
from diffcam.core.grid import crop_to, pad_to
from diffcam.reconstruct.checks import (as_psf_stack, batch_shape, check_image,
                                        check_iterations, check_psf, check_tol,
                                        float_dtype)
from diffcam.reconstruct.loop import Reconstruction, iterate, relative_residual
from diffcam.reconstruct.operators import convolution_model, divergence, gradient

__all__ = ["admm_tv", "admm_tv_3d"]

_AXES = (-2, -1)
_BOUNDARIES = ("crop", "circular")


def admm_tv(image: ArrayLike, psf: ArrayLike, iterations: int = 100, *,
            mu1: float = 1e-6, mu2: float = 1e-5, mu3: float = 4e-5, tau: float = 1e-4,
            boundary: str = "crop", tol: float | None = None,
            progress: bool = True) -> Reconstruction:
    """DiffuserCam ADMM-TV reconstruction of a 2-D scene from one sensor image.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (``iterations=1`` is enough) to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image (background subtracted; may hold small
            negatives).
        psf: ``(..., my, mx)`` PSF, non-negative, ``my <= ny``, ``mx <= nx``; leading axes
            broadcast with the image's.
        iterations: iterations (static). The DiffuserCam tutorial shows 5; 50–200 converge
            much further.
        mu1, mu2, mu3: ADMM penalties of the splits ``x = Hv``, ``u = Ψv``, ``w = v``
            (defaults from the DiffuserCam tutorial).
        tau: TV weight, in the image's units (1e-4 for an L2-normalised image).
        boundary: ``"crop"`` (the sensor sees the centre of the full convolution; the
            estimate is on the larger object grid) or ``"circular"``.
        tol: stop early when the objective changes by less than ``tol`` (relative).
        progress: a progress bar for runs over 2 s (:mod:`diffcam.core.progress`).

    Returns:
        :class:`Reconstruction`; ``image`` is the non-negative split variable ``w``,
        ``(..., oy, ox)``.
    """
    return _admm(image, psf, iterations, mu1=mu1, mu2=mu2, mu3=mu3, tau=tau,
                 boundary=boundary, tol=tol, volume=False, tv_axial=False,
                 progress=progress)


def admm_tv_3d(image: ArrayLike, psf_stack: ArrayLike, iterations: int = 100, *,
               mu1: float = 1e-3, mu2: float = 1e-3, mu3: float = 1e-3, tau: float = 6e-4,
               tv_axial: bool = True, boundary: str = "crop",
               tol: float | None = None, progress: bool = True) -> Reconstruction:
    """DiffuserCam ADMM-TV reconstruction of a volume: ``b = crop(Σ_z h_z * v_z)``.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (``iterations=1`` is enough) to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image.
        psf_stack: ``(..., nz, my, mx)`` PSFs, one per depth, on one common scale, or a
            list of ``(my, mx)`` arrays.
        tv_axial: include differences along depth in the TV (3-D TV, as DiffuserCam).
        iterations, mu1, mu2, mu3, tau, boundary, tol, progress: as for
            :func:`admm_tv`. Defaults
            measured on the shipped DiffuserCam 3-D capture (raw counts minus the bias,
            binned 2×, 40 iterations): the tilted USAF target's depth ramps steadily
            across it (tests/test_real_data.py); ``tau`` = 6e-4 is DiffuserCam's 3-D TV
            weight for raw counts minus the bias. (The 2-D tutorial's μ = 1e-6/1e-5/4e-5
            leave the 3-D target unresolved.)

    Returns:
        :class:`Reconstruction` with ``image`` the volume ``(..., nz, oy, ox)``.
    """
    return _admm(image, as_psf_stack(psf_stack), iterations, mu1=mu1, mu2=mu2, mu3=mu3,
                 tau=tau, boundary=boundary, tol=tol, volume=True, tv_axial=tv_axial,
                 progress=progress)


def _admm(image, psf, iterations, *, mu1, mu2, mu3, tau, boundary, tol, volume, tv_axial,
          progress):
    if boundary not in _BOUNDARIES:
        raise DiffcamError(f"ADMM supports boundary in {_BOUNDARIES}, got {boundary!r}; "
                           f"for a 'same'-size model use richardson_lucy.")
    iterations = check_iterations(iterations)
    check_tol(tol)
    check_image(image, nonnegative=False)
    core = 3 if volume else 2
    check_psf(psf, jnp.shape(image), min_ndim=core)
    for name, value in (("mu1", mu1), ("mu2", mu2), ("mu3", mu3)):
        if is_concrete(value) and not 0 < float(value) < math.inf:
            raise DiffcamError(f"{name} must be a finite number > 0, got {value!r}; "
                               f"DiffuserCam uses mu1=1e-6, mu2=1e-5, mu3=4e-5.")
    if is_concrete(tau) and not 0 <= float(tau) < math.inf:
        raise DiffcamError(f"tau must be a finite number >= 0, got {tau!r}.")
    if is_concrete(image) and float(jnp.sum(jnp.asarray(image) ** 2)) == 0:
        raise DiffcamError("image is all zeros: there is nothing to reconstruct.")
    batch = batch_shape(jnp.shape(image), jnp.shape(psf), core)
    dtype = float_dtype(image, psf)
    image = jnp.broadcast_to(jnp.asarray(image, dtype), batch + jnp.shape(image)[-2:])
    psf = jnp.broadcast_to(jnp.asarray(psf, dtype), batch + jnp.shape(psf)[-core:])
    if not volume:
        psf = psf[..., None, :, :]
    flat = lambda a, k: a.reshape((-1,) + a.shape[a.ndim - k:])  # noqa: E731
    penalties = jnp.asarray([mu1, mu2, mu3, tau], dtype)
    with progress_bar(iterations, "ADMM-TV", progress):
        out = jax.block_until_ready(_admm_batched(
            flat(image, 2), flat(psf, 3), penalties,
            None if tol is None else jnp.asarray(tol, dtype),
            iterations=iterations, boundary=boundary, tv_axial=tv_axial))
    if not volume:
        out = out._replace(image=out.image[:, 0])
    return jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), out)


@partial(jax.jit, static_argnames=("iterations", "boundary", "tv_axial"))
def _admm_batched(image, psf, penalties, tol, *, iterations, boundary, tv_axial):
    def one(b, h):
        return _admm_solve(b, h, penalties, tol, iterations=iterations, boundary=boundary,
                           tv_axial=tv_axial)
    return jax.vmap(one)(image, psf)


def _tv(v, axial):
    """Ψ v: ``(2 or 3, nz, oy, ox)`` lateral circular and axial Neumann differences."""
    g = gradient(v)
    if not axial:
        return g
    dz = jnp.concatenate([v[1:] - v[:-1], jnp.zeros_like(v[:1])], axis=0)
    return jnp.concatenate([g, dz[None]], axis=0)


def _tv_adjoint(g, axial):
    """Ψᵀ g."""
    out = -divergence(g[:2])
    if axial:
        dz = g[2, :-1]
        out = out + jnp.pad(dz, [(1, 0), (0, 0), (0, 0)]) - jnp.pad(dz, [(0, 1), (0, 0), (0, 0)])
    return out


def _admm_solve(b, psf, penalties, tol, *, iterations, boundary, tv_axial):
    """One problem: ``b (ny, nx)``, ``psf (nz, my, mx)``; everything on the object grid."""
    mu1, mu2, mu3, tau = penalties
    h_norm = jnp.linalg.norm(psf)
    model = convolution_model(psf / h_norm, b.shape, boundary, volume=True)
    otf, grid = model.otf, model.fft_shape                  # (nz, fy, fxr), (fy, fx)
    nz = psf.shape[0]
    axial = tv_axial and nz > 1

    v_solve = _v_solver(otf, grid, axial, (mu1, mu2, mu3), b.dtype)

    if boundary == "crop":
        crop_mask = pad_to(jnp.ones_like(b), grid)
        data = pad_to(b, grid)
    else:
        crop_mask = jnp.ones_like(b)
        data = b
    rfft = rfft2
    irfft = lambda a: irfft2(a, s=grid)       # noqa: E731

    def step(state):
        v, hv, tv_v, w, xi, eta, rho = state
        # misfit and objective of the current v, from quantities already at hand
        predicted = crop_to(hv, b.shape)
        residual = relative_residual(predicted, b)
        objective = 0.5 * jnp.sum((predicted - b) ** 2) + tau * jnp.sum(jnp.abs(tv_v))
        u = _soft(tv_v + eta / mu2, tau / mu2)
        x = (data + mu1 * hv + xi) / (crop_mask + mu1)
        w = jnp.maximum(v + rho / mu3, 0)
        rhs = (jnp.conj(otf) * rfft(mu1 * x - xi)[None]
               + rfft(_tv_adjoint(mu2 * u - eta, axial) + mu3 * w - rho))
        v_spec = v_solve(rhs)
        v = irfft(v_spec)
        hv = irfft(jnp.sum(otf * v_spec, axis=0))
        tv_v = _tv(v, axial)
        xi = xi + mu1 * (hv - x)
        eta = eta + mu2 * (tv_v - u)
        rho = rho + mu3 * (v - w)
        return (v, hv, tv_v, w, xi, eta, rho), (residual, objective)

    v0 = jnp.zeros((nz,) + grid, b.dtype)
    plane = jnp.zeros(grid, b.dtype)
    tv0 = _tv(v0, axial)
    state = (v0, plane, tv0, v0, plane, tv0, v0)
    state, res, obj, its, done = iterate(step, state, iterations, tol)
    v, _, _, _, _, _, rho = state
    estimate = jnp.maximum(v + rho / mu3, 0) / h_norm
    return Reconstruction(image=estimate, residual=res, objective=obj, iterations=its,
                          converged=done)


def _v_solver(otf, grid, axial, mu, dtype):
    """r ↦ (mu1 HᵀH + mu2 ΨᵀΨ + mu3)⁻¹ r on lateral spectra ``(nz, fy, fxr)``.

    ΨᵀΨ is diagonal under the 2-D DFT (lateral circular differences) and the orthonormal
    DCT-II over depth (axial Neumann differences); HᵀH couples the depths through one
    rank-one term per frequency, inverted by Sherman–Morrison.
    """
    mu1, mu2, mu3 = mu
    nz = otf.shape[0]
    ky = 2 * jnp.pi * jnp.fft.fftfreq(grid[0])[:, None]
    kx = 2 * jnp.pi * jnp.fft.rfftfreq(grid[1])[None, :]
    lateral = (4 - 2 * jnp.cos(ky) - 2 * jnp.cos(kx)).astype(dtype)
    if axial:
        axial_eig = (2 - 2 * jnp.cos(jnp.pi * jnp.arange(nz) / nz)).astype(dtype)
        diag = mu2 * (lateral + axial_eig[:, None, None]) + mu3     # (nz, fy, fxr)
    else:
        diag = mu2 * lateral + mu3                                    # (fy, fxr)

    def diag_solve(r):
        """(mu2 ΨᵀΨ + mu3)⁻¹ r."""
        if not axial:
            return r / diag
        return idct(dct(r, axis=0, norm="ortho") / diag, axis=0, norm="ortho")

    dinv_g = diag_solve(jnp.conj(otf))
    coupling = 1 + mu1 * jnp.real(jnp.sum(otf * dinv_g, axis=0))   # (fy, fxr)

    def v_solve(r):
        t = diag_solve(r)
        return t - dinv_g * (mu1 * jnp.sum(otf * t, axis=0) / coupling)

    return v_solve


def _soft(x, threshold):
    """Soft thresholding, the proximal map of ``threshold·|x|``."""
    return jnp.sign(x) * jnp.maximum(jnp.abs(x) - threshold, 0)
