"""The installed diffcam's version."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

__all__ = ["installed_version"]


def installed_version() -> str:
    """The installed distribution's version (pyproject.toml); ``0+unknown`` when diffcam
    runs from a source tree that was never installed."""
    try:
        return version("diffcam")
    except PackageNotFoundError:
        return "0+unknown"
