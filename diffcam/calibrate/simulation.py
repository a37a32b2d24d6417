"""The paper's simulated calibration (Section 3.1): the cameraman diffuser and its exact
near/far intensities (`diffcam.calibrate.phase.near_far.calibration_intensities`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.core.options import Options
from diffcam.core.grid import pad_to
from diffcam.model import Camera
from diffcam.model.camera import finer_diffuser, oversampled, random_diffuser
from diffcam.model.off_axis import disc_samples
from diffcam.model.sensor import bin_pixels, resample
from diffcam.model.stack import psf_stack
from diffcam.optics.elements import circular_aperture
from diffcam.calibrate.phase.near_far import CalibrationGeometry, calibration_intensities

__all__ = ["cameraman_phase", "PaperSimulation",
           "paper_simulation", "measured_stack_simulation", "HIGH_FIDELITY_SPECTRUM",
           "high_fidelity_captures", "high_fidelity_psfs", "recorded_psfs"]


def cameraman_phase(size: int = 512) -> Float[Array, "size size"]:
    """The paper's simulated diffuser (Section 3.1): scikit-image's 512×512 "cameraman"
    scaled linearly to [−π, π] radians; other sizes are area-resampled first."""
    import skimage.data
    import skimage.transform
    img = skimage.data.camera().astype(np.float64)
    if size != img.shape[0]:
        img = skimage.transform.resize(img, (size, size), anti_aliasing=True)
    theta = (img - img.min()) / (img.max() - img.min()) * 2 * np.pi - np.pi
    return jnp.asarray(theta, jnp.float32)


# The paper's simulation (Section 3.1; docs/design.md, "The paper's simulation"), SI units
PAPER_DX = 5e-6
PAPER_WAVELENGTH = 532e-9
PAPER_FOCAL_LENGTH = 5e-2
PAPER_APERTURE_RADIUS = 1.2e-3


class PaperSimulation(NamedTuple):
    """The paper's Fig. 3 problem on an N×N grid (see
    [`paper_simulation`][diffcam.calibrate.simulation.paper_simulation])."""

    phase: Float[Array, "n n"]      # θd on the grid (radians; 0 outside the diffuser)
    aperture: Float[Array, "n n"]   # circular aperture C
    geometry: CalibrationGeometry
    near: Float[Array, "n n"]       # exact near-field intensity (at the diffuser)
    far: Float[Array, "n n"]        # exact far-field intensity (Fourier-lens pitch)
    truth: Float[Array, "size size"]  # θd on the diffuser crop, for scoring
    mask: Float[Array, "size size"]   # the scored central square (300/512 of the side)


def paper_simulation(n: int = 1024, size: int = 512, phase=None) -> PaperSimulation:
    """Paper Section 3.1: a ``size``² cameraman diffuser at 5 µm, aperture radius 1.2 mm,
    f = 5 cm, λ = 532 nm, embedded in an ``n``² grid; ``size < 512`` shrinks the diffuser,
    the aperture and the scored square (300 px at 512) in proportion, for fast tests.
    ``phase`` (``size``², radians) replaces the cameraman, e.g. a random diffuser (Fig. 6)."""
    dx = PAPER_DX
    geometry = CalibrationGeometry(dx=dx, wavelength=PAPER_WAVELENGTH,
                                   focal_length=PAPER_FOCAL_LENGTH)
    truth = cameraman_phase(size) if phase is None else jnp.asarray(phase, jnp.float32)
    if truth.shape != (size, size):
        raise ShapeError(f"phase must be {size}×{size}, got {truth.shape}.")
    aperture = circular_aperture((n, n), dx, PAPER_APERTURE_RADIUS * size / 512)
    phase = pad_to(truth, (n, n))
    near, far = calibration_intensities(phase, aperture, geometry)
    scored = round(300 * size / 512)
    lo = (size - scored) // 2
    mask = jnp.zeros((size, size), jnp.float32).at[lo:lo + scored, lo:lo + scored].set(1.0)
    return PaperSimulation(phase, aperture, geometry, near, far, truth, mask)


def _disc(radius: float):
    """Source offsets (y1, x1) sampling a disc of ``radius`` (m): None for a point."""
    if radius <= 0:
        return None
    return np.asarray(disc_samples(0.7 * radius), np.float64)


class StackSimulation(Options):
    """The camera and sensor of `measured_stack_simulation` (lengths in metres).

    Attributes:
        z2: diffuser → sensor distance.
        z1_near, z1_far: the nearest and farthest source depths (the planes are
            equally spaced in 1/z1 between them).
        grid: field samples per side; ``dx``: their pitch.
        binning: field samples per sensor pixel (per side).
        photons: expected counts at the brightest pixel of the stack.
        dark: dark level, counts.
        seed: the diffuser's seed.
        noise: Poisson noise (else the expected counts, the truth the noisy planes
            scatter about).
        deflection: the diffuser's r.m.s. deflection, degrees (its strength).
        bandwidth: half-width of the light's spectrum around 532 nm: three lines at
            532 nm ∓ ``bandwidth`` (weights ½, 1, ½); 0 for one line.
        source_radius: radius of the point source (a disc, sampled by its centre and
            six points at 0.7·radius, weighted alike); 0 for a point.
    """

    z2: float = 0.6e-3
    z1_near: float = 2e-3
    z1_far: float = 10e-3
    grid: int = 768
    dx: float = 1e-6
    binning: int = 4
    photons: float = 150.0
    dark: float = 5.0
    seed: int = 3
    noise: bool = True
    deflection: float = 1.5
    bandwidth: float = 17e-9
    source_radius: float = 0.0


def measured_stack_simulation(n_planes: int = 12, *, options: StackSimulation | None = None,
                              **overrides) -> tuple[np.ndarray, np.ndarray]:
    """A PSF stack as a camera would measure it, made by a higher-fidelity model than
    the stack model that fits it (`diffcam.calibrate.fit_stack`: monochromatic,
    thin phase, 2× oversampled, a point source): a ``grid``² field at ``dx`` behind a
    random 30 µm diffuser (``deflection`` 1.5°, aperture radius 0.2·grid·dx), three
    wavelengths (515/532/549 nm, weights ½/1/½), a point or disc source,
    ``n_planes`` depths from ``z1_near`` to ``z1_far``
    equally spaced in 1/z1, integrated over ``binning``×``binning`` pixels, Poisson
    noise at a peak of ``photons`` and a dark level of ``dark`` counts
    (`StackSimulation`; keywords named after its fields replace them).

    Returns:
        (float32 counts (n_planes, grid/(2·binning), grid/(2·binning)), z1 in m).
    """
    o = StackSimulation.of(options, **overrides)
    grid, dx, binning = o.grid, o.dx, o.binning
    camera = Camera(wavelength=532e-9, z2=o.z2, dx=dx, aperture_radius=0.2 * grid * dx,
                    shape=(grid, grid), pad=26, crop=(grid // 2, grid // 2))
    phase = random_diffuser(jax.random.key(o.seed), (grid, grid), dx, 532e-9,
                            feature_size=30e-6, deflection=np.deg2rad(o.deflection))
    z1 = 1 / np.linspace(1 / o.z1_near, 1 / o.z1_far, n_planes)
    lines = 532e-9 + o.bandwidth * np.array([-1.0, 0.0, 1.0])
    spectrum = (lines, np.array([0.5, 1.0, 0.5])) if o.bandwidth > 0 else None
    stack = psf_stack(phase, camera, z1, spectrum=spectrum, offsets=_disc(o.source_radius),
                      progress=False)
    if o.source_radius > 0:
        stack = stack.mean(axis=1)
    pixels = np.asarray(bin_pixels(stack, dx, binning * dx))
    pixels = pixels / pixels.max() * o.photons
    if o.noise:
        pixels = np.random.default_rng(0).poisson(pixels)
    counts = pixels.astype(np.float32) + o.dark
    return counts, z1


HIGH_FIDELITY_SPECTRUM = (np.array([526e-9, 532e-9, 538e-9]), np.array([0.5, 1.0, 0.5]))
"""Three lines across a 12 nm band around 532 nm (metres, relative power): the light of
the higher-fidelity simulations below (a filtered LED or a laser diode's width)."""


def high_fidelity_psfs(phase, camera, z1, *, oversample: int = 2,
                       spectrum=HIGH_FIDELITY_SPECTRUM, source_radius: float = 50e-6,
                       photons: float | None = None, seed: int = 0) -> np.ndarray:
    """PSFs as a camera records them, made by a higher-fidelity model than the one
    diffcam inverts with (monochromatic, at the sensor pitch, a point source):

    - the diffuser phase (radians at ``camera.wavelength``, on the camera grid)
      cubic-interpolated onto a grid ``oversample``× finer, the aperture drawn there;
    - three wavelengths (``spectrum``; the phase of a dispersion-free thin element,
      θ·λ0/λ);
    - a source of radius ``source_radius`` (m): its centre and six points on its rim,
      averaged;
    - the irradiance integrated over each sensor pixel (``camera.dx``);
    - Poisson noise at ``photons`` at the brightest pixel (``None``: the expected
      irradiance).

    Args:
        phase: ``camera.shape`` phase, radians.
        camera: the camera diffcam's model uses (``aperture_radius`` set).
        z1: depths, metres.

    Returns:
        float32 ``(nz, *camera.out_shape)``, each PSF of unit sum.
    """
    if camera.aperture_radius is None:
        raise DiffcamError("high_fidelity_psfs draws the aperture on its finer grid: give "
                           "the camera an aperture_radius.")
    fine = oversampled(camera, oversample)
    offsets = np.asarray(disc_samples(source_radius), np.float64)
    stack = psf_stack(finer_diffuser(phase, oversample), fine, np.atleast_1d(z1),
                      offsets=offsets, spectrum=spectrum, progress=False)  # (nz, 7, ny, nx)
    pixels = np.asarray(bin_pixels(jnp.asarray(stack.mean(axis=1)), fine.dx, camera.dx,
                                   camera.out_shape), np.float64)
    if photons is not None:
        return recorded_psfs(pixels, photons, np.random.default_rng(seed))
    return (pixels / pixels.sum(axis=(-2, -1), keepdims=True)).astype(np.float32)


def recorded_psfs(psfs, photons: float, rng: np.random.Generator) -> np.ndarray:
    """PSFs ``(…, ny, nx)`` (non-negative) as a calibration records them: Poisson noise
    at ``photons`` at each PSF's brightest pixel, then each normalised to unit sum
    (float32)."""
    psfs = np.asarray(psfs, np.float64)
    peak = psfs.max(axis=(-2, -1), keepdims=True)
    counts = rng.poisson(psfs / peak * photons).astype(np.float64)
    return (counts / counts.sum(axis=(-2, -1), keepdims=True)).astype(np.float32)


def high_fidelity_captures(phase, aperture_radius: float, geometry: CalibrationGeometry, *,
                           oversample: int = 2, spectrum=HIGH_FIDELITY_SPECTRUM,
                           photons: float | None = 1e5, seed: int = 0
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Near- and far-field captures of the paper's calibration (Section 3.1) made by a
    higher-fidelity model than the one that inverts them:

    - the diffuser on a grid ``oversample``× finer (phase cubic-interpolated, aperture
      of ``aperture_radius`` (m) drawn there);
    - three wavelengths (``spectrum``): the far field of each lands at its own pitch
      λf/(N·dx) and is resampled onto the sensor, whose pixels are the pitch at
      ``geometry.wavelength``; the near capture integrates each sensor pixel (the
      grid's ``geometry.dx``);
    - Poisson noise at ``photons`` at the brightest pixel of each (``None``: none).

    Args:
        phase: ``(n, n)`` phase on the calibration grid, radians at
            ``geometry.wavelength``.

    Returns:
        ``(near, far)`` on the calibration grid and its far-field pitch, float32, scaled
        as `diffcam.calibrate.phase.near_far.calibration_intensities` (W/m² for a unit
        plane wave, up to the noise).
    """
    import dataclasses


    k = int(oversample)
    fine_phase = finer_diffuser(phase, k)
    shape = np.shape(phase)[-2:]
    fine_dx = geometry.dx / k
    aperture = circular_aperture(fine_phase.shape, fine_dx, aperture_radius)
    lam0 = float(geometry.wavelength)
    sensor_pitch = geometry.far_pitch(shape)
    near = far = 0.0
    for lam, w in zip(*(np.asarray(a, np.float64) for a in spectrum)):
        g = dataclasses.replace(geometry, dx=fine_dx, wavelength=float(lam))
        n_l, f_l = calibration_intensities(fine_phase * (lam0 / lam), aperture, g)
        near = near + w * bin_pixels(n_l, fine_dx, geometry.dx, shape)
        # the fine grid's far field: pitch λf/(k·N·dx/k), k× the field of view
        far = far + w * resample(f_l, g.far_pitch(fine_phase.shape)[0], sensor_pitch[0], shape)
    # the near capture sums k² fine samples per pixel; the far one is read at its pitch
    total = float(np.sum(spectrum[1]))
    near = np.asarray(near, np.float64) / (total * k * k)
    far = np.asarray(far, np.float64) / total
    if photons is not None:
        rng = np.random.default_rng(seed)
        near, far = (rng.poisson(a / a.max() * photons) * (a.max() / photons)
                     for a in (near, far))
    return np.asarray(near, np.float32), np.asarray(far, np.float32)
