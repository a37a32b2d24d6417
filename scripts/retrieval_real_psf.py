"""Real data: fit a thin-phase diffuser to 2–3 planes of the measured 44-plane DiffuserCam
PSF stack (Waller Lab, via ``diffcam.data``) and predict the other planes.

Nothing about this camera's geometry was published with the stack (docs/design.md, "Real
data"). The script takes the 3-D DiffuserCam's sensor pixel (6.5 µm) binned 8× (the
stack is 1/8 of 2560×2160: 52 µm), λ = 532 nm as a nominal wavelength, z2 = 8.9 mm and
the nearest plane at z1 = 20 mm as start values, and a rectangular aperture whose
shadow is the measured PSF's footprint, then fits z2 and a 2-parameter depth
model (planes uniform in 1/z1) with the phase; only λz/dx² is identifiable, and is
reported. Each plane is scored by Pearson against the measurement, beside the scaling
baseline with the same depths and registration (magnification about the grid centre):
anchored at plane 0 as the paper does, and anchored at the nearest fitted plane (the same
measurements the model saw).

    python scripts/retrieval_real_psf.py --planes 0,21,43
"""

from __future__ import annotations

import argparse
import json
import time

import jax.numpy as jnp
import numpy as np
import scipy.ndimage

from diffcam.model.camera import Camera
from diffcam.data import load_psf_stack_3d
from diffcam.evaluate.metrics import pearson
from diffcam.optics.elements import rectangular_aperture
from diffcam.calibrate import DepthLaw, fit_to_psfs, predict_psfs
from diffcam.calibrate.psf_fit import depths
from diffcam.evaluate.baseline import magnify_psf

PIXEL, WAVELENGTH, Z2, Z1_NEAR = 8 * 6.5e-6, 532e-9, 8.9e-3, 20e-3


def magnification_ratio(ref, target, dx):
    """Best magnification of ``ref`` onto ``target`` about the grid centre (1-D search)."""
    ms = np.linspace(0.8, 1.05, 51)
    z2 = 1.0  # magnify_psf takes depths; choose z1 so that m = M(z1)/M(z1_ref) is ms
    z1 = z2 / ((1 + z2) * ms - 1)
    scaled = magnify_psf(ref, dx, 1.0, z1[ms * (1 + z2) > 1], z2)
    p = np.asarray(pearson(scaled, jnp.asarray(target)))
    return float(ms[ms * (1 + z2) > 1][int(np.argmax(p))])


