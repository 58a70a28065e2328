"""The strike to plan and the plan: the robot's start state (:class:`StrikeStart`), the
racket target at tau (:class:`StrikeTarget`) and the planner's result (:class:`Plan`).

World frame of ``DESIGN.md``, SI units; joint order and units of :mod:`studio.robot.model`
(gantry x, y [m]; a1..a6 [rad]). Times are relative to the start of the strike (t = 0 at
the switch from the toss).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError, checked_array

FloatArray = npt.NDArray[np.float64]

PlanStatus = Literal["ok", "infeasible", "tolerance", "limits", "collision", "failed"]


def checked_vector(x: npt.ArrayLike, shape: tuple[int, ...], name: str) -> FloatArray:
    """Validated read-only float array (shape, finite) or InvalidInputError naming ``name``."""
    return checked_array(x, shape, name)  # type: ignore[no-any-return]


@dataclass(frozen=True, slots=True)
class StrikeStart:
    """Initial, generally moving, state of the robot at the start of the strike.

    Usually taken from the toss trajectory at the switch time (commands and predicted
    joint state). Joint order of :mod:`studio.robot.model`, units m / rad.
    """

    u: FloatArray
    """Joint commands u0 (8,) [m | rad]."""
    ud: FloatArray
    """Command velocities u0' (8,) [m/s | rad/s]."""
    udd: FloatArray
    """Command accelerations u0'' (8,) [m/s^2 | rad/s^2]."""
    X: FloatArray
    """Predicted joint state X0 (8, 2): columns actual position q and velocity q'."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "u", checked_vector(self.u, (8,), "StrikeStart.u"))
        object.__setattr__(self, "ud", checked_vector(self.ud, (8,), "StrikeStart.ud"))
        object.__setattr__(self, "udd", checked_vector(self.udd, (8,), "StrikeStart.udd"))
        object.__setattr__(self, "X", checked_vector(self.X, (8, 2), "StrikeStart.X"))

    @classmethod
    def at_rest(cls, q: npt.ArrayLike) -> StrikeStart:
        """The robot standing still at configuration q (8,) (command = position)."""
        qa = checked_vector(q, (8,), "StrikeStart.at_rest q")
        z = np.zeros(8)
        return cls(u=qa, ud=z, udd=z, X=np.stack([qa, z], axis=1))


@dataclass(frozen=True, slots=True)
class StrikeTarget:
    """Desired racket state at tau and the end of the strike (paper's xi_s minus the
    initial state). World frame, SI units; times from the start of the strike."""

    tau: float
    """Contact time tau [s] (0 < tau < tau_f)."""
    position: FloatArray
    """p_tau (3,) [m]: racket origin (blade centre) at tau."""
    normal: FloatArray
    """n_tau (3,): racket face-A normal at tau (normalised here)."""
    velocity: FloatArray
    """v_tau (3,) [m/s]: velocity of the racket origin at tau."""
    tau_f: float
    """End of the strike [s]: the command is at rest at u_tauf."""
    u_rest: FloatArray | None = None
    """u_tauf (8,) [m | rad]: final command (None: the robot's q_rest)."""

    def __post_init__(self) -> None:
        for name in ("tau", "tau_f"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(float(v)):
                raise InvalidInputError(f"StrikeTarget.{name}: must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        object.__setattr__(self, "position", checked_vector(self.position, (3,), "StrikeTarget.position"))
        n = checked_vector(self.normal, (3,), "StrikeTarget.normal")
        nn = float(np.linalg.norm(n))
        if nn < 1e-9:
            raise InvalidInputError("StrikeTarget.normal: zero vector")
        n = n / nn
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "velocity", checked_vector(self.velocity, (3,), "StrikeTarget.velocity"))
        if self.u_rest is not None:
            object.__setattr__(self, "u_rest", checked_vector(self.u_rest, (8,), "StrikeTarget.u_rest"))
        if not (0.0 < self.tau < self.tau_f):
            raise InvalidInputError(f"StrikeTarget: need 0 < tau < tau_f, got tau={self.tau}, tau_f={self.tau_f}")


@dataclass(frozen=True, eq=False)
class Plan:
    """Result of :meth:`studio.planning.planner.StrikePlanner.plan` (also for infeasible or invalid targets).

    Trajectories are sampled at ``t = k dt`` (1 kHz) on [0, tau_f], relative to the
    start of the strike; joint order of :mod:`studio.robot.model`. Arrays are empty (shape
    (0, 8)) when no trajectory was produced (status "infeasible" before solving).
    """

    status: PlanStatus
    """"ok", or why the plan is not valid: "infeasible" (no trajectory within the
    limits / bad inputs), "tolerance" (racket errors at tau above tolerance),
    "limits" (a limit broken at 1 kHz), "collision" (set by a collision check),
    "failed" (solver breakdown)."""
    reason: str
    """Human-readable explanation (empty when ok)."""
    target: StrikeTarget
    """The target planned for."""
    start: StrikeStart
    """The initial state planned from."""
    t: FloatArray
    """Sample times (N,) [s]."""
    u: FloatArray
    """Commands (N, 8) [m | rad]."""
    ud: FloatArray
    """Command velocities (N, 8)."""
    udd: FloatArray
    """Command accelerations (N, 8)."""
    q: FloatArray
    """Predicted joint positions (N, 8) (joint dynamics model, exact)."""
    qd: FloatArray
    """Predicted joint velocities (N, 8)."""
    segment_times: FloatArray
    """Segment boundaries (n_l + 1,) [s]; tau is ``segment_times[n_tau]``."""
    n_tau: int
    """Index of the boundary at tau (segments before tau)."""
    jerk: FloatArray
    """Piecewise-constant command jerks (n_l, 8) [m/s^3 | rad/s^3]."""
    q_tau: FloatArray
    """Predicted joint positions at tau (8,)."""
    qd_tau: FloatArray
    """Predicted joint velocities at tau (8,)."""
    position_error: float
    """|p(q_tau) - p_tau| [m] (pinocchio, a posteriori)."""
    angle_error: float
    """Angle between n(q_tau) and n_tau [rad]."""
    velocity_error: float
    """|v(q_tau, qd_tau) - v_tau| [m/s]."""
    slacks: FloatArray
    """Paper's slacks at the solution (3,): position excess [m], ``cos(dphi) - n.n_tau``
    excess [-], velocity excess [m/s] (0 when within tolerance)."""
    jerk_cost: float
    """Scaled jerk cost 1/2 sum_k (h_k / tau_f) |j_k / j_max|^2 [-]."""
    solver: str
    """Solver that produced the trajectory ("sqp-daqp", "ipopt", or "" if none)."""
    iterations: int
    """QPs solved (sqp-daqp) or IPOPT iterations, summed over stages."""
    solve_time_ms: float
    """Wall time of :meth:`studio.planning.planner.StrikePlanner.plan` [ms] (checks included)."""

    @property
    def ok(self) -> bool:
        """True when the plan is valid (status "ok")."""
        return self.status == "ok"

    @property
    def tau(self) -> float:
        """Contact time [s]."""
        return self.target.tau

    def with_status(self, status: PlanStatus, reason: str) -> Plan:
        """A copy with another status and reason (e.g. after a collision check)."""
        return replace(self, status=status, reason=reason)

    @classmethod
    def empty(
        cls, status: PlanStatus, reason: str, target: StrikeTarget, start: StrikeStart, solve_time_ms: float
    ) -> Plan:
        """A plan without a trajectory (refused inputs, or no solver produced one): empty
        arrays, NaN errors and joint states at tau."""
        e8 = np.zeros((0, 8))
        nanv = np.full(8, np.nan)
        return cls(
            status=status,
            reason=reason,
            target=target,
            start=start,
            t=np.zeros(0),
            u=e8,
            ud=e8,
            udd=e8,
            q=e8,
            qd=e8,
            segment_times=np.zeros(0),
            n_tau=0,
            jerk=np.zeros((0, 8)),
            q_tau=nanv,
            qd_tau=nanv,
            position_error=math.nan,
            angle_error=math.nan,
            velocity_error=math.nan,
            slacks=np.full(3, np.nan),
            jerk_cost=math.nan,
            solver="",
            iterations=0,
            solve_time_ms=solve_time_ms,
        )
