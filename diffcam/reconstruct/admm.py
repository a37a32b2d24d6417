"""ADMM with total variation for the DiffuserCam crop model (Antipa et al., Optica 5,
1, 2018), in 2-D and for a PSF stack (3-D).

The problem, for a sensor image ``b``, crop ``C`` and convolution ``H`` (the sum over
depths for a volume)::

    min_v  ½ ||C H v - b||²  +  tau ||Ψ v||₁  +  sparsity ||v||₁    subject to  v >= 0

with ``Ψ`` anisotropic finite differences: circular along y and x (diagonal under the
FFT, as in the DiffuserCam reference), and, for a volume, ``tau_axial / tau`` times the
Neumann (non-periodic) differences along depth (diagonal under the DCT-II). ADMM splits
``x = H v`` (so the crop is a pixel-wise division), ``u = Ψ v`` (soft threshold) and
``w = v`` (projection onto ``w >= 0``, shifted by the L1 weight), with penalties
``mu1``, ``mu2``, ``mu3`` (fixed, or adapted by residual balancing) and unscaled duals,
optionally over-relaxed (``relaxation``).
The ``v`` update solves ``(mu1 HᵀH + mu2 ΨᵀΨ + mu3) v = r`` exactly: per lateral
frequency, ``HᵀH`` over depth is the rank-one ``conj(h) hᵀ``, so Sherman–Morrison
turns it into divisions by the diagonal of the TV-and-identity part. The OTF stack is
taken into the DCT basis once; the DCT of each iterate along depth is a product with
the ``(nz, nz)`` DCT matrix applied to real volumes (one each way per iteration), so an
iteration costs one real FFT pair of the stack, one of a plane, and element-wise work.

With a ``sensor_response`` ``S`` (`diffcam.reconstruct.sensor_terms`: the fraction of
the light each pixel records, relative to the PSF calibration's) the data term is
``½ ||S ⊙ C H v - b||²`` and the ``x`` update stays a pixel-wise division,
``x = (CᵀS b + μ1 H v + ξ) / (CᵀS²C + μ1)``. With ``background`` (a polynomial degree),
the data term is ``½ ||S ⊙ C H v + B c - b||²`` with ``B`` smooth polynomials on the
sensor and ``c`` free; the ``x = Hv`` update then minimises over ``x`` and ``c``
together, which leaves for ``c`` the least-squares fit of ``B`` to
``b - S ⊙ C(Hv + ξ/μ1)``, weighted by ``μ1 / (S² + μ1)`` (unweighted without ``S``).

A field-dependent model (`FieldModel`) in place of
the PSF has no ``HᵀH`` diagonal in any basis, so its ``v`` update is *linearised*
(Yang & Yuan, Math. Comp. 82, 301, 2013): ``mu1 HᵀH`` is replaced by ``mu1 L`` with
``L >= ||H||²`` plus the data term's gradient at the previous iterate,
``(mu1 L + mu2 ΨᵀΨ + mu3) v = mu1 L v_k - Hᵀ(mu1 H v_k - mu1 x + ξ) + rest``, diagonal in
the same basis. An iteration costs one application of ``H`` and one of ``Hᵀ`` (each
``K + 1`` FFTs) and a real FFT pair of the volume. It converges to the same problem's
solution, in more iterations than the exact update for a shift-invariant model. The
model's scale is that of the PSF at the centre of its field (the whole stack's norm in
3-D), and ``L`` is the power iteration's ``||H||²`` times 1.1.

The solvers return the non-negative split variable ``w``; ``final_residual`` and
``final_objective`` are those of ``w`` itself, and ``split_gap`` is ``||v - w|| / ||w||``
(the residual history is that of the iterates ``v``, which fit the data more closely
than ``w`` until the split has closed).

Scaling: like the DiffuserCam code (2-D tutorial and 3-D solver), the PSF (the whole
stack for a volume) is divided by its L2 norm, so the penalties ``mu1..mu3`` do not
depend on the PSF's units nor on the image's (every term of the augmented Lagrangian
scales with ``||b||²``); the weights ``tau``, ``tau_axial``, ``sparsity`` scale with the
image: the tutorial's ``tau = 1e-4`` and `VOLUME`'s weights are for an
L2-normalised image (`diffcam.io.normalise_l2`), the DiffuserCam 3-D solver's
``tau = 6e-4`` for raw counts minus the bias. Inside, the image is divided by its L2
norm too and the weights with it (every iterate is then the same up to that factor), so
a faint (1e-25) or bright (1e30) image computes in float32 without a square under- or
overflowing. The estimate is returned in the units of ``image / psf`` (so ``A x ≈ b``
with the PSF as given); the objective history is in units of the image squared, for
the normalised PSF.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike

from diffcam.core.backend import irfft2, rfft2
from diffcam.core.errors import DiffcamError, is_concrete, real_number
from diffcam.core.grid import crop_to, pad_to
from diffcam.core.options import Options
from diffcam.core.progress import progress_bar
from diffcam.reconstruct.checks import (as_psf_stack, batch_shape, check_image,
                                        check_iterations, check_operator, check_psf,
                                        check_scale,
                                        check_tol, float_dtype)
from diffcam.reconstruct.loop import Reconstruction, iterate, relative_residual
from diffcam.reconstruct.operators import (FieldModel, convolution_model, divergence,
                                           gradient, operator_norm)
from diffcam.reconstruct.sensor_terms import (MAX_BACKGROUND_DEGREE,
                                              check_sensor_response, sensor_split,
                                              smooth_background)

__all__ = ["AdmmOptions", "TUTORIAL_2D", "VOLUME", "admm_tv", "admm_tv_3d"]
_AXES = (-2, -1)
_BOUNDARIES = ("crop", "circular")


class AdmmOptions(Options):
    """Settings of the ADMM-TV solvers ([`admm_tv`][diffcam.reconstruct.admm.admm_tv],
    [`admm_tv_3d`][diffcam.reconstruct.admm.admm_tv_3d]).

    The PSF is divided by its L2 norm inside the solver, so the penalties ``mu1..mu3``
    are dimensionless; the weights ``tau``, ``tau_axial`` and ``sparsity`` are in the
    image's units (scale them with the image, or give an L2-normalised image).

    Attributes:
        mu1, mu2, mu3: penalties of the splits ``x = Hv``, ``u = Ψv``, ``w = v`` (the
            starting values when ``balance`` is on).
        tau: weight of the lateral TV (differences along y and x).
        tau_axial: weight of the axial TV (differences along depth; volumes only).
            ``None``: equal to ``tau`` (isotropic 3-D TV, as DiffuserCam); 0: the
            planes are coupled only through the data.
        sparsity: weight of ``||v||₁`` (with ``v >= 0``, a constant pull towards 0 that
            empties planes whose light another plane explains as well).
        balance: adapt ``mu1..mu3`` by residual balancing (Boyd et al., Found. Trends
            Mach. Learn. 3, 2011, §3.4.1: a penalty doubles when its primal residual
            exceeds 10× its dual residual, halves in the opposite case), so that the
            splits close whatever the image's scale.
        boundary: ``"crop"`` (the sensor sees the centre of the full convolution; the
            estimate is on the larger object grid) or ``"circular"``.
        tol: stop early when the objective changes by less than ``tol`` (relative).
        background: degree of a smooth background on the sensor solved jointly with
            the scene: the data term becomes ``½ ||C H v + B c - b||²`` with ``B`` the
            2-D Legendre polynomials of total degree ``<= background`` over the sensor
            (unpenalised, either sign: ambient or scattered light, a dark-level
            gradient); ``None``: no background.
        relaxation: over-relaxation ``α`` in (0, 2) (Boyd et al. 2011, §3.4.3): the
            ``v`` update and the dual updates see the splits as ``α s + (1 - α) K v``
            (``s = (x, u, w)`` just updated, ``K v = (Hv, Ψv, v)`` the previous
            iterate's); 1 is plain ADMM, 1.5–1.8 usually converges in fewer
            iterations. The solution is the same for every ``α``.
    """

    mu1: float = 1e-3
    mu2: float = 1e-3
    mu3: float = 1e-3
    tau: float = 6e-4
    tau_axial: float | None = None
    sparsity: float = 0.0
    balance: bool = False
    boundary: str = "crop"
    tol: float | None = None
    background: int | None = None
    relaxation: float = 1.0

    def __check_init__(self):
        if self.boundary not in _BOUNDARIES:
            raise DiffcamError(f"ADMM supports boundary in {_BOUNDARIES}, got "
                               f"{self.boundary!r}; for a 'same'-size model use "
                               f"richardson_lucy.")
        check_tol(self.tol)
        if self.background is not None and not (
                isinstance(self.background, int)
                and 0 <= self.background <= MAX_BACKGROUND_DEGREE):
            raise DiffcamError(f"background is a polynomial degree from 0 to "
                               f"{MAX_BACKGROUND_DEGREE} (or None), got {self.background!r}.")
        for name in ("mu1", "mu2", "mu3"):
            value = getattr(self, name)
            if is_concrete(value) and not 0 < real_number(name, value, "a number > 0") \
                    < math.inf:
                raise DiffcamError(f"{name} must be a finite number > 0, got {value!r}; "
                                   f"DiffuserCam uses mu1=1e-6, mu2=1e-5, mu3=4e-5.")
        if is_concrete(self.relaxation) and not 0 < real_number(
                "relaxation", self.relaxation, "a number in (0, 2)") < 2:
            raise DiffcamError(f"relaxation must be in (0, 2) (1: plain ADMM; 1.5-1.8 "
                               f"over-relaxes), got {self.relaxation!r}.")
        for name in ("tau", "tau_axial", "sparsity"):
            value = getattr(self, name)
            if value is not None and is_concrete(value) and not 0 <= real_number(
                    name, value, "a number >= 0") < math.inf:
                raise DiffcamError(f"{name} must be a finite number >= 0, got {value!r}.")

    def weights(self) -> tuple:
        """``(tau, tau_axial, sparsity)`` with ``tau_axial`` resolved."""
        axial = self.tau if self.tau_axial is None else self.tau_axial
        return self.tau, axial, self.sparsity


TUTORIAL_2D = AdmmOptions(mu1=1e-6, mu2=1e-5, mu3=4e-5, tau=1e-4)
"""The DiffuserCam 2-D tutorial's settings, `admm_tv`'s defaults (for an
L2-normalised image)."""

VOLUME = AdmmOptions(mu1=0.5, mu2=0.25, mu3=0.5, tau=1e-5, tau_axial=2e-6, sparsity=2e-5,
                     balance=True, relaxation=1.85)
"""Settings for a volume from a capture scaled to unit L2 norm, chosen by measurement
on the shipped DiffuserCam 3-D capture (docs/volume.md, ``benchmarks/bench_3d.py``,
``benchmarks/bench_3d_convergence.py``):
lateral TV 1e-5, a five times weaker axial TV (isotropic 3-D TV smears the tilted
target into axial blocks), an L1 pull of 2e-5 (it empties the haze planes), residual
balancing from the penalties it settles at on that capture (0.5, 0.25, 0.5), and
over-relaxation 1.85. ``diffcam reconstruct --3d`` uses them."""


def admm_tv(image: ArrayLike, psf: ArrayLike, iterations: int = 100,
            options: AdmmOptions | None = None, *, progress: bool = True,
            sensor_response: ArrayLike | None = None, **overrides) -> Reconstruction:
    """DiffuserCam ADMM-TV reconstruction of a 2-D scene from one sensor image.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (``iterations=1`` is enough) to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image (background subtracted; may hold small
            negatives).
        psf: ``(..., my, mx)`` PSF, non-negative, ``my <= ny``, ``mx <= nx``; leading axes
            broadcast with the image's. Or a 2-D forward model
            (`FieldModel`, boundary ``"crop"`` or
            ``"circular"``) for the image's sensor (module docstring).
        iterations: iterations (static). The DiffuserCam tutorial shows 5; 50–200 converge
            much further.
        options: [`AdmmOptions`][diffcam.reconstruct.admm.AdmmOptions]; default
            `TUTORIAL_2D` (``tau = 1e-4`` is for an L2-normalised image); keywords named
            after its fields replace them.
        progress: a progress bar for runs over 2 s
            ([`diffcam.core.progress`][diffcam.core.progress]).
        sensor_response: ``S``, dimensionless, broadcasting to ``(ny, nx)``: the
            fraction of the light each pixel records, relative to the PSF
            calibration's; the model is ``b = S ⊙ C H v``
            (`diffcam.reconstruct.sensor_terms`).
            ``None``: 1 everywhere.

    Returns:
        [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction]; ``image`` is the
        non-negative split variable ``w``, ``(..., oy, ox)``.
    """
    options = AdmmOptions.of(options or TUTORIAL_2D, **overrides)
    return _admm(image, psf, iterations, options, sensor_response, volume=False,
                 progress=progress)


def admm_tv_3d(image: ArrayLike, psf_stack: ArrayLike, iterations: int = 100,
               options: AdmmOptions | None = None, *, progress: bool = True,
               sensor_response: ArrayLike | None = None, **overrides) -> Reconstruction:
    """DiffuserCam ADMM-TV reconstruction of a volume: ``b = S ⊙ crop(Σ_z h_z * v_z)``.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (``iterations=1`` is enough) to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image.
        psf_stack: ``(..., nz, my, mx)`` PSFs, one per depth, on one common scale, or a
            list of ``(my, mx)`` arrays; or a 3-D forward model
            (`FieldModel`).
        iterations: iterations (static).
        options: [`AdmmOptions`][diffcam.reconstruct.admm.AdmmOptions]; default
            ``AdmmOptions()``: DiffuserCam's 3-D settings (μ = 1e-3, isotropic 3-D TV with
            ``tau = 6e-4`` for raw counts minus the bias); keywords named after its fields
            replace them.
        progress: a progress bar for runs over 2 s
            ([`diffcam.core.progress`][diffcam.core.progress]).
        sensor_response: ``S`` as in [`admm_tv`][diffcam.reconstruct.admm.admm_tv]
            (e.g. `diffcam.io.SensorWindow.response`); ``None``: 1 everywhere.

    Returns:
        [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction] with ``image`` the
        volume ``(..., nz, oy, ox)`` and, with ``background``, ``background`` the fitted
        sensor background ``(..., ny, nx)`` in the image's units.
    """
    options = AdmmOptions.of(options, **overrides)
    return _admm(image, as_psf_stack(psf_stack), iterations, options, sensor_response,
                 volume=True, progress=progress)


def _admm(image, psf, iterations, options, response, *, volume, progress):
    iterations = check_iterations(iterations)
    check_image(image, nonnegative=False)
    core = 3 if volume else 2
    model = check_operator(psf, jnp.shape(image), volume=volume, boundaries=_BOUNDARIES,
                           solver="admm_tv" + ("_3d" if volume else ""))
    if model:
        batch, dtype = tuple(jnp.shape(image)[:-2]), float_dtype(image)
        if is_concrete(image, psf):
            check_scale(image, psf.centre_psf(), dtype)
        depth = psf.weights.shape[1] if volume else 1
        boundary = psf.boundary
    else:
        psf = check_psf(psf, jnp.shape(image), min_ndim=core)
        batch = batch_shape(jnp.shape(image), jnp.shape(psf), core)
        dtype = float_dtype(image, psf)
        if is_concrete(image) and is_concrete(psf):
            check_scale(image, psf, dtype)
        psf = jnp.broadcast_to(jnp.asarray(psf, dtype), batch + jnp.shape(psf)[-core:])
        if not volume:
            psf = psf[..., None, :, :]
        depth, boundary = psf.shape[-3], options.boundary
    image = jnp.broadcast_to(jnp.asarray(image, dtype), batch + jnp.shape(image)[-2:])
    response = check_sensor_response(response, jnp.shape(image), dtype)
    tau, tau_axial, sparsity = options.weights()
    axial = depth > 1 and not (is_concrete(tau_axial) and float(tau_axial) == 0)
    flat = lambda a, k: a.reshape((-1,) + a.shape[a.ndim - k:])  # noqa: E731
    settings = jnp.asarray([options.mu1, options.mu2, options.mu3, tau, tau_axial,
                            sparsity, options.relaxation], dtype)
    tol = None if options.tol is None else jnp.asarray(options.tol, dtype)
    with progress_bar(iterations, "ADMM-TV", progress):
        out = jax.block_until_ready(_admm_batched(
            flat(image, 2), psf if model else flat(psf, 3), response, settings, tol,
            iterations=iterations, boundary=boundary, axial=axial,
            balance=bool(options.balance), background=options.background))
    if not volume:
        out = out._replace(image=out.image[:, 0])
    return jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), out)


@partial(jax.jit, static_argnames=("iterations", "boundary", "axial", "balance",
                                   "background"))
def _admm_batched(image, psf, response, settings, tol, *, iterations, boundary, axial,
                  balance, background):
    """One problem per image; ``psf`` is a batch of PSF stacks or one forward model;
    ``response`` the sensor response shared by all (or None)."""
    def one(b, h):
        return _admm_solve(b, h, response, settings, tol, iterations=iterations,
                           boundary=boundary, axial=axial, balance=balance,
                           background=background)
    return jax.vmap(one, in_axes=(0, None if isinstance(psf, FieldModel) else 0))(image, psf)


def safe_norm(a, axis=None, keepdims: bool = False):
    """``||a||₂`` over ``axis`` (all axes by default) without overflow or underflow of
    the squares: ``m·||a/m||`` with ``m = max|a|`` (1 where ``a`` is zero)."""
    m = jnp.max(jnp.abs(a), axis=axis, keepdims=True)
    m = jnp.where(m > 0, m, 1)
    norm = m * jnp.sqrt(jnp.sum((a / m) ** 2, axis=axis, keepdims=True))
    return norm if keepdims else jnp.squeeze(norm, axis)


def _tv(v, a):
    """Ψ v: lateral circular differences and, for ``a`` not None, ``a`` times the axial
    Neumann differences: ``(2 or 3, nz, oy, ox)``."""
    g = gradient(v)
    if a is None:
        return g
    dz = jnp.concatenate([v[1:] - v[:-1], jnp.zeros_like(v[:1])], axis=0)
    return jnp.concatenate([g, a * dz[None]], axis=0)


def _tv_adjoint(g, a):
    """Ψᵀ g."""
    out = -divergence(g[:2])
    if a is not None:
        dz = a * g[2, :-1]
        out = out + jnp.pad(dz, [(1, 0), (0, 0), (0, 0)]) - jnp.pad(dz, [(0, 1), (0, 0), (0, 0)])
    return out


def _dct_matrix(n, dtype):
    """The orthonormal DCT-II as an ``(n, n)`` matrix: it diagonalises the Neumann
    second difference along depth (eigenvalues ``2 - 2cos(πk/n)``). Applied by a
    matrix product, which on a CPU costs a fraction of an FFT-based DCT along a
    leading axis."""
    k = jnp.arange(n)[:, None]
    z = jnp.arange(n)[None, :]
    c = jnp.sqrt(2 / n) * jnp.cos(jnp.pi * k * (2 * z + 1) / (2 * n))
    return c.at[0].multiply(1 / jnp.sqrt(2)).astype(dtype)


class _Basis(NamedTuple):
    """The volume's spectral basis: lateral real FFT, and along depth the orthonormal
    DCT-II (with axial TV) or nothing. ``otf`` is the PSF stack's OTF in that basis;
    ``eig`` the eigenvalues of ΨᵀΨ."""

    otf: jax.Array | None    # (nz, fy, fxr) complex; None for a linearised data term
    eig: jax.Array           # (nz or 1, fy, fxr) real
    dct: jax.Array | None    # (nz, nz) or None
    grid: tuple

    def forward(self, v):
        """Real volume → its spectrum in the basis."""
        return rfft2(v if self.dct is None else jnp.tensordot(self.dct, v, 1))

    def inverse(self, spectrum):
        """Spectrum in the basis → real volume."""
        v = irfft2(spectrum, s=self.grid)
        return v if self.dct is None else jnp.tensordot(self.dct.T, v, 1)

    def image(self, spectrum):
        """``H v`` on the FFT grid from ``v``'s spectrum (Σ_z h_z * v_z; the basis along
        depth is orthonormal, so the sum keeps its form)."""
        return irfft2(jnp.sum(self.otf * spectrum, axis=0), s=self.grid)


def _basis(otf, grid, a, dtype, nz=None) -> _Basis:
    """The basis of a model of ``nz`` planes (default: the OTF stack's) with OTF stack
    ``otf`` (None: not needed) and axial TV scale ``a`` (None: no axial TV)."""
    ky = 2 * jnp.pi * jnp.fft.fftfreq(grid[0])[:, None]
    kx = 2 * jnp.pi * jnp.fft.rfftfreq(grid[1])[None, :]
    lateral = (4 - 2 * jnp.cos(ky) - 2 * jnp.cos(kx)).astype(dtype)[None]
    if a is None:
        return _Basis(otf, lateral, None, grid)
    nz = otf.shape[0] if nz is None else nz
    dct = _dct_matrix(nz, dtype)
    axial_eig = (2 - 2 * jnp.cos(jnp.pi * jnp.arange(nz) / nz)).astype(dtype)
    return _Basis(None if otf is None else jnp.tensordot(dct, otf, 1),
                  lateral + a ** 2 * axial_eig[:, None, None], dct, grid)


class _ExactData(NamedTuple):
    """The data term of a shift-invariant model: ``v`` solved exactly (`_v_update`)."""

    basis: _Basis

    def solve(self, d, rest, mu, v, hv):
        """``v`` from ``(mu1 HᵀH + mu2 ΨᵀΨ + mu3) v = Hᵀ d + rest``, and ``H v``."""
        return _v_update(self.basis, rfft2(d), rest, mu)

    def blur(self, v):
        """``H v`` on the FFT grid."""
        return self.basis.image(self.basis.forward(v))


class _LinearisedData(NamedTuple):
    """The data term of a field-dependent model (module docstring): ``H`` and ``Hᵀ``
    on the FFT grid, ``L >= ||H||²``."""

    basis: _Basis
    forward: object
    adjoint: object
    lipschitz: jax.Array

    def solve(self, d, rest, mu, v, hv):
        """``v`` from ``(mu1 L + mu2 ΨᵀΨ + mu3) v = mu1 L v_k - Hᵀ(mu1 H v_k - d) + rest``
        and ``H v``."""
        mu1, mu2, mu3 = mu
        step = mu1 * self.lipschitz
        rhs = step * v - self.adjoint(mu1 * hv - d) + rest
        v = self.basis.inverse(self.basis.forward(rhs) / (step + mu2 * self.basis.eig + mu3))
        return v, self.forward(v)

    def blur(self, v):
        return self.forward(v)


def _linearised(model: FieldModel, a, dtype):
    """The data term of ``model`` scaled by its centre PSF's norm (the volume's in
    3-D): ``(data term, that norm)``."""
    h_norm = safe_norm(model.centre_psf())
    if model.volume:
        forward = lambda v: model.blur(v) / h_norm  # noqa: E731
        adjoint = lambda y: model.blur_adjoint(y) / h_norm  # noqa: E731
    else:
        forward = lambda v: model.blur(v[0]) / h_norm  # noqa: E731
        adjoint = lambda y: model.blur_adjoint(y)[None] / h_norm  # noqa: E731
    nz = model.weights.shape[1] if model.volume else 1
    start = jnp.ones((nz,) + model.object_shape, dtype)
    lipschitz = 1.1 * operator_norm(forward, adjoint, start) ** 2
    basis = _basis(None, model.fft_shape, a, dtype, nz)
    return _LinearisedData(basis, forward, adjoint, lipschitz), h_norm


def _planes(psf) -> int:
    """Depth planes of a PSF stack ``(nz, my, mx)`` or of a forward model."""
    if isinstance(psf, FieldModel):
        return psf.weights.shape[1] if psf.volume else 1
    return psf.shape[0]


def _data_term(psf, b, boundary, a):
    """The data term of one problem and the scale it divides the model by: the exact
    one for a PSF stack ``(nz, my, mx)``, the linearised one for a forward model."""
    if isinstance(psf, FieldModel):
        return _linearised(psf, a, b.dtype)
    h_norm = safe_norm(psf)
    model = convolution_model(psf / h_norm, b.shape, boundary, volume=True)
    return _ExactData(_basis(model.otf, model.fft_shape, a, b.dtype)), h_norm


def _v_update(basis, data_spectrum, rest, mu):
    """Solve ``(mu1 HᵀH + mu2 ΨᵀΨ + mu3) v = Hᵀ d + rest`` for ``v``; ``data_spectrum``
    is the lateral spectrum of ``d`` (one plane). Per lateral frequency HᵀH is the
    rank-one ``conj(h) hᵀ`` over depth and ΨᵀΨ is diagonal in the basis, so
    Sherman–Morrison solves it exactly. Returns ``(v, H v)`` on the FFT grid."""
    mu1, mu2, mu3 = mu
    otf = basis.otf
    diag = mu2 * basis.eig + mu3
    t = (jnp.conj(otf) * data_spectrum[None] + basis.forward(rest)) / diag
    coupling = 1 + mu1 * jnp.sum(jnp.abs(otf) ** 2 / diag, axis=0)
    spectrum = t - jnp.conj(otf) / diag * (mu1 * jnp.sum(otf * t, axis=0) / coupling)
    return basis.inverse(spectrum), basis.image(spectrum)


def _balanced(mu, primal, dual):
    """Residual balancing: a penalty doubles when its primal residual exceeds 10× its
    dual residual and halves in the opposite case."""
    return jnp.where(primal > 10 * dual, 2 * mu, jnp.where(dual > 10 * primal, mu / 2, mu))


def _norm(a):
    return jnp.sqrt(jnp.sum(a ** 2))


def _on_sensor(z, response, shape):
    """``S ⊙ C z``: ``z`` cropped to the sensor, times the sensor response (if any)."""
    z = crop_to(z, shape)
    return z if response is None else response * z


def _admm_solve(b, psf, response, settings, tol, *, iterations, boundary, axial, balance,
                background):
    """One problem: ``b (ny, nx)``, ``psf (nz, my, mx)``, sensor response ``(ny, nx)``
    or None; everything on the object grid.
    With a ``background`` (polynomial degree), the ``x = Hv`` update minimises jointly
    over ``x`` and the background's coefficients: eliminating ``x`` leaves the
    weighted least-squares fit of the background to ``b - S C(Hv + ξ/μ1)``. The background
    returned is that fit at the last iterate, and ``final_residual`` is that of the
    volume returned plus it (the residual history: each iterate with its best
    background)."""
    # solved for the image and the PSF at unit L2 norm (the weights scaled alike), so
    # that no square under- or overflows; the estimate is scaled back at the end
    b_norm = safe_norm(b)
    b = b / b_norm
    tau, tau_axial, sparsity = settings[3] / b_norm, settings[4] / b_norm, settings[5] / b_norm
    alpha = settings[6]
    a = (tau_axial / jnp.where(tau > 0, tau, 1)) if axial else None
    data_term, h_norm = _data_term(psf, b, boundary, a)
    grid, nz = data_term.basis.grid, _planes(psf)
    sensor = (lambda a: pad_to(a, grid)) if boundary == "crop" else (lambda a: a)
    data = sensor(b)
    mask = sensor(jnp.ones_like(b) if response is None else response)    # CᵀS
    smooth = smooth_background(b.shape, background, b.dtype)

    on_sensor = partial(_on_sensor, response=response, shape=b.shape)
    def joint_background(z, mu1):     # minimising jointly with x, for z = Hv + ξ/μ1
        return smooth.fit_joint(b - on_sensor(z), response, mu1)

    def fit(v, hv, tv_v, bg):
        """Relative residual and objective of a volume with a sensor background."""
        predicted = on_sensor(hv) + bg
        objective = (0.5 * jnp.sum((predicted - b) ** 2) + tau * jnp.sum(jnp.abs(tv_v))
                     + sparsity * jnp.sum(v))
        return relative_residual(predicted, b), objective

    def step(state):
        v, hv, tv_v, xi, eta, rho, mu = state
        mu1, mu2, mu3 = mu
        u = _soft(tv_v + eta / mu2, tau / mu2)
        bg = sensor(joint_background(hv + xi / mu1, mu1))
        x = sensor_split(mask, data - bg, hv, xi, mu1)
        w = jnp.maximum(v + (rho - sparsity) / mu3, 0)
        splits = (x, u, w)          # relaxed below; the primal residuals use them as is
        x, u, w = (alpha * s + (1 - alpha) * k for s, k in zip(splits, (hv, tv_v, v)))
        rest = _tv_adjoint(mu2 * u - eta, a) + mu3 * w - rho
        v_new, hv_new = data_term.solve(mu1 * x - xi, rest, mu, v, hv)
        tv_new = _tv(v_new, a)
        primal = jnp.stack([_norm(k - s) for k, s in zip((hv_new, tv_new, v_new), splits)])
        dual = mu * jnp.stack([_norm(hv_new - hv), _norm(tv_new - tv_v), _norm(v_new - v)])
        xi = xi + mu1 * (hv_new - x)
        eta = eta + mu2 * (tv_new - u)
        rho = rho + mu3 * (v_new - w)
        mu = _balanced(mu, primal, dual) if balance else mu
        best = smooth.fit(b - on_sensor(hv))
        return (v_new, hv_new, tv_new, xi, eta, rho, mu), fit(v, hv, tv_v, best)

    v0 = jnp.zeros((nz,) + grid, b.dtype)
    plane = jnp.zeros(grid, b.dtype)
    tv0 = _tv(v0, a)
    state = (v0, plane, tv0, plane, tv0, v0, settings[:3])
    state, res, obj, its, done = iterate(step, state, iterations, tol)
    v, hv, _, xi, _, rho, mu = state
    w = jnp.maximum(v + (rho - sparsity) / mu[2], 0)
    bg = joint_background(hv + xi / mu[0], mu[0])      # the solve's background
    final_residual, final_objective = fit(w, data_term.blur(w), _tv(w, a), bg)
    fitted = None if background is None else bg * b_norm
    return Reconstruction(image=w * (b_norm / h_norm), residual=res,
                          objective=obj * b_norm ** 2, iterations=its,
                          converged=done, final_residual=final_residual,
                          final_objective=final_objective * b_norm ** 2,
                          split_gap=_norm(v - w) / jnp.maximum(_norm(w), 1e-30),
                          background=fitted)


def _soft(x, threshold):
    """Soft thresholding, the proximal map of ``threshold·|x|``."""
    return jnp.sign(x) * jnp.maximum(jnp.abs(x) - threshold, 0)
