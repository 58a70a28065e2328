"""What a toss should do: the option objects of :func:`studio.toss.synthesis.make_toss`.

:class:`TossDesign` holds the rise of the ball, the start pose (:class:`TossPose`), the
shape of the vertical lift (:class:`studio.toss.lift_profile.LiftShape`) and the move that
clears the falling ball's path (:class:`ClearMove`). The defaults (found by a search over
start pose and profile times on the shipped robot) give the shipped tosses: a 0.35 m rise,
release at x = -1.649 m (0.28 m behind the end line), z = 0.419 m, 2.68 m/s, 0.359 s after
the start, within 90 % of every velocity, acceleration and jerk limit. World frame, SI
units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

from studio import constants as C
from studio.errors import InvalidInputError
from studio.toss.lift_profile import LiftShape


def _check_at_least(owner: str, name: str, value: float, lo: float) -> None:
    """InvalidInputError unless ``value`` is finite and >= ``lo``."""
    if not (math.isfinite(value) and value >= lo):
        raise InvalidInputError(f"{owner}.{name} must be finite and >= {lo}, got {value}")


@dataclass(frozen=True, slots=True)
class TossPose:
    """Start pose of a toss, derived from ``robot.q_flat`` (the racket orientation of
    ``q_flat`` is kept)."""

    lateral: float = 0.30
    """Distance of the cup from the robot's centre line ``y = 0`` [m] (right toss at
    ``y = -lateral``, left at ``+lateral``)."""
    start_height: float | None = 0.04
    """Cup centre height at the start [m] (``None``: that of ``q_flat``); low (4 cm: the
    ball 2 cm above the table level) so that the arm has room to lift the ball within
    its limits."""
    gantry_x: float | None = -0.40
    """Gantry X position at the start [m] (``None``: that of ``q_flat``); the arm's start
    pose puts the cup at the ``q_flat`` x, and the cup stays on that x during the lift
    (the gantry moves back by the arm's x drift, ~0.17 m)."""

    def __post_init__(self) -> None:
        _check_at_least("TossPose", "lateral", self.lateral, 0.0)


@dataclass(frozen=True, slots=True)
class ClearMove:
    """How the racket gets out of the falling ball's path after the release: the gantry's
    Y axis steps aside, then the cup is lowered (rest-to-rest degree-9 smoothsteps)."""

    side: float = 0.08
    """Sideways move of the racket (gantry Y, away from ``y = 0``) [m]."""
    drop: float = 0.15
    """Lowering of the cup once the lift has stopped [m] (at most the lift's travel)."""
    delay: float = 0.06
    """Start of the sideways move after the (designed) release [s]; the ball must have
    risen out of the cup by then."""
    time: float = 0.40
    """Duration of the sideways move and of the lowering [s]."""

    def __post_init__(self) -> None:
        for name, lo in (("side", 0.0), ("drop", 0.0), ("delay", 0.0), ("time", 1e-3)):
            _check_at_least("ClearMove", name, getattr(self, name), lo)


@dataclass(frozen=True, slots=True)
class TossDesign:
    """A flat-racket toss that releases the ball vertically (see
    :func:`studio.toss.synthesis.make_toss`)."""

    rise: float = 0.35
    """Rise of the ball above the release point [m], in air (drag of the ball flight
    model); >= :data:`studio.constants.TOSS_MIN_RISE` (ITTF 2.6.2)."""
    pose: TossPose = field(default_factory=TossPose)
    """Start pose (lateral offset, start height, gantry X)."""
    lift: LiftShape = field(default_factory=LiftShape)
    """Lift acceleration and ramp times of the cup's vertical motion."""
    clear: ClearMove = field(default_factory=ClearMove)
    """The move that clears the falling ball's path."""
    drag_k: float | None = None
    """Ball drag constant ``k = rho C_D A / (2 m)`` [1/m] (``None``: the flight model's)."""

    def __post_init__(self) -> None:
        _check_at_least("TossDesign", "rise", self.rise, C.TOSS_MIN_RISE)


DEFAULT_DESIGN: Final[TossDesign] = TossDesign()
"""The design of the shipped tosses."""
