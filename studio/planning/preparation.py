"""The preparation phase of a serve: from the pose at the ball feeder a rest-to-rest
quintic to the toss's first command, then a hold, slow enough to keep the ball in the cup
(:func:`preparation_phase`). 1 kHz commands at the interval midpoints (the planner's
convention), predicted states at the samples; joint order and units of
:mod:`studio.robot.model`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.planning.options import COMMAND_DT
from studio.planning.strike import checked_vector
from studio.robot.cup_hold import CupGrip, CupHoldCheck, check_cup_hold
from studio.robot.model import JointLimits, Robot

FloatArray = npt.NDArray[np.float64]


def quintic(q0: FloatArray, q1: FloatArray, T: float, dt: float) -> tuple[FloatArray, ...]:
    """Quintic minimum-jerk rest-to-rest motion q0 -> q1 (8,) of duration T [s] (a multiple
    of dt), sampled at the interval midpoints: (u, ud, udd), each (T / dt, 8)."""
    n = int(round(T / dt))
    s = (np.arange(n) + 0.5) * dt / T
    p = 10 * s**3 - 15 * s**4 + 6 * s**5
    pd = (30 * s**2 - 60 * s**3 + 30 * s**4) / T
    pdd = (60 * s - 180 * s**2 + 120 * s**3) / T**2
    d = (q1 - q0)[None]
    return q0[None] + p[:, None] * d, pd[:, None] * d, pdd[:, None] * d


def _rest_to_rest(
    q0: FloatArray, q1: FloatArray, limits: JointLimits, dt: float
) -> tuple[float, FloatArray, FloatArray, FloatArray]:
    """Quintic minimum-jerk rest-to-rest joint motion, duration chosen from the limits
    (peak |u'| = 1.875 D/T, |u''| = 5.774 D/T^2, |u'''| = 60 D/T^3 for a distance D),
    rounded up to dt. Returns (T, u, ud, udd) sampled at the interval midpoints."""
    D = np.abs(q1 - q0)
    T = float(
        np.max(
            np.concatenate(
                [
                    1.875 * D / limits.velocity,
                    np.sqrt(5.774 * D / limits.acceleration),
                    np.cbrt(60.0 * D / limits.jerk),
                    [dt],
                ]
            )
        )
    )
    T = math.ceil(T / dt - 1e-9) * dt
    u, ud, udd = quintic(q0, q1, T, dt)
    return T, u, ud, udd


MAX_PREPARATION_TIME: Final[float] = 10.0
"""Longest preparation motion tried [s] before giving up on keeping the ball in the cup."""


@dataclass(frozen=True, eq=False)
class PreparationPhase:
    """Feeder pose to the toss's first command, then a hold: the first part of a serve
    (1 kHz, commands at the interval midpoints as :class:`~studio.planning.strike.Plan`; states at the samples)."""

    u: FloatArray
    """Commands (P, 8)."""
    ud: FloatArray
    """Command velocities (P, 8)."""
    udd: FloatArray
    """Command accelerations (P, 8)."""
    q: FloatArray
    """Predicted joint positions (P, 8) from rest at the start pose."""
    qd: FloatArray
    """Predicted joint velocities (P, 8)."""
    max_tilt: float
    """Largest racket-normal tilt from vertical over the phase [rad] (the ball rides in the cup)."""
    motion_time: float = 0.0
    """Duration of the quintic [s] (the hold follows)."""
    cup: CupHoldCheck | None = None
    """The ball-in-cup check of the whole phase (motion and hold), on its clock (t = 0 at its start)."""

    @property
    def duration(self) -> float:
        """Length of the phase [s] (the toss starts then)."""
        return self.u.shape[0] * COMMAND_DT


def held_quintic(
    robot: Robot, q0: FloatArray, u1: FloatArray, T: float, n_hold: int, dt: float
) -> tuple[FloatArray, ...]:
    """Quintic q0 -> u1 of duration T [s], then ``n_hold`` samples holding u1, with the
    predicted states from rest at q0: (u, ud, udd, X (P, 8, 2))."""
    pu, pud, pudd = quintic(q0, u1, T, dt)
    pu = np.vstack([pu, np.repeat(u1[None], n_hold, axis=0)])
    pud = np.vstack([pud, np.zeros((n_hold, 8))])
    pudd = np.vstack([pudd, np.zeros((n_hold, 8))])
    return pu, pud, pudd, robot.dynamics.simulate(pu, dt, np.stack([q0, np.zeros(8)], axis=1))


def cup_check(robot: Robot, parts: tuple[FloatArray, ...], dt: float, grip: CupGrip) -> CupHoldCheck:
    """Ball-in-cup check of :func:`held_quintic`'s output."""
    pu, _, _, X = parts
    return check_cup_hold(robot, np.arange(pu.shape[0]) * dt, pu, X[:, :, 0], X[:, :, 1], grip=grip)


