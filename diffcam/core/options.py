"""The base of diffcam's options objects (solver settings as one validated value)."""

from __future__ import annotations

import dataclasses

import equinox as eqx

from diffcam.core.errors import DiffcamError

__all__ = ["Options"]


class Options(eqx.Module):
    """Settings of a solver or fit: an equinox Module whose subclasses validate their
    fields in ``__check_init__``. ``Cls.of(options, **overrides)`` is how functions take
    them: ``options`` (default: the class's defaults) with the named fields replaced;
    an instance of a base class (a ``FitOptions`` where a subclass is expected) keeps
    its fields and takes the subclass's defaults for the rest."""

    @classmethod
    def of(cls, options=None, **overrides):
        unknown = set(overrides) - set(cls.__dataclass_fields__)
        if unknown:
            raise DiffcamError(f"unknown option(s) {sorted(unknown)} for {cls.__name__}; "
                               f"its fields are {sorted(cls.__dataclass_fields__)}.")
        if options is not None and not isinstance(options, cls):
            if not (isinstance(options, Options) and issubclass(cls, type(options))):
                raise DiffcamError(f"options must be a {cls.__name__}, got "
                                   f"{type(options).__name__}.")
            options = cls(**{f.name: getattr(options, f.name)
                             for f in dataclasses.fields(options)})
        return dataclasses.replace(options or cls(), **overrides)
