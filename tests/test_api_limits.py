"""The second hardening round, API side: resource limits checked before any work,
exceptions that are DiffcamErrors, metrics that say why they are undefined instead of
returning NaN, garbage refused, and solvers whose results do not depend on the scale
of their inputs.

``PROBES`` lists the cases by the issue's class; each ends in the named error (or
warning) or in a valid, finite result that the probe checks. Property-based tests
(hypothesis) vary shapes, constant slices and scales. ``docs/hardening.md`` states
the limits these check.
"""

from __future__ import annotations

import functools
import warnings
from typing import Callable, NamedTuple

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import fftconvolve

import diffcam as dc
import diffcam.core.backend as backend
import diffcam.core.grid as grid
import diffcam.reconstruct.checks as checks
from diffcam.core import fftw
from diffcam.apps.processes import distributed_settings
from diffcam.calibrate import fit_psf_from_scenes, fit_stack, predict_raw
from diffcam.calibrate.phase.lsq import retrieve_lsq
from diffcam.calibrate.phase.projections import retrieve_projections
from diffcam.calibrate.scene.fit import ScenePsf, ScenePsfOptions
from diffcam.core.errors import DiffcamError, SamplingError, UndersamplingWarning
from diffcam.evaluate.baseline import magnify_psf
from diffcam.evaluate.metrics import align_to, mse, psf_fidelity, psnr
from diffcam.evaluate.volume import depth_map, ridge_measures, target_box
from diffcam.evaluate.registration import register_magnification, scaling_baseline
from diffcam.io import (apply_envelope, downsample, envelope_widths, plane_light,
                        subtract_background)
from diffcam.model import Camera, HeightMap
from diffcam.model.camera import with_method
from diffcam.model.point_spread import MIN_SAMPLES_ACROSS
from diffcam.model.sensor import resample
from diffcam.optics.lens import fourier_lens
from diffcam.optics.propagation import (angular_spectrum, fresnel_ir,
                                        fresnel_tf, propagate)
from diffcam.reconstruct import (admm_tv, fista, focus_sweep, richardson_lucy,
                                 richardson_lucy_3d, wiener)

N = 64
CAMERA = Camera(wavelength=532e-9, z2=1e-3, dx=5e-6, aperture_radius=0.08e-3, shape=(N, N))
PHASE = np.asarray(dc.random_diffuser(jax.random.key(0), (N, N), 5e-6, 532e-9))
RNG = np.random.default_rng(0)
IMAGE, KERNEL = RNG.random((32, 32)) + 0.1, RNG.random((5, 5)) ** 3
FIELD = np.ones((16, 16), np.complex64)
VALID = "valid"


class Probe(NamedTuple):
    kind: str                    # the class
    name: str
    call: Callable[[], object]
    expect: object               # an exception or warning class, or VALID


def _camera(**changes):
    settings_ = dict(wavelength=532e-9, z2=1e-3, dx=5e-6, aperture_radius=1e-4,
                     shape=(64, 64))
    return Camera(**{**settings_, **changes})


def _pearson_of_integers(dtype):
    """Integer images (squares up to 10⁸ for int32: the sums overflowed) give NumPy's
    correlation coefficient."""
    a, b = (IMAGE * 100).astype(dtype), (IMAGE.T * 100).astype(dtype)
    if np.dtype(dtype).itemsize >= 4:
        a, b = a ** 2, b ** 2
    want = np.corrcoef(a.ravel().astype(np.float64), b.ravel().astype(np.float64))[0, 1]
    return lambda: np.testing.assert_allclose(float(dc.pearson(a, b)), want, rtol=1e-5)


def _pearson_beyond_the_sums_range():
    """float32 images ×1e37 (their sums leave float32): the unscaled coefficient."""
    a, b = (IMAGE * 1e37).astype(np.float32), (IMAGE.T * 1e37).astype(np.float32)
    np.testing.assert_allclose(float(dc.pearson(a, b)), float(dc.pearson(IMAGE, IMAGE.T)),
                               rtol=1e-5)


_SCENES = [RNG.random((16, 16)) + 0.05 for _ in range(2)]
_RAWS = [fftconvolve(s, KERNEL, mode="same") + 0.01 for s in _SCENES]
_CALIBRATION = ScenePsf(np.ones((1, 16, 16), np.float32), np.zeros(1, np.float32), "none",
                        np.zeros(1), {})


def _scene_fit(raws=_RAWS, truths=_SCENES, iterations=3):
    return fit_psf_from_scenes(raws, truths, iterations=iterations, flip="none",
                               progress=False)


def _coordinator(address):
    return lambda: distributed_settings({"JAX_COORDINATOR_ADDRESS": address,
                                         "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"})


