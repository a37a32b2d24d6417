"""What the propagators and the Fourier lens share: the complex dtype a field computes
in, the piston e^{jkz}, and the geometry packed for one host-to-device copy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffcam.core.errors import is_concrete

__all__ = ["complex_dtype", "piston", "pack_geometry"]


def complex_dtype(field):
    """The complex dtype a propagator computes ``field`` in: complex128 for float64 or
    complex128 input (with x64 enabled), else complex64."""
    dtype = field.dtype if hasattr(field, "dtype") else np.asarray(field).dtype
    dtype = jax.dtypes.canonicalize_dtype(dtype)   # float64 is float32 without x64
    return jnp.complex128 if dtype in (jnp.float64, jnp.complex128) else jnp.complex64


def piston(wavelength, z):
    """The constant phase factor e^{jkz}, k = 2π/λ, with kz reduced modulo 2π.

    Concrete arguments are reduced in float64 (numpy); traced ones in their own dtype.
    """
    if is_concrete(wavelength, z):
        cycles = np.asarray(z, dtype=np.float64) / np.asarray(wavelength, dtype=np.float64)
        phase = 2 * np.pi * np.mod(cycles, 1.0)
        return np.exp(1j * phase)
    cycles = z / wavelength
    return jnp.exp(2j * jnp.pi * (cycles - jnp.floor(cycles)))


def pack_geometry(lengths, p, dtype):
    """``(dy, dx, λ, z)`` and the piston's real and imaginary parts as one (6,) vector:
    a NumPy array when all are concrete, so a call pays one host-to-device copy instead
    of five (10 µs each, against 250 µs for a 128² step); else the traced values
    stacked."""
    values = (*lengths, p.real, p.imag)
    if is_concrete(*values) and not any(isinstance(v, jax.Array) for v in values):
        return np.asarray(values, dtype)
    return jnp.stack([jnp.asarray(v).astype(dtype) for v in values])
