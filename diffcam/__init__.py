"""diffcam: differentiable JAX optics for lensless diffuser cameras.

The four stages of the method (Optics Express 2019), one subpackage each, on two
shared layers:

1. calibrate — :mod:`diffcam.calibrate`: the diffuser phase from near/far captures
   (GS/HIO/RAAR, least squares through the forward model) and fits to captured PSFs;
2. model — :mod:`diffcam.model`: the :class:`Camera`, the PSF at any depth (Eq. 7),
   stacks over depth grids, the sensor;
3. reconstruct — :mod:`diffcam.reconstruct`: Richardson–Lucy (Eq. 15), ADMM-TV, Wiener;
4. evaluate — :mod:`diffcam.evaluate`: Pearson (Eq. 14), SSIM, the phase metric, the
   magnification baseline;

- :mod:`diffcam.optics` — propagators, optical elements, sampling rules;
- :mod:`diffcam.core` — the grid convention, errors, units, the FFT backend seam;
- :mod:`diffcam.io`, :mod:`diffcam.data` — captures in and out, built-in measured data;
- :mod:`diffcam.apps` — the command line, the demo, the paper's experiments.

Units are SI everywhere (metres, radians); grids are centred (index N//2 is the axis).
``docs/design.md`` maps the paper's equations to functions.
"""


from diffcam import calibrate, core, evaluate, model, optics, reconstruct
from diffcam.calibrate import retrieve_phase
from diffcam.core.errors import (ConvergenceWarning, DiffcamError, GeometryWarning,
                                 SamplingError, ShapeError, UndersamplingWarning)
from diffcam.evaluate import magnify_psf, pearson, psf_fidelity, psnr, ssim
from diffcam.model import (Camera, HeightMap, Spectrum, load_stack, psf, psf_stack,
                           random_diffuser, save_stack)
from diffcam.optics import (angular_spectrum, apply_phase, circular_aperture, fourier_lens,
                            fresnel_ir, fresnel_tf, plan_sampling, point_source_field,
                            thin_lens)
from diffcam.reconstruct import admm_tv, richardson_lucy, wiener
from diffcam.core.version import installed_version


__version__ = installed_version()

__all__ = [
    "Camera", "HeightMap", "Spectrum", "psf", "random_diffuser", "psf_stack", "save_stack",
    "load_stack", "magnify_psf", "retrieve_phase", "richardson_lucy", "admm_tv", "wiener",
    "fresnel_tf", "fresnel_ir", "angular_spectrum", "fourier_lens",
    "circular_aperture", "point_source_field", "thin_lens", "apply_phase", "plan_sampling",
    "pearson", "ssim", "psnr", "psf_fidelity", "DiffcamError", "SamplingError", "ShapeError",
    "UndersamplingWarning", "GeometryWarning", "ConvergenceWarning", "calibrate", "core",
    "evaluate", "model", "optics", "reconstruct",
]
