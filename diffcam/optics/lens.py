"""The Fourier lens (paper Eqs. 9–13): the field at the back focal plane of a lens of
focal length f with the input at its front focal plane,
U'(u) = e^{jkf}/(jλf) ∫ U(x) e^{-j2π x·u/(λf)} dx, at pitch λf/(N·dx) per axis, and its
inverse."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jaxtyping import Complex, Num

from diffcam.core.errors import check_field, check_finite, check_positive, found_false
from diffcam.core.grid import check_grid_size, fft2c, ifft2c, pad_by, pitch_yx
from diffcam.optics.fields import complex_dtype, pack_geometry, piston

__all__ = ["fourier_lens", "inverse_fourier_lens"]


@partial(jax.jit, static_argnames=("inverse",))
def _fourier_lens_core(field, geometry, *, inverse):
    u = field.astype(complex_dtype(field))
    dy, dx, wavelength, focal_length = geometry[0], geometry[1], geometry[2], geometry[3]
    p = lax.complex(geometry[4], geometry[5]).astype(u.dtype)
    finite = jnp.isfinite(field).all()
    if not inverse:
        return p / (1j * wavelength * focal_length) * dy * dx * fft2c(u), finite
    ny, nx = u.shape[-2:]
    # dy, dx here are the far-field pitches; ifft2c carries 1/(ny·nx)
    return (jnp.conj(p) / (-1j * wavelength * focal_length) * dy * dx * (ny * nx)
            * ifft2c(u), finite)


def _fourier_lens_run(field, dx, wavelength, focal_length, pad, inverse):
    check_field(field, finite="host")   # a device array: inside the jitted call, as in _run
    for q in pitch_yx(dx):
        check_positive("dx (pixel pitch)", q, "m")
    check_positive("wavelength", wavelength, "m")
    check_positive("focal_length", focal_length, "m")
    check_grid_size(np.shape(field), pad)
    field = jnp.asarray(field)
    if pad:
        field = pad_by(field, pad)
    ny, nx = field.shape[-2:]
    dy, dxx = pitch_yx(dx)
    out_pitch = (wavelength * focal_length / (ny * dy), wavelength * focal_length / (nx * dxx))
    cdt = complex_dtype(field)
    rdt = jnp.float64 if cdt == jnp.complex128 else jnp.float32
    out, finite = _fourier_lens_core(
        field, pack_geometry((dy, dxx, wavelength, focal_length), piston(wavelength, focal_length),
                         rdt), inverse=inverse)
    if found_false(finite):
        check_finite("field", field)
    return out, out_pitch


def fourier_lens(field: Num[Array, "... ny nx"], dx, wavelength, focal_length, *, pad=0
                 ) -> tuple[Complex[Array, "... my mx"], tuple]:
    """Field at the back focal plane of a lens with ``field`` at its front focal plane.

    Paper Eq. 13: U'(u) = e^{jkf}/(jλf) ∫ U(x) e^{-j2π x·u/(λf)} dx, evaluated on the
    centred grid of pitch λf/(N·dx) per axis. Energy-preserving in physical units:
    Σ|U'|²·du_y·du_x = Σ|U|²·dy·dx.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly to validate.

    Args:
        field: field at the front focal plane, last two axes space.
        dx: its pitch, metres (scalar or ``(dy, dx)``).
        wavelength: metres.
        focal_length: metres.
        pad: zero samples added on each side first; the output keeps the padded shape
            and so has a finer pitch λf/((N + 2·pad)·dx). The padded grid holds at
            most ``diffcam.core.grid.MAX_GRID_SAMPLES``.

    Returns:
        ``(far_field, (du_y, du_x))``: the field and its pitch in metres.
    """
    return _fourier_lens_run(field, dx, wavelength, focal_length, pad, inverse=False)


def inverse_fourier_lens(field: Num[Array, "... ny nx"], du, wavelength, focal_length
                         ) -> tuple[Complex[Array, "... ny nx"], tuple]:
    """Front-focal-plane field from the back-focal-plane field: inverse of
    [`fourier_lens`][diffcam.optics.lens.fourier_lens]. ``du`` is the far-field pitch
    (metres); returns the field and its pitch λf/(N·du).

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly to validate.
    """
    return _fourier_lens_run(field, du, wavelength, focal_length, 0, inverse=True)
