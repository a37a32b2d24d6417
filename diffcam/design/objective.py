"""The depth-discrimination objective: PSFs of different depths should differ.

A diffuser discriminates depth when the PSFs of any two depths of the range are unlike;
the figure is the largest Pearson correlation (paper Eq. 14) between the PSFs of two
different depths,

    ρ_max = max_{i<j} P(h_i, h_j),   P(a, b) = ⟨â, b̂⟩,   â = (a − ā)/‖a − ā‖,

which the optimiser lowers through its smooth upper bound (log-sum-exp at temperature τ)

    ρ_τ = τ · log Σ_{i<j} exp(P(h_i, h_j)/τ),   ρ_max ≤ ρ_τ ≤ ρ_max + τ·log(#pairs),

whose gradient reaches every close pair, not only the worst one. Lowering correlation
alone could spread each PSF into a faint haze (two flat, noisy images correlate little):
the PSFs' spread, their L1/L2 ratio ‖h‖₁/(√N·‖h‖₂) (1 for a uniform image, 1/√N for a
single bright pixel; Miniscope3D asks for sparse, high-contrast PSFs), enters with a
weight:

    loss = ρ_τ + w · mean_z spread(h_z).

The PSFs are those of a point source and one wavelength unless the objective says
otherwise: a ``spectrum`` (wavelengths and weights, as `psf_map` takes it) and a
``source_radius`` make them what a camera records from a disc source in a band of light,
whose blur hides structure finer than the source's image (a radius of
source_radius·z2/z1 on the sensor): `source_blurred`. With ``oversample`` k > 1 the
field is computed on a grid k× finer (the height cubic-interpolated,
`diffcam.model.camera.finer_diffuser`) and its irradiance integrated over each sensor
pixel (`diffcam.model.sensor.resample`, area), as a sensor records it; at k = 1 the
irradiance is sampled at each pixel's centre, which keeps detail up to the grid's
Nyquist frequency that pixels average away.

The PSFs come from `diffcam.model.stack_map.psf_map`, a chunk of depths at a time
(at least `CHUNKS` chunks) and recomputed in the reverse pass, so the gradient's memory
is a chunk's fields plus the nz standardised PSFs the correlations need. ``jax.vmap`` of
`diffcam.model.point_spread.psf` (chunked too, by a custom_vmap) keeps every chunk's
fields for the reverse pass instead: its gradient's temporaries grow with the number of
depths (``python -m benchmarks.bench_design``).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import logsumexp
from jaxtyping import Float

from diffcam.design.surfaces import Surface, height_map
from diffcam.evaluate.metrics import fourier_shift
from diffcam.model.camera import Camera, finer_diffuser, oversampled
from diffcam.model.off_axis import disc_samples
from diffcam.model.point_spread import items_per_chunk
from diffcam.model.sensor import resample
from diffcam.model.stack_map import psf_map

__all__ = ["standardised", "spread", "correlation_matrix", "pair_correlations",
           "smooth_max", "source_blurred", "DepthObjective", "Terms", "depth_terms",
           "depth_objective", "recorded", "objective_terms"]


CHUNKS = 4
"""Fewest chunks the depths are split into (`psf_map`'s ``batch_size``; fewer depths per
chunk when its default, about 2**20 field samples, holds more): with every depth in one
chunk the gradient's temporaries were 2.3× the forward pass's at 256² over 16 depths,
with four 1.5× (``python -m benchmarks.bench_design``)."""


def standardised(image: Float[Array, "... ny nx"]) -> Float[Array, "... ny nx"]:
    """(a − ā)/‖a − ā‖ over the last two axes: Pearson correlations are dot products
    of these."""
    d = image - jnp.mean(image, axis=(-2, -1), keepdims=True)
    return d / jnp.sqrt(jnp.sum(d * d, axis=(-2, -1), keepdims=True))


def spread(image: Float[Array, "... ny nx"]) -> Float[Array, "..."]:
    """‖a‖₁/(√N·‖a‖₂) over the last two axes (N samples): 1 for a uniform image,
    1/√N for one bright sample; lower is sparser."""
    n = image.shape[-2] * image.shape[-1]
    l1 = jnp.sum(jnp.abs(image), axis=(-2, -1))
    l2 = jnp.sqrt(jnp.sum(image * image, axis=(-2, -1)))
    return l1 / (jnp.sqrt(n) * l2)


def correlation_matrix(q: Float[Array, "nz ny nx"]) -> Float[Array, "nz nz"]:
    """Pearson correlations of every pair of `standardised` images."""
    flat = q.reshape(q.shape[0], -1)
    return flat @ flat.T


def pair_correlations(q: Float[Array, "nz ny nx"]) -> Float[Array, " npairs"]:
    """The correlations of the nz(nz − 1)/2 pairs i < j of `standardised` images."""
    i, j = np.triu_indices(q.shape[0], k=1)
    return correlation_matrix(q)[i, j]


def smooth_max(values: Float[Array, " n"], temperature) -> Float[Array, ""]:
    """τ · log Σ exp(v/τ): an upper bound of max(v) within τ·log n (τ = ``temperature``,
    in the units of v)."""
    return temperature * logsumexp(values / temperature)


def source_blurred(psf: Float[Array, "ny nx"], radius) -> Float[Array, "ny nx"]:
    """``psf`` as a disc source records it: the mean of ``psf`` moved to the centre and
    six points on the rim of a disc of ``radius`` (sensor pixels; the source's image,
    source radius · z2/z1), the sampling of
    `diffcam.calibrate.simulation.high_fidelity_psfs`. Circular (``fourier_shift``):
    keep the PSF a radius inside the frame."""
    shifts = disc_samples(radius)
    return jnp.mean(fourier_shift(jnp.broadcast_to(psf, (7, *psf.shape)), shifts), axis=0)


class DepthObjective(NamedTuple):
    """What the objective needs besides the surface.

    Attributes:
        camera: the camera the diffuser sits in (its grid is the surface's).
        z1: the depths of the range, metres, (nz,) with nz ≥ 2.
        refractive_index: n of the diffuser material, unitless.
        temperature: τ of the smooth maximum, in correlation units.
        sparsity_weight: w of the spread term, unitless.
        spectrum: ``(wavelengths in metres, weights)`` of the light, or ``None`` for
            ``camera.wavelength`` alone.
        source_radius: radius of the disc source, metres (0: a point); the PSFs are
            `source_blurred` by its image, source_radius·z2/z1.
        oversample: field samples per sensor pixel, per side (1: the irradiance at
            each pixel's centre; k > 1: on a k× finer grid, integrated over each pixel).
    """

    camera: Camera
    z1: np.ndarray
    refractive_index: float
    temperature: float = 0.01
    sparsity_weight: float = 0.1
    spectrum: tuple | None = None
    source_radius: float = 0.0
    oversample: int = 1


class Terms(NamedTuple):
    """The objective's parts at one surface: ``smooth`` (ρ_τ), ``max_correlation``
    (ρ_max, the true maximum), ``spread`` (mean over depths)."""

    smooth: Array
    max_correlation: Array
    spread: Array


def depth_objective(surface: Surface, objective: DepthObjective) -> tuple[Array, Terms]:
    """``(loss, Terms)`` of ``surface``: loss = ρ_τ + w·mean spread (module docstring).
    Differentiable in the surface's array leaves."""
    q, s = recorded(lambda h: (standardised(h), spread(h)), surface, objective)
    return objective_terms(q, s, objective)


def recorded(fn: Callable, surface: Surface, objective: DepthObjective):
    """``fn(PSF)`` for every depth of ``objective.z1``, the PSFs as the objective's light,
    source and pixels record them (module docstring; ``objective`` has the fields
    ``camera``, ``z1``, ``refractive_index``, ``spectrum``, ``source_radius`` and
    ``oversample`` of `DepthObjective`), a chunk of depths at a time (`CHUNKS`)."""
    diffuser = height_map(surface, objective.refractive_index)
    nz = np.shape(objective.z1)[0]
    camera, k = objective.camera, objective.oversample
    fine = oversampled(camera, k)
    chunk = min(items_per_chunk(fine, 1), -(-nz // CHUNKS))
    radius = objective.source_radius * camera.z2 / (jnp.asarray(objective.z1) * camera.dx)

    def record(h, r):
        h = resample(h, fine.dx, camera.dx, camera.out_shape, max_width=k) if k > 1 else h
        return fn(source_blurred(h, r) if objective.source_radius > 0 else h)
    return psf_map(record, finer_diffuser(diffuser, k), fine, objective.z1, radius,
                   spectrum=objective.spectrum, batch_size=chunk)


def depth_terms(q: Float[Array, "nz ny nx"], spreads: Float[Array, " nz"],
                temperature) -> Terms:
    """`Terms` from the `standardised` PSFs ``q`` and their `spread`, the smooth maximum
    at ``temperature`` (correlation units)."""
    pairs = pair_correlations(q)
    return Terms(smooth_max(pairs, temperature), jnp.max(pairs), jnp.mean(spreads))


def objective_terms(q: Float[Array, "nz ny nx"], spreads: Float[Array, " nz"],
                    objective: DepthObjective) -> tuple[Array, Terms]:
    """``(loss, Terms)`` from the `standardised` PSFs ``q`` and their `spread`."""
    terms = depth_terms(q, spreads, objective.temperature)
    return terms.smooth + objective.sparsity_weight * terms.spread, terms
