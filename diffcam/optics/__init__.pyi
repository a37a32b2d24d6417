"""Stub of [`diffcam.optics`][diffcam.optics]: its public names and the modules they come
from.

diffcam/optics/__init__.py imports each on first use
([`diffcam.core.lazy`][diffcam.core.lazy])."""

from diffcam.optics.elements import (apply_phase, circular_aperture, point_source_field,
                                     rectangular_aperture, thin_lens)
from diffcam.optics.lens import fourier_lens, inverse_fourier_lens
from diffcam.optics.propagation import angular_spectrum, fresnel_ir, fresnel_tf, propagate
from diffcam.optics.sampling import plan_sampling

__all__ = ["apply_phase", "circular_aperture", "point_source_field", "rectangular_aperture",
           "thin_lens", "angular_spectrum", "fourier_lens", "fresnel_ir", "fresnel_tf",
           "inverse_fourier_lens", "propagate", "plan_sampling"]