def aperture_from_footprint(psf, dx, magnification):
    """The rectangular aperture whose shadow, magnified by ``magnification``, is the PSF's
    footprint (where the smoothed PSF exceeds 15 % of its maximum)."""
    smooth = scipy.ndimage.gaussian_filter(psf, 6)
    ys, xs = np.nonzero(smooth > 0.15 * smooth.max())
    ny, nx = psf.shape
    height, width = (ys.max() - ys.min()) * dx, (xs.max() - xs.min()) * dx
    centre = (((ys.max() + ys.min()) / 2 - ny // 2) * dx, ((xs.max() + xs.min()) / 2 - nx // 2) * dx)
    return rectangular_aperture((ny, nx), dx, height / magnification, width / magnification,
                                (centre[0] / magnification, centre[1] / magnification),
                                edge="soft")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--planes", default="0,21,43")
    ap.add_argument("--iterations", type=int, default=500)
    ap.add_argument("--pad", type=int, default=32)
    ap.add_argument("--upsample", type=int, default=1,
                    help="phase grid this many times finer than the PSF pixels; the model "
                         "integrates over the pixels")
    ap.add_argument("--json")
    args = ap.parse_args()
    stack = load_psf_stack_3d()
    stack = stack - np.median(stack[:, :10, :10], axis=(1, 2), keepdims=True)
    stack = np.maximum(stack, 0)
    nz, ny, nx = stack.shape
    fit_planes = [int(p) for p in args.planes.split(",")]
    # start values: nearest plane at Z1_NEAR, farthest plane from the measured
    # magnification ratio, 1/z1 linear in the plane index in between
    m_far = magnification_ratio(stack[0], stack[-1], PIXEL)
    M0 = 1 + Z2 / Z1_NEAR
    z1_far = Z2 / (M0 * m_far - 1)
    inv = 1 / Z1_NEAR + (1 / z1_far - 1 / Z1_NEAR) * np.arange(nz) / (nz - 1)
    z1_start = 1 / inv
    print(f"plane 43 / plane 0 magnification {m_far:.4f}: start z1 = {z1_start[0] * 1e3:.1f}"
          f" … {z1_start[-1] * 1e3:.1f} mm, z2 = {Z2 * 1e3} mm", flush=True)
    k = args.upsample
    dx = PIXEL / k
    footprint = np.kron(stack[0], np.ones((k, k), np.float32))
    camera = Camera(wavelength=WAVELENGTH, z2=Z2, dx=dx,
                    aperture_mask=aperture_from_footprint(footprint, dx, M0),
                    shape=(ny * k, nx * k), pad=args.pad * k)
    sensor = dict(sensor_pitch=PIXEL) if k > 1 else {}
    t = time.perf_counter()
    # stage 1: the phase with the start geometry; stage 2: phase, z2 and depths together
    r = fit_to_psfs(stack[fit_planes], camera, z1_start[fit_planes],
                    iterations=args.iterations, **sensor)
    r = fit_to_psfs(stack[fit_planes], camera, z1_start[fit_planes], init=r.phase,
                    depth=DepthLaw("inverse_linear", plane_index=fit_planes, fit_z2=True),
                    iterations=args.iterations // 2, **sensor)
    fit_s = time.perf_counter() - t
    z2 = r.stats["z2"]
    z1_all = np.asarray(depths(r.stats["extra"], z1_start[fit_planes], "inverse_linear",
                               fit_planes, at=np.arange(nz)))
    zeta = WAVELENGTH / dx ** 2
    print(f"fit {fit_s:.0f} s, loss {float(r.history[0]):.4g} → {float(r.history[-1]):.4g}; "
          f"z2 = {z2 * 1e3:.3f} mm (ζ2 = λz2/dx² = {z2 * zeta:.4f}), z1 = "
          f"{z1_all[0] * 1e3:.2f} … {z1_all[-1] * 1e3:.2f} mm (phase grid {dx * 1e6:.1f} µm)",
          flush=True)
    pred = predict_psfs(r.phase, camera, z1_all, z2=z2, **sensor)
    meas = jnp.asarray(stack)
    p_model = np.asarray(pearson(jnp.asarray(pred), meas))
    p_scale0 = np.asarray(pearson(magnify_psf(stack[0], PIXEL, z1_all[0], z1_all, z2), meas))
    nearest = [min(fit_planes, key=lambda f: abs(f - k)) for k in range(nz)]
    p_scale_near = np.array([float(pearson(magnify_psf(stack[a], PIXEL, z1_all[a], z1_all[k],
                                                     z2), meas[k]))
                             for k, a in enumerate(nearest)])
    print("\n| plane | z1 (mm) | model | scaling from plane 0 | scaling from nearest fitted |")
    print("| --- | --- | --- | --- | --- |")
    for k in range(nz):
        tag = " (fitted)" if k in fit_planes else ""
        print(f"| {k}{tag} | {z1_all[k] * 1e3:.2f} | {p_model[k]:.4f} | {p_scale0[k]:.4f} | "
              f"{p_scale_near[k]:.4f} |")
    held = [k for k in range(nz) if k not in fit_planes]
    print(f"\nmean over held-out planes: model {p_model[held].mean():.4f}, scaling from "
          f"plane 0 {p_scale0[held].mean():.4f}, scaling from nearest fitted "
          f"{p_scale_near[held].mean():.4f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"planes": fit_planes, "z2": z2, "z1": z1_all.tolist(),
                       "model": p_model.tolist(), "scaling_plane0": p_scale0.tolist(),
                       "scaling_nearest": p_scale_near.tolist(), "fit_s": fit_s}, f, indent=1)


if __name__ == "__main__":
    main()
