"""Scalar wave optics on a centred grid.

- :mod:`.propagation` — free space (paper Eqs. 1–2, 6: Fresnel transfer function and
  impulse response, angular spectrum) and the Fresnel scaling theorem's magnification
  and effective distance;
- :mod:`.fourier_lens` — the Fourier lens (Eqs. 9–13) and its inverse;
- :mod:`.elements` — apertures (Eqs. 3–4), the point source (Eq. 2), a thin lens, the
  thin diffuser (Eq. 5);
- :mod:`.sampling` — what a grid samples: the point-source chirp check and the sampling
  planner.
"""

from diffcam.optics.elements import (apply_phase, circular_aperture, point_source_field,
                                     rectangular_aperture, thin_lens)
from diffcam.optics.fourier_lens import fourier_lens, inverse_fourier_lens
from diffcam.optics.propagation import angular_spectrum, fresnel_ir, fresnel_tf, propagate
from diffcam.optics.sampling import plan_sampling

__all__ = ["apply_phase", "circular_aperture", "point_source_field", "rectangular_aperture",
           "thin_lens", "angular_spectrum", "fourier_lens", "fresnel_ir", "fresnel_tf",
           "inverse_fourier_lens", "propagate", "plan_sampling"]
