"""The sensor's side of the ADMM data term ``½ ||S ⊙ C H v + B c - b||²``
(`diffcam.reconstruct.admm`): the sensor response ``S`` and a smooth background
``B c``.

``S`` is a fixed, non-negative ``(ny, nx)`` array: the fraction of the light a pixel
records, relative to the PSF calibration's (1 everywhere: the PSFs as measured). A
window fixed on the sensor, the same for every scene point, is the limit of a scene
that sends its light over a narrower range of angles than the calibration's point
source (docs/volume.md). `diffcam.io.fit_sensor_window` fits a vertical Gaussian
``S(y)`` to a capture.

``B`` holds the 2-D Legendre polynomials of total degree ``<= background`` over the
sensor (`legendre_terms`), orthonormalised on its pixels; ``c`` is free (either sign).
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from diffcam.core.errors import DiffcamError, ShapeError, is_concrete, real_array

__all__ = ["MAX_BACKGROUND_DEGREE", "check_sensor_response", "sensor_split",
           "legendre_terms", "smooth_background"]

MAX_BACKGROUND_DEGREE = 8
"""Highest degree of `AdmmOptions.background` (45 polynomials)."""


def check_sensor_response(response: ArrayLike | None, sensor_shape: Sequence[int],
                          dtype) -> jax.Array | None:
    """``response`` broadcast to the sensor ``(ny, nx)`` in ``dtype``, after checking that
    it is real, finite, non-negative and not all zero (``None`` stays ``None``)."""
    if response is None:
        return None
    real_array("sensor_response", response)
    shape, sensor_shape = np.shape(response), tuple(int(n) for n in sensor_shape[-2:])
    if len(shape) > 2 or any(n not in (1, m) for n, m in zip(shape[::-1],
                                                            sensor_shape[::-1])):
        raise ShapeError(f"sensor_response must broadcast to the sensor {sensor_shape} "
                         f"(e.g. ({sensor_shape[0]}, 1) for a response along y), got "
                         f"shape {shape}.")
    if is_concrete(response):
        values = np.asarray(response, np.float64)
        if not np.isfinite(values).all() or values.min() < 0 or not values.max() > 0:
            raise DiffcamError("sensor_response is the fraction of the light each pixel "
                               "records: finite, >= 0 and not all zero; got values from "
                               f"{values.min():.3g} to {values.max():.3g}.")
    return jnp.broadcast_to(jnp.asarray(response, dtype), sensor_shape)


def sensor_split(mask, residual, hv, xi, mu1):
    """The ADMM update of the split ``x = H v`` (DiffuserCam's crop variable) on the FFT
    grid: ``argmin_x ½ ||S ⊙ C x - r||² + μ1/2 ||H v - x + ξ/μ1||²``, pixel-wise
    ``x = (CᵀS r + μ1 H v + ξ) / (CᵀS²C + μ1)``; ``mask`` is ``CᵀS`` (``S`` padded with
    zeros: 0 off the sensor), ``residual`` ``Cᵀr`` (``r`` the image less any
    background)."""
    return (mask * residual + mu1 * hv + xi) / (mask ** 2 + mu1)


def legendre_terms(shape: tuple, degree: int) -> tuple[np.ndarray, list]:
    """The background's polynomials: ``P_i(y) P_j(x)`` for ``i + j <= degree``, with
    ``y``, ``x`` mapped to [-1, 1] over an image of ``shape`` (pixels).

    Returns:
        ``(k, ny, nx)`` float64 images and the ``k`` pairs ``(i, j)``.
    """
    y = np.polynomial.legendre.legvander(np.linspace(-1, 1, shape[0]), degree)
    x = np.polynomial.legendre.legvander(np.linspace(-1, 1, shape[1]), degree)
    pairs = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]
    return np.stack([np.outer(y[:, i], x[:, j]) for i, j in pairs]), pairs


class SmoothBackground(NamedTuple):
    """A smooth background on the sensor, ``B c``: ``basis`` holds the ``(k, ny, nx)``
    orthonormal images spanning it (``k = 0``: no background)."""

    basis: jax.Array

    def fit(self, r):
        """The background closest to ``r`` (``B Bᵀ r``, the least-squares fit)."""
        return jnp.tensordot(jnp.tensordot(self.basis, r, 2), self.basis, 1)

    def fit_joint(self, r, response, mu1):
        """The background of the ADMM ``x`` update: ``B c`` minimising
        ``min_x ½ ||S ⊙ x + B c - b||² + μ1/2 ||x - z||²`` for ``r = b - S ⊙ z``, the
        fit of ``B`` to ``r`` weighted by ``W = μ1 / (S² + μ1)``,
        ``(Bᵀ W B) c = Bᵀ W r`` (the plain fit for ``response`` None: ``S = 1``)."""
        if response is None:
            return self.fit(r)
        if self.basis.shape[0] == 0:
            return jnp.zeros_like(r)
        weighted = self.basis * (mu1 / (response ** 2 + mu1))
        gram = jnp.tensordot(weighted, self.basis, ((1, 2), (1, 2)))
        c = jnp.linalg.solve(gram, jnp.tensordot(weighted, r, 2))
        return jnp.tensordot(c, self.basis, 1)


def smooth_background(shape, degree, dtype) -> SmoothBackground:
    """`legendre_terms` of ``degree`` (``None``: none) orthonormalised on the pixels of
    a sensor of ``shape``."""
    if degree is None:
        return SmoothBackground(jnp.zeros((0,) + tuple(shape), dtype))
    terms = legendre_terms(shape, degree)[0]
    q = np.linalg.qr(terms.reshape(len(terms), -1).T)[0]
    return SmoothBackground(jnp.asarray(q.T.reshape((-1,) + tuple(shape)), dtype))
