"""Stub of [`diffcam.model`][diffcam.model]: its public names and the modules they come
from.

diffcam/model/__init__.py imports each on first use
([`diffcam.core.lazy`][diffcam.core.lazy])."""

from diffcam.model.camera import Camera, HeightMap, Spectrum, random_diffuser, with_method
from diffcam.model.field import (FieldPSF, chief_rays, field_psf, load_field_psf,
                                 save_field_psf)
from diffcam.model.point_spread import psf
from diffcam.model.stack_map import psf_loss, psf_map
from diffcam.model.stack import (PsfStackOptions, iter_psf_stack, load_stack, psf_stack,
                                 save_stack)

__all__ = ["Camera", "HeightMap", "Spectrum", "random_diffuser", "psf", "psf_map", "psf_loss",
           "psf_stack",
           "iter_psf_stack", "PsfStackOptions", "save_stack", "load_stack", "with_method",
           "FieldPSF", "field_psf", "chief_rays", "save_field_psf", "load_field_psf"]
