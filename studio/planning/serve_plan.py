"""A whole serve on one 1 kHz clock: preparation, toss, strike (and return to rest), then
a hold until the joints settle. :func:`plan_serve` plans it (:class:`ServePlan`);
:func:`serve_arrays` assembles the exported arrays of a motion (:class:`ServeArrays`).

Commands follow the planner's convention (``u[k]`` held over [t_k, t_k + dt), the
underlying cubic at the interval midpoint); ``q``, ``qd`` are the predicted joint states
at t_k. Joint order and units of :mod:`studio.robot.model`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.planning.options import COMMAND_DT
from studio.planning.planner import StrikePlanner
from studio.planning.preparation import PreparationPhase, preparation_phase
from studio.planning.settle import SETTLE, SettleTolerance, settle_hold
from studio.planning.strike import Plan, StrikeStart, StrikeTarget
from studio.robot.cup_hold import CupGrip, CupHoldCheck, check_cup_hold
from studio.robot.model import JointDynamics, Robot

FloatArray = npt.NDArray[np.float64]


class TossCommands(Protocol):
    """What a serve takes from a toss (a :class:`studio.toss.primitive.TossPrimitive`):
    its 1 kHz commands, their derivatives and the predicted joint states."""

    @property
    def t(self) -> FloatArray:
        """Sample times (N,) [s] on the toss clock."""
        ...

    @property
    def u(self) -> FloatArray:
        """Joint commands (N, 8)."""
        ...

    @property
    def ud(self) -> FloatArray:
        """Command velocities (N, 8)."""
        ...

    @property
    def udd(self) -> FloatArray:
        """Command accelerations (N, 8)."""
        ...

    @property
    def uddd(self) -> FloatArray:
        """Command jerks (N, 8)."""
        ...

    @property
    def X(self) -> FloatArray:
        """Predicted joint states (N, 8, 2): position, velocity."""
        ...

    @property
    def dt(self) -> float:
        """Command period [s]."""
        ...

    def index_at(self, time: float) -> int:
        """Index of the sample at or just before ``time`` [s]."""
        ...


class _ReleaseTime(Protocol):
    @property
    def time(self) -> float:
        """Release time [s] on the toss clock."""
        ...


class TossHold(Protocol):
    """What the ball-in-cup check takes from a toss (a :class:`studio.toss.primitive.TossPrimitive`)."""

    @property
    def u(self) -> FloatArray:
        """Joint commands (N, 8)."""
        ...

    @property
    def X(self) -> FloatArray:
        """Predicted joint states (N, 8, 2): position, velocity."""
        ...

    @property
    def dt(self) -> float:
        """Command period [s]."""
        ...

    @property
    def release(self) -> _ReleaseTime:
        """The predicted release of the ball from the cup."""
        ...


class ServeToss(TossCommands, TossHold, Protocol):
    """A toss as :func:`plan_serve` takes it (a :class:`studio.toss.primitive.TossPrimitive`)."""


@dataclass(frozen=True, eq=False)
class ServePlan:
    """One command trajectory at 1 kHz for a whole serve (see :func:`plan_serve`).

    Times on the serve clock: t = 0 at the start of the preparation. Commands follow
    the planner's convention (``u[k]`` held over [t_k, t_k + dt), the underlying
    cubic at the interval midpoint); ``q``, ``qd`` are the predicted joint states at t_k.
    A planned strike ends with the rest command held until the predicted joints are at
    rest (:func:`~studio.planning.settle.settle_hold`, ``settle_samples`` samples).
    """

    t: FloatArray
    """Sample times (N,) [s]."""
    u: FloatArray
    """Joint commands (N, 8)."""
    ud: FloatArray
    """Command velocities (N, 8)."""
    udd: FloatArray
    """Command accelerations (N, 8)."""
    q: FloatArray
    """Predicted joint positions (N, 8)."""
    qd: FloatArray
    """Predicted joint velocities (N, 8)."""
    t_toss: float
    """Serve-clock time of the first toss command [s]."""
    t_switch: float
    """Serve-clock time at which the strike takes over [s]."""
    t_contact: float
    """Serve-clock contact time (strike tau) [s]."""
    strike: Plan
    """The strike plan (status, reason, errors at tau, ...)."""
    max_preparation_tilt: float
    """Largest angle [rad] of the racket normal from +Z during the preparation."""
    cup: CupHoldCheck | None = None
    """Ball-in-cup check of preparation + toss up to the release (serve clock)."""
    settle_samples: int = 0
    """Samples of the final hold of the rest command (part of the arrays)."""

    @property
    def ok(self) -> bool:
        """True when the strike plan is valid."""
        return self.strike.ok


@dataclass(frozen=True, eq=False)
class ServeArrays:
    """A whole serve on one 1 kHz clock as exported (:mod:`studio.library.store`): preparation
    (if any), toss, strike, return to rest and a final hold of the rest command until the
    predicted joints are at rest (:func:`~studio.planning.settle.settle_hold`)."""

    t: FloatArray
    """Sample times (N,) [s], from 0 when a preparation leads (else the motion's clock)."""
    u: FloatArray
    """Commands (N, 8) [m | rad], u[k] sent at t_k and held until t_k+1."""
    q: FloatArray
    """Predicted joint positions at t_k (N, 8) [m | rad]."""
    qd: FloatArray
    """Predicted joint velocities at t_k (N, 8) [m/s | rad/s]."""
    t_toss: float
    """Time of the first toss command [s]."""
    settle_samples: int
    """Samples of the final hold appended after the motion's last command."""


def serve_arrays(
    t: npt.ArrayLike,
    u: npt.ArrayLike,
    q: npt.ArrayLike,
    qd: npt.ArrayLike | None,
    dynamics: JointDynamics,
    *,
    preparation: PreparationPhase | None = None,
    tol: SettleTolerance = SETTLE,
) -> ServeArrays:
    """Assemble the exported arrays of a motion (toss clock: times t (M,) [s] at 1 kHz,
    commands u, predicted q and qd (M, 8); qd None: central differences of q): the
    preparation before it (times shifted so that it starts at 0), then the motion, then
    the hold of its last command until the joints settle (``tol``)."""
    T, U, Q = (np.asarray(a, dtype=float) for a in (t, u, q))
    if T.ndim != 1 or T.size < 2 or U.shape != (T.size, 8) or Q.shape != U.shape:
        raise InvalidInputError(
            f"serve_arrays: t (M >= 2,), u and q (M, 8) expected, got {T.shape}, {U.shape}, {Q.shape}"
        )
    dt = float(T[1] - T[0])
    QD = np.gradient(Q, T, axis=0) if qd is None else np.asarray(qd, dtype=float)
    tail = settle_hold(U[-1], np.stack([Q[-1], QD[-1]], axis=1), dynamics, dt=dt, tol=tol)
    n = tail.shape[0]
    T = np.concatenate([T, T[-1] + dt * np.arange(1, n + 1)])
    U, Q, QD = (
        np.vstack([U, np.repeat(U[-1:], n, axis=0)]),
        np.vstack([Q, tail[:, :, 0]]),
        np.vstack([QD, tail[:, :, 1]]),
    )
    if preparation is None:
        return ServeArrays(T, U, Q, QD, float(T[0]), n)
    P = preparation.u.shape[0]
    t_toss = P * dt
    return ServeArrays(
        np.concatenate([np.arange(P) * dt, T - T[0] + t_toss]),
        np.vstack([preparation.u, U]),
        np.vstack([preparation.q, Q]),
        np.vstack([preparation.qd, QD]),
        t_toss,
        n,
    )


def serve_cup_check(
    robot: Robot, preparation: PreparationPhase, toss: TossHold, *, grip: CupGrip | None = None
) -> CupHoldCheck:
    """The ball-in-cup check of preparation + toss on the serve clock (t = 0 at the start of
    the preparation), at every 1 kHz sample before the toss's predicted release from the
    cup (``toss.release.time``, where the normal load vanishes; the ball flies from then on).

    ``toss``: a :class:`studio.toss.primitive.TossPrimitive` (u, X, release, dt)."""
    dt = float(toss.dt)
    tu, tX = np.asarray(toss.u), np.asarray(toss.X)
    P = preparation.u.shape[0]
    t = np.arange(P + tu.shape[0]) * dt
    u = np.vstack([preparation.u, tu])
    q, qd = np.vstack([preparation.q, tX[:, :, 0]]), np.vstack([preparation.qd, tX[:, :, 1]])
    t_end = P * dt + float(toss.release.time)
    return check_cup_hold(robot, t, u, q, qd, t_end=t_end, grip=grip)


def start_from_toss(toss: TossCommands, t_switch: float) -> tuple[StrikeStart, int]:
    """Strike start state at the toss sample k at or before ``t_switch`` (toss clock):
    the predicted joint state ``toss.X[k]`` (at t_k) and the command state moved from
    the sample's interval midpoint (the commands' convention, see :class:`~studio.planning.strike.Plan`) back
    to t_k with the toss's jerk. Returns (start, k); the strike's first command then
    continues ``toss.u[:k]`` seamlessly."""
    k = int(toss.index_at(t_switch))
    tu, tud, tudd, tuddd, tX = (np.asarray(getattr(toss, f)) for f in ("u", "ud", "udd", "uddd", "X"))
    h = 0.5 * float(getattr(toss, "dt", COMMAND_DT))
    u0 = tu[k] - tud[k] * h + tudd[k] * h**2 / 2 - tuddd[k] * h**3 / 6
    ud0 = tud[k] - tudd[k] * h + tuddd[k] * h**2 / 2
    udd0 = tudd[k] - tuddd[k] * h
    return StrikeStart(u=u0, ud=ud0, udd=udd0, X=tX[k]), k


def plan_serve(
    planner: StrikePlanner,
    toss: ServeToss,
    target: StrikeTarget,
    *,
    t_switch: float,
    q_start: npt.ArrayLike | None = None,
    settle: float = 0.3,
    warm_start: Plan | None = None,
) -> ServePlan:
    """Plan a whole serve as one 1 kHz command trajectory, continuous up to acceleration:

    1. preparation: rest-to-rest quintic in joint space from ``q_start`` (default: the
       robot's ``q_flat``, e.g. the pose at the ball feeder) to the toss's first command,
       then ``settle`` seconds of hold so the joints are at rest when the toss starts
       (its predicted states assume so), slow enough to keep the ball in the cup
       (:func:`~studio.planning.preparation.preparation_phase`; ``cup`` checks preparation +
       toss up to the release);
    2. the toss commands ``toss.u`` up to the switch sample (``toss.index_at(t_switch)``);
    3. the strike from the toss's command and predicted joint state at the switch
       (the command state is moved from the sample's midpoint back to the sample time
       with the toss's jerk), ending at rest at ``target.u_rest`` (return to rest),
       then holding it until the predicted joints are at rest
       (:func:`~studio.planning.settle.settle_hold`).

    Args:
        planner: the strike planner.
        toss: a :class:`studio.toss.primitive.TossPrimitive` (t, u, ud, udd, uddd, X, dt, index_at).
        target: strike target with tau, tau_f on the *strike* clock (from the switch).
        t_switch: switch time on the toss clock [s].
        q_start: preparation start (8,) (default ``robot.q_flat``).
        settle: hold before the toss [s].
        warm_start: previous strike plan to seed the planner.

    Returns:
        The :class:`ServePlan` (check ``.ok`` / ``.strike.reason``).

    Raises:
        InvalidInputError: bad inputs (non-finite, wrong shapes, switch outside the toss).
    """
    robot = planner.robot
    dt = planner.options.dt
    if abs(getattr(toss, "dt", dt) - dt) > 1e-12:
        raise InvalidInputError(f"plan_serve: toss dt {getattr(toss, 'dt', None)} differs from the planner's {dt}")
    if not (math.isfinite(t_switch) and 0.0 <= t_switch < float(toss.t[-1])):
        raise InvalidInputError(f"plan_serve: t_switch = {t_switch} s outside the toss [0, {float(toss.t[-1])}]")
    tu, tud, tudd, tX = (np.asarray(getattr(toss, f)) for f in ("u", "ud", "udd", "X"))
    start, k = start_from_toss(toss, t_switch)
    # 1. Preparation and hold.
    prep = preparation_phase(robot, tu[0], limits=planner.limits, q_start=q_start, settle=settle, dt=dt)
    pu, pud, pudd = prep.u, prep.ud, prep.udd
    n_p = pu.shape[0]
    # 3. Strike from the toss state at sample k (command state moved to t_k).
    strike = planner.plan(start, target, warm_start=warm_start)
    t_toss = n_p * dt
    t_sw = t_toss + k * dt
    su, sud, sudd, sq, sqd = _strike_with_hold(strike, robot.dynamics, dt)
    u = np.vstack([pu, tu[:k], su])
    n = u.shape[0]
    return ServePlan(
        t=np.arange(n, dtype=np.float64) * dt,
        u=u,
        ud=np.vstack([pud, tud[:k], sud]),
        udd=np.vstack([pudd, tudd[:k], sudd]),
        q=np.vstack([prep.q, tX[:k, :, 0], sq]),
        qd=np.vstack([prep.qd, tX[:k, :, 1], sqd]),
        t_toss=t_toss,
        t_switch=t_sw,
        t_contact=t_sw + target.tau,
        strike=strike,
        max_preparation_tilt=prep.max_tilt,
        cup=serve_cup_check(robot, prep, toss),
        settle_samples=su.shape[0] - strike.u.shape[0],
    )


def _strike_with_hold(strike: Plan, dynamics: JointDynamics, dt: float) -> tuple[FloatArray, ...]:
    """The strike's commands (u, ud, udd) and predicted states (q, qd), each (M, 8), with
    the rest command held until the predicted joints are at rest (:func:`~studio.planning.settle.settle_hold`)."""
    if strike.u.shape[0] == 0:
        return (np.zeros((0, 8)),) * 5
    tail = settle_hold(strike.u[-1], np.stack([strike.q[-1], strike.qd[-1]], axis=1), dynamics, dt=dt)
    n_tail = tail.shape[0]
    su = np.vstack([strike.u, np.repeat(strike.u[-1:], n_tail, axis=0)])
    sud, sudd = (np.vstack([a, np.zeros((n_tail, 8))]) for a in (strike.ud, strike.udd))
    sq, sqd = np.vstack([strike.q, tail[:, :, 0]]), np.vstack([strike.qd, tail[:, :, 1]])
    return su, sud, sudd, sq, sqd
