"""Reading real captures, and the preprocessing steps that make them fit to reconstruct.

The I/O edge: files come in as 8/16-bit PNG or TIFF, float ``.npy`` or MATLAB ``.mat``
PSF stacks; they leave as float32 NumPy arrays in sensor counts with colour channels on
a leading axis. Each preprocessing step is a separate, tested function, applied in this
order (LenslessPiCam-style, as the DiffuserCam tutorial does it)::

    capture = read_image("raw.tif")                       # counts, (ny, nx) or (c, ny, nx)
    mask = saturation_mask(capture)                       # pixels at full scale
    level = dark_level(psf_capture.image, (slice(5, 15), slice(5, 15)))
    image = subtract_background(capture.image, level)     # small negatives clipped
    image = downsample(image, 4)                          # box average
    image = normalise_l2(image)
    window = fit_sensor_window(image, psfs)     # volumes: admm_tv_3d's sensor_response
    terms = fit_field_terms(image, psfs, z1, z2, pixel_pitch)   # the off-axis terms

Everything here is NumPy (files are read once, outside ``jit``); the results go to the
JAX solvers in [`diffcam.reconstruct`][diffcam.reconstruct].

Both directions are guarded at this edge. Readers turn every damaged, truncated or
oversized file into one [`DiffcamError`][diffcam.core.errors.DiffcamError] line naming the
file and the problem, and they check the size a header declares against
[`MAX_READ_BYTES`][diffcam.io.MAX_READ_BYTES] before allocating anything. Writers check the
output path with [`check_output_path`][diffcam.io.writing.check_output_path] before any work
starts and write through [`atomic_output`][diffcam.io.writing.atomic_output]: a temporary
file beside the target, fsynced and moved into place with ``os.replace``, so an existing
file is either untouched or wholly replaced.
"""


from __future__ import annotations

from diffcam.io.field_terms import (FIELD_TERMS, AcceptanceSplit, FieldTerms,
                                    acceptance_split, fit_field_terms)
from diffcam.io.preprocessing import (BackgroundWarning, apply_envelope,
                                      SensorWindow, border_dark_level, dark_level,
                                      downsample, envelope_widths, fit_sensor_window,
                                      normalise_l2, plane_light, saturation_mask,
                                      subtract_background)
from diffcam.io.reading import (IMAGE_SUFFIXES, Capture, as_rgb, check_read_size,
                                file_kind, image_files, natural_key, npz_keys, read_image,
                                read_mat_stack, read_npz, read_psf_stack, read_rgb)
from diffcam.io.writing import (Terminated, atomic_output, check_output_path,
                                interrupts_as_keyboard_interrupt, make_output_folder,
                                temporary_files)

__all__ = [
    "Capture", "read_image", "read_rgb", "as_rgb", "read_psf_stack", "image_files",
    "natural_key", "IMAGE_SUFFIXES", "border_dark_level", "plane_light", "read_mat_stack", "dark_level",
    "subtract_background", "saturation_mask", "downsample", "normalise_l2",
    "envelope_widths", "apply_envelope", "SensorWindow", "fit_sensor_window",
    "FIELD_TERMS", "FieldTerms", "fit_field_terms", "AcceptanceSplit", "acceptance_split",
    "BackgroundWarning", "read_npz", "npz_keys",
    "file_kind", "check_read_size",
    "check_output_path", "make_output_folder", "atomic_output", "Terminated",
    "temporary_files",
    "interrupts_as_keyboard_interrupt", "MAX_READ_BYTES",
]

MAX_READ_BYTES = 4 * 2**30
"""The largest array (bytes, as float32 or the file's own type if wider) a reader will
allocate: 4 GiB. A header declaring more is refused before anything is read, since a
damaged or crafted header can declare terabytes. Raise it for a genuinely larger file,
per call (``max_bytes=``) or for the session (``diffcam.io.MAX_READ_BYTES = 2**36``)."""
