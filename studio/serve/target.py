"""The racket state a serve asks for at the contact time (world frame, SI units)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class RacketTarget:
    """The racket state the planner is asked to reach at the contact time."""

    position: tuple[float, float, float]
    """Racket centre p_tau [m], world frame."""
    normal: tuple[float, float, float]
    """Unit face normal n_tau, world frame."""
    velocity: tuple[float, float, float]
    """Racket velocity v_tau [m/s], world frame."""
