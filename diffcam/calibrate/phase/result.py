"""The result every phase-retrieval solver returns."""

from __future__ import annotations

from typing import NamedTuple

from jax import Array
from jaxtyping import Complex, Float

__all__ = ["RetrievalResult"]


class RetrievalResult(NamedTuple):
    """Retrieved diffuser phase, with the error history and solver statistics.

    Attributes:
        phase: θd at the diffuser plane, radians in [−π, π); meaningful inside the
            aperture only, and defined up to a piston and the conjugate twin.
        field: the retrieved diffuser-plane field (complex, the solver's scale).
        history: per-iteration error of the returned run, the quantity the solver
            minimises: for projections the relative near-amplitude misfit of the
            far-projected iterate ‖|P_M u| − A_near‖/‖A_near‖, for least squares the loss.
        stats: solver statistics: ``method``, ``iterations``, ``wall_time`` (s) and
            solver-specific entries (``restart_errors``, ``best``, ``scale``, ...).
    """

    phase: Float[Array, "ny nx"]
    field: Complex[Array, "ny nx"]
    history: Float[Array, " iterations"]
    stats: dict