def _cup_safe_duration(
    robot: Robot, q0: FloatArray, u1: FloatArray, T0: float, n_hold: int, dt: float, grip: CupGrip
) -> tuple[float, tuple[FloatArray, ...], CupHoldCheck]:
    """Shortest quintic duration T >= T0 [s] (on the dt grid) whose motion and hold keep
    the ball in the cup: doubling from T0 until the check passes, then bisection down to
    dt. The returned duration is always a checked one (the ratio need not be monotone in
    T, so it is the shortest found, not proven shortest).

    Raises:
        InvalidInputError: not even :data:`MAX_PREPARATION_TIME` keeps the ball in the cup
            (e.g. a start or end pose tilted beyond the cone).
    """
    parts = held_quintic(robot, q0, u1, T0, n_hold, dt)
    check = cup_check(robot, parts, dt, grip)
    lo = hi = T0
    while not check.passed:
        if hi >= MAX_PREPARATION_TIME:
            raise InvalidInputError(
                f"preparation: the ball does not stay in the cup even with a {hi:.2f} s motion ({check.detail})"
            )
        lo, hi = hi, min(math.ceil(2.0 * hi / dt) * dt, MAX_PREPARATION_TIME)
        parts = held_quintic(robot, q0, u1, hi, n_hold, dt)
        check = cup_check(robot, parts, dt, grip)
    best = (hi, parts, check)
    while best[0] - lo > 1.5 * dt:
        mid = math.ceil(0.5 * (lo + best[0]) / dt - 1e-9) * dt
        parts = held_quintic(robot, q0, u1, mid, n_hold, dt)
        check = cup_check(robot, parts, dt, grip)
        if check.passed:
            best = (mid, parts, check)
        else:
            lo = mid
    return best


def preparation_phase(
    robot: Robot,
    u_toss0: npt.ArrayLike,
    *,
    limits: JointLimits | None = None,
    q_start: npt.ArrayLike | None = None,
    settle: float = 0.3,
    dt: float = COMMAND_DT,
    grip: CupGrip | None = None,
) -> PreparationPhase:
    """The preparation of the paper: from ``q_start`` (default ``robot.q_flat``, the pose
    at the ball feeder) a rest-to-rest quintic to the toss's first command ``u_toss0``
    (8,), then ``settle`` seconds of hold so the joints are at rest when the toss starts
    (its predicted states assume so).

    The ball rides in the cup all along: the quintic is the shortest (on the 1 kHz grid)
    that is within the joint limits *and* keeps the cup's specific force inside the
    holding cone ``grip`` (default: the robot's cup, :class:`studio.robot.cup_hold.CupGrip`) at
    every sample of the motion and the hold; the check is :attr:`PreparationPhase.cup`.

    Raises:
        InvalidInputError: bad inputs, or no duration up to :data:`MAX_PREPARATION_TIME`
            keeps the ball in the cup.
    """
    if not (math.isfinite(settle) and settle >= 0.0):
        raise InvalidInputError(f"preparation: settle must be >= 0 s, got {settle}")
    q0 = checked_vector(robot.q_flat if q_start is None else q_start, (8,), "preparation q_start")
    u1 = checked_vector(u_toss0, (8,), "preparation u_toss0")
    T0, *_ = _rest_to_rest(q0, u1, limits if limits is not None else robot.limits, dt)
    grip = grip if grip is not None else CupGrip.of(robot)
    T, (pu, pud, pudd, X), check = _cup_safe_duration(robot, q0, u1, T0, int(round(settle / dt)), dt, grip)
    tilt = [math.acos(float(np.clip(robot.fk(qq).normal[2], -1.0, 1.0))) for qq in X[::10, :, 0]]
    return PreparationPhase(pu, pud, pudd, X[:, :, 0], X[:, :, 1], max(tilt) if tilt else 0.0, T, check)
