"""diffcam: differentiable JAX optics for lensless diffuser cameras.

The four stages of the method (Optics Express 2019), one subpackage each, on two
shared layers:

1. calibrate — [`diffcam.calibrate`][diffcam.calibrate]: the diffuser phase from near/far
   captures (GS/HIO/RAAR, least squares through the forward model) and fits to captured
   PSFs;
2. model — [`diffcam.model`][diffcam.model]: the [`Camera`][diffcam.model.camera.Camera],
   the PSF at any depth (Eq. 7), stacks over depth grids, the sensor;
3. reconstruct — [`diffcam.reconstruct`][diffcam.reconstruct]: Richardson–Lucy (Eq. 15),
   ADMM-TV, Wiener;
4. evaluate — [`diffcam.evaluate`][diffcam.evaluate]: Pearson (Eq. 14), SSIM, the phase
   metric, the magnification baseline;

- [`diffcam.optics`][diffcam.optics] — propagators, optical elements, sampling rules;
- [`diffcam.core`][diffcam.core] — the grid convention, errors, units, the FFT backend seam;
- [`diffcam.io`][diffcam.io], [`diffcam.data`][diffcam.data] — captures in and out, built-in
  measured data;
- `diffcam.apps` — the command line, the demo, the paper's experiments.

Units are SI everywhere (metres, radians); grids are centred (index N//2 is the axis).
``docs/design.md`` maps the paper's equations to functions.
"""

from diffcam.core.lazy import attach_stub
from diffcam.core.version import installed_version

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
__version__ = installed_version()
