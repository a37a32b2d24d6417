"""Lengths with units at the command-line edge: ``"25mm"`` → 0.025 (metres).

Only the CLI parses units; everything inside diffcam takes SI numbers.
"""

from __future__ import annotations

import re

import numpy as np

from diffcam.core.errors import DiffcamError

__all__ = ["parse_length", "parse_length_range"]

_SCALE = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "nm": 1e-9}
# the most values a range may expand to (a step typo such as 20mm:30mm:1nm would ask
# for ten million depths)
MAX_RANGE = 10_000
_PATTERN = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zµμ]*)\s*$")


def parse_length(text: str, *, name: str = "length") -> float:
    """``"25mm"``, ``"3.45um"``, ``"532nm"`` or ``"0.05m"`` → metres.

    A unit is required (a bare ``25`` would be 25 metres, almost never what was meant);
    only ``0`` may go without one.
    """
    m = _PATTERN.match(str(text))
    if not m:
        raise DiffcamError(f"{name}: cannot read {text!r} as a length; write e.g. 25mm, "
                           f"3.45um, 532nm or 0.025m.")
    value, unit = float(m.group(1)), m.group(2)
    if not unit:
        if value != 0:
            raise DiffcamError(f"{name}: {text!r} has no unit; write e.g. {m.group(1)}mm, "
                               f"{m.group(1)}um or {m.group(1)}m.")
        unit = "m"
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
    if count > MAX_RANGE:
        raise DiffcamError(f"{name}: {text!r} expands to {count} values (limit {MAX_RANGE}); "
                           f"check the step.")
    return start + step * np.arange(count)
