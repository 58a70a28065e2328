"""Options of the strike planner: racket tolerances at tau, the paper's slack weights and
the solver settings (:class:`PlannerOptions`). SI units."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final, Literal

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.robot.model import JointLimits

FloatArray = npt.NDArray[np.float64]

N_SEGMENTS: Final[int] = 32
"""Number of constant-jerk segments n_l on [0, tau_f] (paper: 32)."""

COMMAND_DT: Final[float] = 1e-3
"""Command period [s]: the robot takes joint commands at 1 kHz (paper)."""

SolverName = Literal["sqp-daqp", "ipopt"]


@dataclass(frozen=True, slots=True)
class StrikeTolerances:
    """Racket-state tolerances at tau (paper, Table "NMPC racket state tolerances")."""

    position: float = 5e-3
    """Delta p_tau [m]: radius of the position ball."""
    angle: float = math.radians(0.5)
    """Delta phi_tau [rad]: largest angle between the racket normal and n_tau."""
    velocity_abs: float = 0.01
    """Delta v_a,tau [m/s]: absolute velocity tolerance."""
    velocity_rel: float = 0.01
    """Delta v_r,tau [-]: velocity tolerance relative to |v_tau|."""

    def velocity(self, v_tau: FloatArray) -> float:
        """Velocity tolerance [m/s] for the target velocity ``v_tau`` (3,):
        ``max(velocity_abs, velocity_rel * |v_tau|)``."""
        return max(self.velocity_abs, self.velocity_rel * float(np.linalg.norm(v_tau)))


@dataclass(frozen=True, slots=True)
class SlackWeights:
    """Slack weights lambda_p, lambda_n, lambda_v (paper, same table)."""

    position: float = 2.0
    """lambda_p [1/m]."""
    normal: float = 1.0
    """lambda_n [-] (here per rad of normal error, see :class:`PlannerOptions`)."""
    velocity: float = 0.2
    """lambda_v [s/m]."""


@dataclass(frozen=True, slots=True)
class PlannerOptions:
    """Options of :class:`studio.planning.planner.StrikePlanner` (keyword-only construction recommended)."""

    n_segments: int = N_SEGMENTS
    """Number of constant-jerk segments on [0, tau_f] (paper: 32)."""
    dt: float = COMMAND_DT
    """Output sample period [s] (1 kHz)."""
    tolerances: StrikeTolerances = field(default_factory=StrikeTolerances)
    """Tolerances of the a-posteriori check (and, times ``margin``, of IPOPT's constraints)."""
    slack_weights: SlackWeights = field(default_factory=SlackWeights)
    """Slack weights of the paper's table (IPOPT formulation)."""
    slack_scale: float = 1e3
    """Factor on the slack weights relative to the scaled jerk cost (dimensionless, at
    most ~4 with every jerk at its limit), so that the slacks act as an exact penalty:
    zero whenever the tolerances can be met. A slack of one tolerance costs
    ``slack_scale * lambda * tolerance`` (IPOPT formulation)."""
    margin: float = 0.85
    """Fraction of each tolerance used as IPOPT's constraint radius (room for the 1 kHz
    re-evaluation); the a-posteriori check uses the full tolerance. The sqp-daqp
    solver aims at the centre (zero error)."""
    max_iterations: int = 40
    """Iteration cap of each solver stage (reduced and full)."""
    limit_rounds: int = 4
    """How many times violations found at 1 kHz may be added as rows and re-solved."""
    limit_tolerance: float = 1e-6
    """Relative tolerance of the 1 kHz limit check (fraction of each limit)."""
    solver: SolverName = "sqp-daqp"
    """Default solver ("sqp-daqp" or "ipopt")."""
    fallback: bool = True
    """With "sqp-daqp": run IPOPT when the SQP ends outside the tolerances or fails."""
    ipopt_max_iter: int = 300
    """Iteration cap of IPOPT."""
    limits: JointLimits | None = None
    """Joint limits to plan with (None: the robot's; e.g. ``robot.limits.expanded(1.2)``)."""

    def __post_init__(self) -> None:
        if self.n_segments < 10:
            raise InvalidInputError(f"PlannerOptions.n_segments must be >= 10, got {self.n_segments}")
        for name in ("dt", "slack_scale", "margin", "limit_tolerance"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInputError(f"PlannerOptions.{name} must be finite and > 0, got {v!r}")
        if self.margin > 1.0:
            raise InvalidInputError(f"PlannerOptions.margin must be <= 1, got {self.margin}")
        if self.solver not in ("sqp-daqp", "ipopt"):
            raise InvalidInputError(f"PlannerOptions.solver must be 'sqp-daqp' or 'ipopt', got {self.solver!r}")
