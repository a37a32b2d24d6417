"""The magnification baseline (Xie et al.; the paper's "scaling method"): one PSF, other
depths. (Not to be confused with the Fresnel scaling theorem, which the model uses:
`diffcam.optics.propagation.magnification`.)

A PSF measured at ``z1_ref`` predicts the PSF at ``z1`` by magnifying it about its
centre by

    m = (1 + z2/z1) / (1 + z2/z1_ref) = M(z1) / M(z1_ref),

the ratio of the scaling theorem's magnifications M = (z1 + z2)/z1 (docs/design.md). What it
misses is the change of z_eff = z1·z2/(z1 + z2) between the two depths: nearly nothing
for z2 = 1 mm, a lot for larger z2 (and everything the measurement got wrong).
"""

from __future__ import annotations

import math
import warnings
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.deprecation import renamed
from diffcam.core.errors import (DiffcamError, ShapeError, check_field, check_finite,
                                 check_positive, is_concrete, real_array)
from diffcam.model.sensor import resample
from diffcam.optics.propagation import magnification

__all__ = ["magnify_psf", "relative_magnification", "scale_psf", "scale_factor"]


def relative_magnification(z1_ref, z1, z2):
    """m = M(z1)/M(z1_ref) = (1 + z2/z1)/(1 + z2/z1_ref): the magnification of the PSF from
    depth ``z1_ref`` to ``z1`` (metres), M the scaling theorem's."""
    return magnification(z1, z2) / magnification(z1_ref, z2)


def magnify_psf(psf_ref: Float[Array, "ny nx"], dx, z1_ref, z1, z2, centre=(0.0, 0.0), *,
                kind: str = "cubic") -> Float[Array, "... ny nx"]:
    """Predict PSFs at depths ``z1`` from ``psf_ref`` measured at ``z1_ref``.

    **Outside its frame the reference is taken to be zero.** For ``kind="cubic"``
    `diffcam.model.sensor.resample` zero-pads the frame before its periodic (FFT)
    spline prefilter: unpadded, light at one edge would leak into the opposite edge.
    With the padding, m = 1 returns the
    reference unchanged even when it has signal at the frame edge, a shrunk PSF (m < 1)
    has zeros where the frame ends, and a magnified one loses what leaves the frame.

    Args:
        psf_ref: the reference PSF (power per pixel), finite, non-negative, with some
            light.
        dx: its pixel pitch, metres.
        z1_ref: depth of the reference, metres.
        z1: target depth(s), metres: a scalar or an array of shape (nz,).
        z2: diffuser-to-sensor distance, metres.
        centre: ``(y0, x0)`` the magnification keeps fixed, metres from the grid
            centre: the image of the aperture centre (0, 0 for an on-axis source).
        kind: resampling of `diffcam.model.sensor.resample`: ``"cubic"`` (default;
            point-sampled PSFs, e.g. simulated) or ``"area"`` (pixel-integrated ones).

    Returns:
        ``z1.shape + psf_ref.shape``: the magnified, resampled reference, renormalised
        to the reference's sum. Differentiable in every argument; with ``kind="area"``
        the magnification must stay ≥ 0.5 when it is traced.

    Raises:
        DiffcamError: NaN/Inf in any argument (named), a negative or all-zero reference,
            non-positive lengths; ``ShapeError`` unless ``psf_ref`` is 2-D.
    """
    real_array("psf_ref", psf_ref)
    check_field(psf_ref, "psf_ref")
    if np.ndim(psf_ref) != 2:
        raise ShapeError(f"psf_ref must be one 2-D PSF (ny, nx), got shape "
                         f"{np.shape(psf_ref)}; magnify a stack one PSF at a time.")
    for name, v in (("dx", dx), ("z1_ref", z1_ref), ("z1", z1), ("z2", z2)):
        check_positive(name, v, "m")
    if np.shape(centre) != (2,):
        raise ShapeError(f"centre must be (y0, x0) in metres, got {centre!r}.")
    check_finite("centre", centre)
    if is_concrete(psf_ref):
        ref_np = np.asarray(psf_ref)
        if np.min(ref_np) < 0 or not np.sum(ref_np, dtype=np.float64) > 0:
            raise DiffcamError(
                f"psf_ref must be non-negative with some light (min {np.min(ref_np):.3g}, "
                f"sum {np.sum(ref_np, dtype=np.float64):.3g}); subtract the background "
                f"with diffcam.io.subtract_background, which clips small negatives.")
    if kind not in ("cubic", "area"):
        raise DiffcamError(f"kind must be 'cubic' or 'area', got {kind!r}.")
    m = relative_magnification(z1_ref, jnp.asarray(z1), z2)
    ref = jnp.asarray(psf_ref)
    if is_concrete(m):
        _check_magnification(np.asarray(m), max(ref.shape))
    # the area kernel's taps depend only on ceil(max_width), and never exceed the frame
    # (diffcam.model.sensor): one compilation per count, at most one per frame size
    max_width = (float(min(math.ceil(1 / float(np.min(np.asarray(m)))), max(ref.shape)))
                 if is_concrete(m) else 2.0)
    if not jnp.issubdtype(ref.dtype, jnp.floating):
        ref = ref.astype(jnp.float32)
    out = _magnify(ref, dx, m, jnp.asarray(centre), kind=kind, max_width=max_width)
    if is_concrete(out) and not bool(jnp.isfinite(out).all()):
        raise DiffcamError(
            f"magnifying psf_ref by m = {np.asarray(m).min():.4g}…{np.asarray(m).max():.4g} "
            f"leaves no light in the frame; check z1, z1_ref and z2 (metres).")
    return out


def _check_magnification(m: np.ndarray, n: int) -> None:
    """``m`` maps the reference's ``n``-pixel frame onto at least one pixel and one of
    its pixels onto at most the frame: 1/n ≤ m ≤ n. Beyond, the whole PSF lands in one
    pixel or one pixel fills the frame: a depth ratio no camera images with (a length
    not in metres, most likely)."""
    lo, hi = float(m.min()), float(m.max())
    if lo < 1 / n or hi > n:
        raise DiffcamError(
            f"magnify_psf: the magnification z1_ref → z1 is {lo:.3g}…{hi:.3g}, outside "
            f"1/{n} … {n}: the reference's {n}-pixel frame would shrink below one pixel or "
            f"one pixel fill the frame; check z1_ref, z1 and z2 (metres: 25 mm is 25e-3).")


@partial(jax.jit, static_argnames=("kind", "max_width"))
def _magnify(ref, dx, m, centre, *, kind, max_width):
    shape = ref.shape[-2:]
    def one(mi):
        out = resample(ref, dx, dx, shape, mi, centre, kind=kind, max_width=max_width)
        return out * (jnp.sum(ref) / jnp.sum(out))

    return jax.vmap(one)(m.reshape(-1)).reshape(m.shape + shape)


scale_psf = renamed(magnify_psf, "diffcam.evaluate.baseline.scale_psf")


def scale_factor(z1, z1_ref, z2):
    """Deprecated: `relative_magnification` takes ``(z1_ref, z1, z2)``, the order of
    `magnify_psf`."""
    warnings.warn("diffcam.evaluate.baseline.scale_factor(z1, z1_ref, z2) is now "
                  "relative_magnification(z1_ref, z1, z2)", DeprecationWarning, stacklevel=2)
    return relative_magnification(z1_ref, z1, z2)
