"""Numerical settings of :func:`studio.sim.rollout.rollout` and the impulse of non-blade
robot contacts (:class:`RolloutOptions`). SI units."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from studio.errors import InvalidInputError


@dataclass(frozen=True, slots=True)
class RolloutOptions:
    """Numerical settings of :func:`studio.sim.rollout.rollout` and the impulse of non-blade robot contacts."""

    substep: float = 0.25e-3
    """Spacing of the narrowphase grid near a geom [s]; grid points that provably hold no
    contact (conservative advancement) are skipped. At 0.25 ms a ball cannot cross any
    geom of the scene between two grid points below ~170 m/s of relative speed."""
    time_tolerance: float = 1e-9
    """Tolerance of the contact instant found by root finding on the distance [s]."""
    rearm_distance: float = 1e-5
    """A geom the ball has just touched counts again only once the ball has been this far
    from it [m] (one contact is counted once; small enough for near-rest bounces)."""
    sink_depth: float = 1e-3
    """A geom not yet re-armed counts again if the ball sinks this deep into it [m]
    (the geom pushes the ball again before it got away: a double hit / carry)."""
    max_step: float = 0.01
    """RK4 step of the ball flight [s] (the same as :func:`studio.physics.ball.simulate`'s
    default, so free flights agree to round-off)."""
    robot_restitution: float = 0.5
    """Normal restitution [-] of the ball on robot geoms other than the blade faces
    (links, handle, cup, blade rim); tangential velocity and spin are kept (assumption:
    such a contact makes the serve illegal, only its qualitative outcome matters)."""
    stop_on_floor: bool = True
    """End the rollout at the first floor contact (the contact is recorded)."""
    max_contacts: int = 64
    """Safety limit on the number of contacts."""
    rest_speed: float = 0.02
    """Normal rebound speed relative to the touched surface [m/s] below which a contact
    ends the rollout ("rest": the ball would rest or roll on it, which the impulse maps do
    not model)."""
    rim_cosine: float = 0.5
    """Blade contacts whose normal makes an angle with the face normal larger than
    ``acos(rim_cosine)`` (60 deg) hit the rim: simple restitution instead of the rubber model."""

    def __post_init__(self) -> None:
        for name in ("substep", "time_tolerance", "rearm_distance", "sink_depth", "max_step", "rest_speed"):
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0.0):
                raise InvalidInputError(f"RolloutOptions.{name} must be a positive finite number, got {val!r}")
        for name in ("robot_restitution", "rim_cosine"):
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and 0.0 <= val <= 1.0):
                raise InvalidInputError(f"RolloutOptions.{name} must be in [0, 1], got {val!r}")
        if not (isinstance(self.max_contacts, int) and self.max_contacts >= 1):
            raise InvalidInputError(f"RolloutOptions.max_contacts must be an int >= 1, got {self.max_contacts!r}")


DEFAULT_OPTIONS: Final[RolloutOptions] = RolloutOptions()
"""The default settings."""
