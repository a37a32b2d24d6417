"""Cubic resampling of captures takes the frame as zero outside: magnification 1 is the
identity, and light at one edge never shows at the opposite edge (the spline prefilter
works by FFT and used to wrap it across, as it did for ``scale_psf``)."""

import numpy as np
import pytest

from diffcam.calibrate import psf_plane, resample_capture
from diffcam.model.camera import Camera

N, DX = 64, 5e-6


def edge_light(level=0.0):
    """A 64² image at ``level`` with a bright bar touching the left edge (3 columns) and a
    bright corner touching the top and right edges."""
    img = np.full((N, N), level, np.float32)
    img[20:30, :3] += 1.0
    img[:4, -5:] += 2.0
    return img


@pytest.mark.slow
def test_resample_capture_at_its_own_pitch_is_the_identity():
    img = edge_light()
    out = np.asarray(resample_capture(img, DX, DX, (N, N)))
    np.testing.assert_allclose(out, img, atol=1e-5 * img.max())


@pytest.mark.slow  # 6 s; the same property of psf_plane by default (below)
def test_resample_capture_does_not_wrap_an_edge_across():
    """Bar at the left edge over a level of 100 (so no leak is hidden by the clip at 0):
    the right half reads the level alone, at the same pitch and at a coarser one that
    reads beyond the frame."""
    for pitch, shape in ((DX, (N, N)), (1.3 * DX, (64, 64)), (0.7 * DX, (96, 96))):
        lit = np.asarray(resample_capture(edge_light(100.0), DX, pitch, shape))
        flat = np.full((N, N), 100.0, np.float32)
        flat[:4, -5:] += 2.0
        dark = np.asarray(resample_capture(flat, DX, pitch, shape))
        half = shape[1] // 2
        np.testing.assert_allclose(lit[:, half:], dark[:, half:], atol=1e-4, rtol=0,
                                   err_msg=f"pitch {pitch}")


def test_psf_plane_does_not_wrap_an_edge_across():
    """psf_plane demagnifies the PSF by M = (z1 + z2)/z1: with the bar at its left edge,
    the right half of the plane is what the PSF without the bar gives; at z1 = 1 km
    (M − 1 = 1e-6) the plane is the PSF inside the mask."""
    camera = Camera(wavelength=532e-9, z2=1e-3, dx=DX, aperture_radius=0.1e-3, shape=(N, N))
    flat = np.full((N, N), 100.0, np.float32)
    flat[:4, -5:] += 2.0
    for z1 in (5e-3, 1e3):
        lit = psf_plane(edge_light(100.0), camera, z1)
        dark = psf_plane(flat, camera, z1)
        np.testing.assert_allclose(np.asarray(lit.intensity)[:, N // 2:],
                                   np.asarray(dark.intensity)[:, N // 2:], atol=1e-4, rtol=0)
    inside = np.asarray(lit.mask) > 0
    np.testing.assert_allclose(np.asarray(lit.intensity)[inside], edge_light(100.0)[inside],
                               rtol=1e-5)
