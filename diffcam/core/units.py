"""Lengths with units at the command-line edge: ``"25mm"`` → 0.025 (metres).

Only the CLI parses units; everything inside diffcam takes SI numbers.
"""

from __future__ import annotations

import re

import numpy as np

from diffcam.core.errors import DiffcamError

__all__ = ["parse_length", "parse_length_range"]

_SCALE = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "nm": 1e-9}
_PATTERN = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zµμ]*)\s*$")


def parse_length(text: str, *, name: str = "length") -> float:
    """``"25mm"``, ``"3.45um"``, ``"532nm"``, ``"0.05m"`` or ``"1e-3"`` (metres) → metres."""
    m = _PATTERN.match(str(text))
    if not m:
        raise DiffcamError(f"{name}: cannot read {text!r} as a length; write e.g. 25mm, "
                           f"3.45um, 532nm or 0.025 (metres).")
    value, unit = float(m.group(1)), m.group(2) or "m"
    if unit not in _SCALE:
        raise DiffcamError(f"{name}: unknown unit {unit!r} in {text!r}; use one of "
                           f"{', '.join(sorted(set(_SCALE) - {'μm'}))}.")
    return value * _SCALE[unit]


def parse_length_range(text: str, *, name: str = "range") -> np.ndarray:
    """``"22mm:30mm:1mm"`` → [22, 23, …, 30] mm in metres (the end is included);
    a single length or a comma-separated list also works."""
    parts = str(text).split(":")
    if len(parts) == 1:
        return np.array([parse_length(p, name=name) for p in parts[0].split(",")])
    if len(parts) != 3:
        raise DiffcamError(f"{name}: write a range as start:stop:step, e.g. 22mm:30mm:1mm; "
                           f"got {text!r}.")
    start, stop, step = (parse_length(p, name=name) for p in parts)
    if step <= 0 or stop < start:
        raise DiffcamError(f"{name}: need start ≤ stop and step > 0, got {text!r}.")
    count = int(np.floor((stop - start) / step + 1e-9)) + 1
    return start + step * np.arange(count)
