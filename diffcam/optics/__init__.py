"""Scalar wave optics on a centred grid.

- `diffcam.optics.propagation` — free space (paper Eqs. 1–2, 6: Fresnel transfer function
  and impulse response, angular spectrum) and the Fresnel scaling theorem's magnification
  and effective distance;
- `diffcam.optics.lens` — the Fourier lens (Eqs. 9–13) and its inverse;
- `diffcam.optics.elements` — apertures (Eqs. 3–4), the point source (Eq. 2), a thin lens,
  the thin diffuser (Eq. 5);
- `diffcam.optics.sampling` — what a grid samples: the point-source chirp check and the
  sampling planner.
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