_VOLUME = np.stack([np.pad(np.ones((4, 4)), 6) * (k + 1) for k in range(3)]) + 0.01


def _fft_threads_from_environment(text):
    def call():
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("DIFFCAM_FFT_THREADS", text)
            fftw._threads(None)
    return call


def _auto_falls_back():
    """DIFFCAM_FFT=auto with an unreadable thread count: XLA, and the status says why."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DIFFCAM_FFT_THREADS", "abc")
        mp.setitem(backend._setting, "backend", None)
        mp.setitem(backend._setting, "why_not_fftw", None)
        backend._choose("auto")
        assert backend.fft_backend() == "xla"
        assert "DIFFCAM_FFT_THREADS" in backend.fft_status()


PROBES = [
    # unbounded work: refused before anything of that size is allocated or run
    Probe("unbounded work", "richardson_lucy(..., 10**9)",
          lambda: richardson_lucy(IMAGE, KERNEL, 10**9), DiffcamError),
    Probe("unbounded work", "richardson_lucy_3d(..., 10**8)",
          lambda: richardson_lucy_3d(IMAGE, KERNEL[None], 10**8), DiffcamError),
    Probe("unbounded work", "admm_tv(..., 10**9)",
          lambda: admm_tv(IMAGE, KERNEL, 10**9), DiffcamError),
    Probe("unbounded work", "fresnel_tf(pad=10**5): 640 GB", lambda: fresnel_tf(
        FIELD, 5e-6, 532e-9, 1e-3, pad=10**5), DiffcamError),
    Probe("unbounded work", "angular_spectrum(pad=(0, 10**8))", lambda: angular_spectrum(
        FIELD, 5e-6, 532e-9, 1e-3, pad=(0, 10**8)), DiffcamError),
    Probe("unbounded work", "fresnel_ir(pad=10**5)", lambda: fresnel_ir(
        FIELD, 5e-6, 532e-9, 10.0, pad=10**5), DiffcamError),
    Probe("unbounded work", "fourier_lens(pad=10**5)", lambda: fourier_lens(
        FIELD, 5e-6, 532e-9, 5e-2, pad=10**5), DiffcamError),
    Probe("unbounded work", "propagate(pad=10**5)", lambda: propagate(
        FIELD, 5e-6, 532e-9, 1e-3, method="fresnel_tf", pad=10**5), DiffcamError),
    # exceptions that were not DiffcamErrors
    Probe("API exception", "fresnel_tf(pad=1.5)", lambda: fresnel_tf(
        FIELD, 5e-6, 532e-9, 1e-3, pad=1.5), DiffcamError),
    Probe("API exception", "fourier_lens(pad=1.5)", lambda: fourier_lens(
        FIELD, 5e-6, 532e-9, 5e-2, pad=1.5), DiffcamError),
    Probe("API exception", "angular_spectrum(pad=(1, 2.0))", lambda: angular_spectrum(
        FIELD, 5e-6, 532e-9, 1e-3, pad=(1, 2.0)), DiffcamError),
    Probe("API exception", "fresnel_tf(pad=True)", lambda: fresnel_tf(
        FIELD, 5e-6, 532e-9, 1e-3, pad=True), DiffcamError),
    Probe("API exception", "fresnel_tf(pad=-1)", lambda: fresnel_tf(
        FIELD, 5e-6, 532e-9, 1e-3, pad=-1), DiffcamError),
    Probe("API exception", "Camera(wavelength='532nm')",
          lambda: _camera(wavelength="532nm"), DiffcamError),
    Probe("API exception", "Camera(z2=b'1mm')", lambda: _camera(z2=b"1mm"), DiffcamError),
    Probe("API exception", "Camera(dx=1j)", lambda: _camera(dx=5e-6 + 1j), DiffcamError),
    Probe("API exception", "Camera(dx=None)", lambda: _camera(dx=None), DiffcamError),
    Probe("API exception", "Camera with two wavelengths",
          lambda: _camera(wavelength=[532e-9, 633e-9]), DiffcamError),
    Probe("API exception", "Camera with two aperture radii",
          lambda: _camera(aperture_radius=np.array([1e-4, 2e-4])), DiffcamError),
    Probe("API exception", "Camera(pad=2.5)", lambda: _camera(pad=2.5), DiffcamError),
    Probe("API exception", "psf of an object-dtype phase",
          lambda: dc.psf(PHASE.astype(object), CAMERA, 25e-3), DiffcamError),
    Probe("API exception", "psf of a text phase",
          lambda: dc.psf(PHASE.astype(str), CAMERA, 25e-3), DiffcamError),
    Probe("API exception", "richardson_lucy of an object-dtype image",
          lambda: richardson_lucy(IMAGE.astype(object), KERNEL, 2), DiffcamError),
    Probe("API exception", "richardson_lucy with an object-dtype PSF",
          lambda: richardson_lucy(IMAGE, KERNEL.astype(object), 2), DiffcamError),
    Probe("API exception", "wiener of an object-dtype image",
          lambda: wiener(IMAGE.astype(object), KERNEL), DiffcamError),
    Probe("API exception", "pearson of an object-dtype array",
          lambda: dc.pearson(IMAGE.astype(object), IMAGE), DiffcamError),
    Probe("API exception", "pearson of images without pixels",
          lambda: dc.pearson(np.zeros((0, 0)), np.zeros((0, 0))), DiffcamError),
    Probe("API exception", "psnr of images without pixels",
          lambda: dc.psnr(np.zeros((3, 0)), np.zeros((3, 0)), data_range=1.0), DiffcamError),
    Probe("API exception", "ssim of an object-dtype array",
          lambda: dc.ssim(IMAGE, IMAGE.astype(object)), DiffcamError),
    Probe("API exception", "magnify_psf of an object-dtype PSF", lambda: magnify_psf(
        IMAGE.astype(object), 5e-6, 25e-3, 26e-3, 1e-3), DiffcamError),
    # silent NaN
    Probe("silent NaN", "pearson of a constant image",
          lambda: dc.pearson(np.ones_like(IMAGE), IMAGE), DiffcamError),
    Probe("silent NaN", "pearson against a constant image",
          lambda: dc.pearson(IMAGE, np.full_like(IMAGE, 3.0)), DiffcamError),
    Probe("silent NaN", "pearson over an all-zero mask",
          lambda: dc.pearson(IMAGE, IMAGE.T, mask=np.zeros_like(IMAGE)), DiffcamError),
    Probe("silent NaN", "pearson over a mask on which a is constant", lambda: dc.pearson(
        np.pad(np.ones((8, 8)), 12), IMAGE, mask=np.pad(np.ones((8, 8)), 12)), DiffcamError),
    Probe("silent NaN", "ssim against a constant reference",
          lambda: dc.ssim(IMAGE, np.ones_like(IMAGE)), DiffcamError),
    Probe("silent NaN", "ssim(data_range=0)",
          lambda: dc.ssim(IMAGE, IMAGE, data_range=0), DiffcamError),
    Probe("silent NaN", "ssim(data_range=nan)",
          lambda: dc.ssim(IMAGE, IMAGE, data_range=float("nan")), DiffcamError),
    Probe("silent NaN", "ssim(data_range=inf)",
          lambda: dc.ssim(IMAGE, IMAGE, data_range=float("inf")), DiffcamError),
    Probe("silent NaN", "psnr(data_range=0)",
          lambda: psnr(IMAGE, IMAGE.T, data_range=0), DiffcamError),
    Probe("silent NaN", "psf_fidelity of a constant model",
          lambda: psf_fidelity(np.ones_like(IMAGE), IMAGE), DiffcamError),
    Probe("silent NaN", "psf_fidelity with one dark measured plane", lambda: psf_fidelity(
        np.stack([IMAGE, IMAGE]), np.stack([IMAGE, 0 * IMAGE])), DiffcamError),
    Probe("silent NaN", "mse(align='affine') of a constant estimate: any gain fits",
          lambda: mse(np.ones_like(IMAGE), IMAGE, align="affine"), DiffcamError),
    Probe("silent NaN", "align_to(mode='scale') of an all-zero estimate",
          lambda: align_to(np.zeros_like(IMAGE), IMAGE, "scale"), DiffcamError),
    # garbage accepted
    Probe("garbage accepted", "richardson_lucy of an all-zero image",
          lambda: richardson_lucy(np.zeros_like(IMAGE), KERNEL, 2), DiffcamError),
    Probe("garbage accepted", "richardson_lucy of a batch with one dark image",
          lambda: richardson_lucy(np.stack([IMAGE, 0 * IMAGE]), KERNEL, 2), DiffcamError),
    Probe("garbage accepted", "ssim(data_range=-1)",
          lambda: dc.ssim(IMAGE, IMAGE, data_range=-1), DiffcamError),
    Probe("garbage accepted", "psf of a complex phase",
          lambda: dc.psf(PHASE + 0.1j, CAMERA, 25e-3), DiffcamError),
    Probe("garbage accepted", "psf of a complex height map", lambda: dc.psf(
        HeightMap(PHASE * 1e-7 + 1e-9j, 1.5), CAMERA, 25e-3), DiffcamError),
    Probe("garbage accepted", "psf(z1=25e-6) on the scaling path",
          lambda: dc.psf(PHASE, CAMERA, 25e-6), SamplingError),
    Probe("garbage accepted", "psf(z1=25e-6) on the direct path",
          lambda: dc.psf(PHASE, with_method(CAMERA, "direct"), 25e-6), SamplingError),
    Probe("garbage accepted", "set_fft('fftw', threads=True)",
          lambda: backend.set_fft("fftw", threads=True), DiffcamError),
    Probe("garbage accepted", "set_fft('fftw', threads=2.0)",
          lambda: backend.set_fft("fftw", threads=2.0), DiffcamError),
    Probe("garbage accepted", "DIFFCAM_FFT_THREADS=abc",
          _fft_threads_from_environment("abc"), DiffcamError),
    Probe("garbage accepted", "DIFFCAM_FFT_THREADS=-2",
          _fft_threads_from_environment("-2"), DiffcamError),
    Probe("garbage accepted", "DIFFCAM_FFT=auto falls back past a bad thread count",
          _auto_falls_back, VALID),
    # the third round (issue #50): dtype and shape corners
    Probe("dtype corner", "pearson of int32 squares", _pearson_of_integers(np.int32), VALID),
    Probe("dtype corner", "pearson of int8 images", _pearson_of_integers(np.int8), VALID),
    Probe("dtype corner", "pearson of uint16 images", _pearson_of_integers(np.uint16), VALID),
    Probe("dtype corner", "pearson of float32 ×1e37", _pearson_beyond_the_sums_range, VALID),
    Probe("dtype corner", "pearson of a complex image",
          lambda: dc.pearson(IMAGE + 1j, IMAGE), DiffcamError),
    Probe("dtype corner", "mse of a complex reference",
          lambda: mse(IMAGE, IMAGE + 0j), DiffcamError),
    Probe("dtype corner", "ssim of a complex estimate",
          lambda: dc.ssim(IMAGE + 1j, IMAGE), DiffcamError),
    Probe("dtype corner", "richardson_lucy of a complex image",
          lambda: richardson_lucy(IMAGE + 0j, KERNEL, 2), DiffcamError),
    Probe("dtype corner", "richardson_lucy from a complex init",
          lambda: richardson_lucy(IMAGE, KERNEL, 2, init=np.ones_like(IMAGE) + 0j),
          DiffcamError),
    Probe("dtype corner", "richardson_lucy with a complex PSF",
          lambda: richardson_lucy(IMAGE, KERNEL + 0j, 2), DiffcamError),
    Probe("dtype corner", "wiener of a complex image",
          lambda: wiener(IMAGE + 1j, KERNEL), DiffcamError),
    Probe("dtype corner", "admm_tv of a complex image",
          lambda: admm_tv(IMAGE + 1j, KERNEL, 2, progress=False), DiffcamError),
    Probe("dtype corner", "fista of a complex image",
          lambda: fista(IMAGE + 1j, KERNEL, 2, progress=False), DiffcamError),
    Probe("dtype corner", "focus_sweep of a complex image",
          lambda: focus_sweep(IMAGE + 1j, KERNEL[None], 2), DiffcamError),
    Probe("dtype corner", "retrieve_lsq of a complex capture (it warned)",
          lambda: retrieve_lsq(IMAGE + 0j, IMAGE, None, np.ones_like(IMAGE)), DiffcamError),
    Probe("dtype corner", "retrieve_projections of a complex capture",
          lambda: retrieve_projections(IMAGE, IMAGE + 1j, None), DiffcamError),
    Probe("dtype corner", "register_magnification of a complex plane",
          lambda: register_magnification(IMAGE + 1j, IMAGE), DiffcamError),
    Probe("dtype corner", "scaling_baseline from a complex plane",
          lambda: scaling_baseline({0: IMAGE + 1j, 3: IMAGE}, [1]), DiffcamError),
    Probe("dtype corner", "fit_stack of a complex stack", lambda: fit_stack(
        np.stack([IMAGE] * 3) + 1j, [0, 2], progress=False), DiffcamError),
    Probe("dtype corner", "downsample of a complex image",
          lambda: downsample(IMAGE + 1j, 2), DiffcamError),
    Probe("dtype corner", "subtract_background of a complex image",
          lambda: subtract_background(IMAGE + 1j, 0.1), DiffcamError),
    Probe("dtype corner", "plane_light of a complex stack",
          lambda: plane_light(np.stack([IMAGE] * 2) + 1j), DiffcamError),
    Probe("dtype corner", "pearson with a complex mask",
          lambda: dc.pearson(IMAGE, IMAGE.T, mask=np.ones_like(IMAGE) + 0j), DiffcamError),
    Probe("dtype corner", "ssim(data_range=1+1j)",
          lambda: dc.ssim(IMAGE, IMAGE.T, data_range=1 + 1j), DiffcamError),
    Probe("dtype corner", "richardson_lucy(tv_weight='a')",
          lambda: richardson_lucy(IMAGE, KERNEL, 2, tv_weight="a"), DiffcamError),
    Probe("dtype corner", "admm_tv(tau='a')",
          lambda: admm_tv(IMAGE, KERNEL, 2, tau="a", progress=False), DiffcamError),
    Probe("dtype corner", "psf_stack with a 2-D z1", lambda: dc.psf_stack(
        PHASE, CAMERA, np.full((2, 2), 25e-3)), DiffcamError),
    Probe("dtype corner", "psf_stack with text depths", lambda: dc.psf_stack(
        PHASE, CAMERA, ["25mm"]), DiffcamError),
    Probe("dtype corner", "propagate(dx=(5e-6,))", lambda: propagate(
        FIELD, (5e-6,), 532e-9, 1e-3), DiffcamError),
    Probe("dtype corner", "fresnel_tf(dx=(5e-6, 5e-6, 5e-6))", lambda: fresnel_tf(
        FIELD, (5e-6,) * 3, 532e-9, 1e-3), DiffcamError),
    Probe("dtype corner", "fit_stack(zetas=['a'])", lambda: fit_stack(
        np.ones((3, 16, 16)), [0, 2], zetas=["a"], progress=False), DiffcamError),
    Probe("dtype corner", "fit_stack(sigma='wide')", lambda: fit_stack(
        np.ones((3, 16, 16)), [0, 2], sigma="wide", progress=False), DiffcamError),
    Probe("dtype corner", "fit_stack(time_budget=None)", lambda: fit_stack(
        np.ones((3, 16, 16)), [0, 2], time_budget=None, progress=False), DiffcamError),
    Probe("dtype corner", "fit_stack(step_field=[0.1, 0.2])", lambda: fit_stack(
        np.ones((3, 16, 16)), [0, 2], step_field=[0.1, 0.2], progress=False), DiffcamError),
    Probe("dtype corner", "mse(constant, random, align='affine'): any gain fits",
          lambda: mse(np.full_like(IMAGE, 3.0), IMAGE, align="affine"), DiffcamError),
    Probe("dtype corner", "psnr(constant, random, align='affine')",
          lambda: psnr(np.ones_like(IMAGE), IMAGE, align="affine"), DiffcamError),
    Probe("dtype corner", "ssim(zeros, random, align='scale')",
          lambda: dc.ssim(np.zeros_like(IMAGE), IMAGE, align="scale"), DiffcamError),
    Probe("dtype corner", "magnify_psf(kind='area', z1_ref=1e-9): m ≈ 1e-6",
          lambda: magnify_psf(IMAGE[:8, :8], 5e-6, 1e-9, 25e-3, 1e-3, kind="area"),
          DiffcamError),
    Probe("dtype corner", "magnify_psf(z1=1e-9): m ≈ 1e6",
          lambda: magnify_psf(IMAGE[:8, :8], 5e-6, 25e-3, 1e-9, 1e-3), DiffcamError),
    # silent NaN
    Probe("silent NaN", "fista of an all-zero image (admm_tv refuses it)",
          lambda: fista(np.zeros_like(IMAGE), KERNEL, 2, progress=False), DiffcamError),
    Probe("silent NaN", "fista of a batch with one dark image", lambda: fista(
        np.stack([IMAGE, 0 * IMAGE]), KERNEL, 2, progress=False), DiffcamError),
    Probe("silent NaN", "admm_tv of a batch with one dark image", lambda: admm_tv(
        np.stack([IMAGE, 0 * IMAGE]), KERNEL, 2, progress=False), DiffcamError),
    Probe("silent NaN", "predict_raw of a NaN truth",
          lambda: predict_raw(_CALIBRATION, np.full((1, 16, 16), np.nan)), DiffcamError),
    Probe("silent NaN", "predict_raw with a NaN PSF", lambda: predict_raw(
        _CALIBRATION._replace(psf=np.full((1, 16, 16), np.nan)), _SCENES[0]), DiffcamError),
    # garbage accepted
    Probe("garbage accepted", "scene pairs with a negative truth",
          lambda: _scene_fit(truths=[_SCENES[0] - 0.5, _SCENES[1]]), DiffcamError),
    Probe("garbage accepted", "scene pairs with a complex truth",
          lambda: _scene_fit(truths=[s + 1j for s in _SCENES]), DiffcamError),
    Probe("garbage accepted", "scene pairs with float64 raws beyond float32",
          lambda: _scene_fit(raws=[r * 1e300 for r in _RAWS]), DiffcamError),
    Probe("garbage accepted", "target_box(fraction=2)",
          lambda: target_box(_VOLUME.max(0), fraction=2), DiffcamError),
    Probe("garbage accepted", "target_box(sigma=-1)",
          lambda: target_box(_VOLUME.max(0), sigma=-1), DiffcamError),
    Probe("garbage accepted", "target_box(margin=-5)",
          lambda: target_box(_VOLUME.max(0), margin=-5), DiffcamError),
    Probe("garbage accepted", "ridge_measures with a box outside the frame",
          lambda: ridge_measures(_VOLUME, (-5, 30, -3, 40)), DiffcamError),
    Probe("garbage accepted", "ridge_measures with a box of text",
          lambda: ridge_measures(_VOLUME, "abcd"), DiffcamError),
    Probe("garbage accepted", "depth_map(fraction=5)",
          lambda: depth_map(_VOLUME, fraction=5), DiffcamError),
    Probe("garbage accepted", "envelope_widths(samples=0)",
          lambda: envelope_widths(IMAGE, KERNEL[None], samples=0), DiffcamError),
    Probe("garbage accepted", "envelope_widths(samples=True)",
          lambda: envelope_widths(IMAGE, KERNEL[None], samples=True), DiffcamError),
    Probe("garbage accepted", "envelope_widths of a complex capture",
          lambda: envelope_widths(IMAGE + 1j, KERNEL[None]), DiffcamError),
    Probe("garbage accepted", "apply_envelope with infinite widths",
          lambda: apply_envelope(KERNEL[None], [np.inf]), DiffcamError),
    # tracebacks
    Probe("API exception", "coordinator address without a port", _coordinator("node1"),
          DiffcamError),
    Probe("API exception", "coordinator port out of range", _coordinator("node1:70000"),
          DiffcamError),
    Probe("API exception", "coordinator without a host", _coordinator(":6123"),
          DiffcamError),
    Probe("API exception", "fit_psf_from_scenes(iterations=True)",
          lambda: _scene_fit(iterations=True), DiffcamError),
    Probe("API exception", "ScenePsfOptions(search_iterations=2.0)",
          lambda: ScenePsfOptions(search_iterations=2.0), DiffcamError),
    Probe("API exception", "richardson_lucy(iterations=np.True_)",
          lambda: richardson_lucy(IMAGE, KERNEL, np.True_), DiffcamError),
    # messages that named the wrong problem
    Probe("misleading message", "psnr against a constant reference names the reference",
          lambda: _raises_naming(lambda: psnr(IMAGE, np.ones_like(IMAGE)), "reference is "
                                 "constant"), VALID),
    Probe("misleading message", "a PSF below float32's range is not 'all zeros'",
          lambda: _raises_naming(lambda: richardson_lucy(IMAGE, KERNEL * 1e-40, 2),
                                 "range of float32"), VALID),
]


def _raises_naming(call, words):
    with pytest.raises(DiffcamError, match=words):
        call()


@pytest.mark.parametrize("probe", PROBES, ids=[f"{p.kind}: {p.name}" for p in PROBES])
def test_probe(probe):
    if probe.expect == VALID:
        probe.call()
        return
    if issubclass(probe.expect, Warning):
        with pytest.warns(probe.expect):
            probe.call()
        return
    with pytest.raises(probe.expect) as err:
        probe.call()
    message = str(err.value)
    assert "\n" not in message and len(message) > 30     # one line that says something


def test_every_class_is_probed():
    assert {p.kind for p in PROBES} == {"unbounded work", "API exception", "silent NaN",
                                        "garbage accepted", "misleading message",
                                        "dtype corner"}


# ------------------------------------------------------------------- the limits

def test_limits_are_overridable(monkeypatch):
    """The iteration and grid limits are module constants a session may raise or lower."""
    monkeypatch.setattr(checks, "MAX_ITERATIONS", 3)
    assert richardson_lucy(IMAGE, KERNEL, 3).residual.shape == (3,)
    with pytest.raises(DiffcamError, match="MAX_ITERATIONS"):
        richardson_lucy(IMAGE, KERNEL, 4)
    monkeypatch.setattr(grid, "MAX_GRID_SAMPLES", 20 * 20)
    assert fresnel_tf(FIELD, 5e-6, 532e-9, 1e-4, pad=2).shape == FIELD.shape
    with pytest.raises(DiffcamError, match="MAX_GRID_SAMPLES"):
        fresnel_tf(FIELD, 5e-6, 532e-9, 1e-4, pad=3)
    with pytest.raises(DiffcamError, match="MAX_GRID_SAMPLES"):
        _camera(shape=(16, 16), aperture_radius=2e-5, pad=3)


def test_the_suggested_z1_is_the_scaling_paths_limit():
    """The frame spans n/M diffuser samples, M = (z1 + z2)/z1 (sample_points): the z1
    the error suggests, z2/(n/MIN_SAMPLES_ACROSS − 1), is where n/M reaches the limit.
    Just above it the PSF is computed; just below it is refused, or with
    accept_undersampling a warning and a finite PSF."""
    z2 = float(CAMERA.z2)
    limit = z2 / (N / MIN_SAMPLES_ACROSS - 1)
    with pytest.raises(SamplingError, match="z1 ≥ 66.67 µm"):
        dc.psf(PHASE, CAMERA, 0.999 * limit)
    assert np.isfinite(np.asarray(dc.psf(PHASE, CAMERA, 1.001 * limit))).all()
    with pytest.warns(UndersamplingWarning):
        flat = np.asarray(dc.psf(PHASE, CAMERA, 25e-6, accept_undersampling=True))
    # nearly flat: the frame spans 1.6 samples of a diffuser with 30 µm features
    assert flat.max() / flat.min() < 1.5


def test_area_resampling_is_bounded_by_the_frame():
    """An output pixel wider than the whole frame reads the frame's pixels once each:
    the power is kept and lands in the output pixel that holds the shrunk frame."""
    ref = IMAGE[:6, :7]
    out = np.asarray(resample(ref, 5e-6, 5e-6, (5, 5), 1e-6, kind="area"))
    assert out.sum() == pytest.approx(ref.sum(), rel=1e-5)
    assert out[2, 2] == pytest.approx(ref.sum(), rel=1e-5)


# ------------------------------------------------------------- property-based

@settings(max_examples=12, deadline=None, derandomize=True, database=None)
@given(constant=st.sets(st.integers(0, 2), max_size=3), which=st.sampled_from("ab"),
       value=st.sampled_from([0.0, 0.5, 1 / 3, 3e4]),
       fn=st.sampled_from(["pearson", "ssim", "psnr", "mse_affine", "fidelity"]))
def test_metrics_on_constant_slices(constant, which, value, fn):
    """A stack of three images in which some slices of one input hold one value: a
    DiffcamError if the metric is undefined there (Pearson; SSIM and PSNR in units of
    a reference whose range is 0; psf_fidelity's min–max normalisation; the affine fit
    of a constant estimate), otherwise finite values (the affine MSE against a
    constant reference is 0)."""
    rng = np.random.default_rng(7)
    a, b = rng.random((3, 9, 10)) + 0.1, rng.random((3, 9, 10)) + 0.1
    dark = sorted(constant)
    (a if which == "a" else b)[dark] = value
    calls = {"pearson": lambda: dc.pearson(a, b), "ssim": lambda: dc.ssim(a, b),
             "psnr": lambda: psnr(a, b), "mse_affine": lambda: mse(a, b, align="affine"),
             "fidelity": lambda: psf_fidelity(a, b, register=False)["pearson"]}
    # the default data range is the whole reference's: 0 only if every slice is constant
    undefined = dark and (fn in ("pearson", "fidelity")
                          or fn == "mse_affine" and which == "a"
                          or fn in ("ssim", "psnr") and which == "b" and len(dark) == 3)
    try:
        out = np.asarray(calls[fn]())
    except DiffcamError as e:
        assert undefined and "\n" not in str(e), str(e)
        return
    assert not undefined and np.isfinite(out).all()
    if fn == "mse_affine":
        np.testing.assert_allclose(out[dark], 0, atol=1e-8)


_VARIANTS = [{}, {"accelerate": True}, {"tv_weight": 1e-3}, {"boundary": "crop"}]
_SMALL, _KSMALL = IMAGE[:16, :16].astype(np.float32), KERNEL.astype(np.float32)


@functools.cache
def _unscaled(variant):
    return np.asarray(_rl(_SMALL, _KSMALL, variant).image)


def _rl(image, psf, variant):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return richardson_lucy(image, psf, 12, progress=False, **_VARIANTS[variant])


@pytest.mark.slow
@settings(max_examples=20, deadline=None, derandomize=True, database=None)
@given(image_exp=st.integers(-36, 36), psf_exp=st.integers(-36, 36),
       variant=st.integers(0, len(_VARIANTS) - 1))
def test_rl_in_float32_at_any_scale(image_exp, psf_exp, variant):
    """float32 Richardson–Lucy (every variant) of an image ×10^i by a PSF ×10^j: the
    estimate ×10^(j − i) of the unscaled problem (it scales with the image and inversely
    with the PSF), or a DiffcamError when an input or the estimate leaves float32's
    range. Among the slow tests (five compilations, 9 s); the default tests keep the
    probes of the float32 range."""
    image = (_SMALL * np.float64(10.0) ** image_exp).astype(np.float32)
    psf = (_KSMALL * np.float64(10.0) ** psf_exp).astype(np.float32)
    try:
        out = _rl(image, psf, variant)
    except DiffcamError as e:
        ratio = image.max() / psf.sum(dtype=np.float64)
        tiny, big = np.finfo(np.float32).tiny, np.finfo(np.float32).max
        assert (psf.max() < tiny or ratio > big / 1e3 or ratio < tiny * 1e3), str(e)
        return
    base = _unscaled(variant)
    got = np.asarray(out.image, np.float64) * 10.0 ** (psf_exp - image_exp)
    assert np.isfinite(np.asarray(out.objective)).all()
    np.testing.assert_allclose(got, base, rtol=0, atol=3e-3 * base.max())


def _admm_problem():
    """A sparse PSF and the image of a random scene through it, at unit L2 norm."""
    rng = np.random.default_rng(1)
    psf = np.zeros((16, 16), np.float32)
    psf[rng.integers(0, 16, 10), rng.integers(0, 16, 10)] = 1
    from scipy.signal import fftconvolve

    image = fftconvolve(rng.random((24, 24)), psf, mode="same").astype(np.float32)
    return image / np.linalg.norm(image), psf


@pytest.mark.parametrize("image_scale, psf_scale", [(1e-25, 1.0), (1e30, 1.0), (1.0, 1e-30),
                                                    (1.0, 1e30), (1e-20, 1e-15)])
def test_admm_tv_at_any_scale(image_scale, psf_scale):
    """float32 ADMM-TV of an image ×a by a PSF ×b, with tau ×a: the estimate ×a/b of
    the unscaled problem to 1e-4 of its peak (a faint image was refused as 'all zeros',
    ×1e30 or a PSF ×1e-30 gave NaN)."""
    image, psf = _admm_problem()
    base = np.asarray(admm_tv(image, psf, 20, progress=False).image, np.float64)
    out = admm_tv((image * np.float64(image_scale)).astype(np.float32),
                  (psf * np.float64(psf_scale)).astype(np.float32), 20, progress=False,
                  tau=1e-4 * image_scale)
    got = np.asarray(out.image, np.float64) * psf_scale / image_scale
    assert np.isfinite(np.asarray(out.residual)).all()
    np.testing.assert_allclose(got, base, rtol=0, atol=1e-4 * base.max())


@pytest.mark.parametrize("image_scale, psf_scale", [(1e30, 1e-30), (1e-30, 1e30)])
def test_admm_tv_refuses_an_estimate_beyond_float32(image_scale, psf_scale):
    """An estimate scale ||image|| / ||psf|| of 1e60 or 1e-60 cannot be a float32: a
    DiffcamError saying so, before the solve."""
    image, psf = _admm_problem()
    with pytest.raises(DiffcamError, match="outside the range of float32"):
        admm_tv((image * image_scale).astype(np.float32),
                (psf * np.float64(psf_scale)).astype(np.float32), 5, progress=False)


_DTYPES = [np.bool_, np.int8, np.uint16, np.int32, np.int64, np.float16, np.float32,
           np.float64, np.complex64, np.object_, np.str_]


@settings(max_examples=10, deadline=None, derandomize=True, database=None)
@given(dtype=st.sampled_from(_DTYPES), which=st.sampled_from("ab"),
       fn=st.sampled_from(["pearson", "mse", "richardson_lucy"]))
def test_any_dtype_is_converted_or_refused(dtype, which, fn):
    """An image (``a``) or a reference or PSF (``b``) of any NumPy dtype: complex,
    object and text data are one DiffcamError naming the dtype; bool, integer and
    float16 data give exactly the result of the same values as float64 (pearson of
    int32 overflowed, of complex returned a complex number)."""
    values = {"a": IMAGE * 100, "b": (IMAGE.T if fn != "richardson_lucy" else KERNEL) * 100}
    if dtype is np.bool_:                      # a mask: light above the median
        values = {k: v > np.median(v) for k, v in values.items()}
    calls = {"pearson": lambda a, b: dc.pearson(a, b), "mse": lambda a, b: mse(a, b),
             "richardson_lucy": lambda a, b: richardson_lucy(a, b, 3).image}
    typed = dict(values)
    typed[which] = values[which].astype(dtype)
    if dtype in (np.complex64, np.object_, np.str_):
        with pytest.raises(DiffcamError, match="complex|dtype") as err:
            calls[fn](typed["a"], typed["b"])
        assert "\n" not in str(err.value)
        return
    as_float = {k: np.asarray(typed[k], np.float64) for k in "ab"}
    got = np.asarray(calls[fn](typed["a"], typed["b"]))
    assert np.isfinite(got).all() and got.dtype.kind == "f"
    np.testing.assert_allclose(got, np.asarray(calls[fn](as_float["a"], as_float["b"])),
                               rtol=1e-5)
