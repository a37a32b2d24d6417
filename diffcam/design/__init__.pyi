"""Stub of [`diffcam.design`][diffcam.design]: its public names and the modules they come
from.

diffcam/design/__init__.py imports each on first use
([`diffcam.core.lazy`][diffcam.core.lazy])."""

from diffcam.design.design_file import load_design, save_design, tiff_path
from diffcam.design.end_to_end import EndToEndObjective, end_to_end_objective, training_volumes
from diffcam.design.objective import DepthObjective, depth_objective
from diffcam.design.optimise import depth_range, design, evaluate_design
from diffcam.design.result import Design, DesignOptions
from diffcam.design.surfaces import LensletArray, SmoothSurface, height_map, lenslet_table

__all__ = ["SmoothSurface", "LensletArray", "height_map", "lenslet_table", "DepthObjective",
           "depth_objective", "EndToEndObjective", "end_to_end_objective",
           "training_volumes", "design", "depth_range", "evaluate_design", "Design",
           "DesignOptions", "save_design", "load_design", "tiff_path"]
