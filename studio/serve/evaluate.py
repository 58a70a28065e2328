"""Serve evaluation: serve parameters -> plan -> ball -> ITTF checks -> reward.

The chain of the paper's section "Optimizing serve parameters":

1. decode the strike target: p_tau = p_bar(tau) + delta_p on the toss's mean path,
   n_tau from (yaw, roll), v_tau;
2. plan the strike from the toss trajectory's state at the switch time (shortly after
   the ball leaves the cup) with :class:`studio.planning.planner.StrikePlanner`; a failed or
   invalid plan gets the fixed penalty P_MPC = -10 and no rollout;
3. check the whole motion for collisions (coal); a colliding plan is unsafe and is
   treated like a planner failure (-10);
4. predict the ball: from the (mean or sampled) toss state just after lift, with the
   racket moving as the predicted joint trajectory says (analytic predictor of
   :mod:`studio.physics.ball`, optionally the MuJoCo rollout of :mod:`studio.sim.rollout`);
5. the legality chain (:mod:`studio.serve.rules`) and the reward (:mod:`studio.serve.reward`).

Times are on the toss command clock (t = 0 at the start of the toss primitive), except
the effort report and the ball-in-cup check: those cover the preparation as well and use
the exported clock of the library NPZ (t = 0 at the start of the preparation).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import InvalidInputError
from studio.physics.ball import (
    DEFAULT_FLIGHT,
    BallState,
    FlightModel,
    RacketModel,
    SampledRacketMotion,
    Trajectory,
    simulate,
    spin_components,
)
from studio.physics.court import DEFAULT_COURT
from studio.robot.model import JointDynamics, Robot, load_robot
from studio.serve.params import HandServe, LimitScale, TossSide
from studio.serve.reward import PLANNER_FAILURE_PENALTY, RewardTerms, RewardWeights, reward, task_weights
from studio.serve.rules import LegalityReport, RuleParams, ServeOutcome, check_serve, net_crossing
from studio.serve.target import RacketTarget
from studio.toss.defaults import load_default_toss_model
from studio.toss.model import TossModel

Status = Literal["legal", "illegal", "planner_failed", "collision"]

MAX_SCALED_PLANNERS = 8
"""How many planners with expanded limits an evaluation context keeps (oldest dropped)."""

SWITCH_DELAY = 0.06
"""Time after the ball's lift at which the strike planner takes over from the toss [s]:
the ball clears the cup rim ~51 ms after release, so the strike may move the cup
sideways only after that."""

FLIGHT_AFTER_CONTACT = 1.6
"""How long the ball is followed after the contact time [s] (ends earlier at the floor)."""


@dataclass
class EvaluationContext:
    """What every evaluation shares: robot, tosses, planner, collision checker, models.

    Built once (loading the planner and the collision model takes about a second) and
    reused; not thread-safe (one worker per context).
    """

    robot: Robot
    """The serve robot."""
    flight: FlightModel = DEFAULT_FLIGHT
    """Ball flight model."""
    racket_model: RacketModel = field(default_factory=RacketModel.default)
    """Calibrated racket impact model."""
    rules: RuleParams = field(default_factory=RuleParams)
    """Legality thresholds."""
    switch_delay: float = SWITCH_DELAY
    """Planner take-over time after lift [s]."""
    planner_options: Any = None
    """:class:`studio.planning.options.PlannerOptions` of the strike planner (``None``: its defaults,
    IPOPT fallback on). Training turns the fallback off (see :func:`training_context`)."""
    _tosses: dict[str, TossModel] = field(default_factory=dict)
    _toss_reports: dict[str, Any] = field(default_factory=dict)
    _preparations: dict[str, Any] = field(default_factory=dict)
    _cup_checks: dict[str, Any] = field(default_factory=dict)
    _planners: dict[LimitScale, Any] = field(default_factory=dict)

    @classmethod
    def default(cls) -> EvaluationContext:
        """Context on the shipped robot, tosses and models."""
        return cls(robot=load_robot())

    @classmethod
    def for_training(cls, *, ipopt_fallback: bool = False) -> EvaluationContext:
        """Context for optimization runs: the strike planner without its IPOPT fallback.

        On uniformly drawn genomes the fallback rescued none of the plans the SQP could not
        finish and made evaluations several times slower (figures:
        ``docs/optimization.md#hebo-runs``). A target the SQP misses costs the optimizer one
        -10 evaluation instead.
        """
        from studio.planning.options import PlannerOptions

        return cls(robot=load_robot(), planner_options=PlannerOptions(fallback=ipopt_fallback))

    def preparation(self, side: TossSide) -> Any:
        """The preparation phase before a side's toss (feeder pose ``q_flat`` to the
        toss's first command, then a hold): :class:`studio.planning.preparation.PreparationPhase`, cached."""
        if side not in self._preparations:
            from studio.planning.preparation import preparation_phase

            self._preparations[side] = preparation_phase(self.robot, self.toss_model(side).primitive.u[0])
        return self._preparations[side]

    def cup_hold(self, side: TossSide) -> Any:
        """Ball-in-cup check of a side's preparation + toss up to the release, on the serve
        clock (:func:`studio.planning.serve_plan.serve_cup_check`), cached."""
        if side not in self._cup_checks:
            from studio.planning.serve_plan import serve_cup_check

            self._cup_checks[side] = serve_cup_check(
                self.robot, self.preparation(side), self.toss_model(side).primitive
            )
        return self._cup_checks[side]

    def warm_up(self, side: TossSide) -> None:
        """Build the toss model of ``side``, the planner, the collision model and the
        preparation now (instead of in the first evaluation)."""
        self.toss_model(side)
        _ = self.planner
        _ = self.collision
        self.cup_hold(side)  # and the preparation it checks (a noticeable cost: docs/measured.md)

    def toss_model(self, side: TossSide) -> TossModel:
        """The toss model of one side (default recordings), cached."""
        if side not in self._tosses:
            self._tosses[side] = load_default_toss_model(side, self.robot)
        return self._tosses[side]

    @cached_property
    def planner(self) -> Any:
        """The strike planner (built on first use)."""
        from studio.planning.planner import StrikePlanner

        return StrikePlanner(self.robot, options=self.planner_options)

    def planner_for(self, scale: LimitScale) -> Any:
        """The strike planner with the derivative limits expanded by ``scale`` (the paper's
        dynamic limit expansion): :attr:`planner` for the identity, else one planner per
        scale, cached (building one takes time: ``docs/planner.md#dynamic-limit-expansion``)."""
        if scale.is_identity:
            return self.planner
        if scale not in self._planners:
            from studio.planning.options import PlannerOptions
            from studio.planning.planner import StrikePlanner

            while len(self._planners) >= MAX_SCALED_PLANNERS:  # a studio user sweeping the sliders
                self._planners.pop(next(iter(self._planners)))

            options = self.planner_options if self.planner_options is not None else PlannerOptions()
            base = options.limits if options.limits is not None else self.robot.limits
            self._planners[scale] = StrikePlanner(self.robot, options=replace(options, limits=scale.apply(base)))
        return self._planners[scale]

    @cached_property
    def racket_poses(self) -> Any:
        """Vectorized racket pose: ``(Q (N, 8)) -> (p (N, 3), R (N, 3, 3))`` (casadi FK).

        One casadi call for a whole trajectory instead of N pinocchio calls from Python.
        """
        import casadi as ca

        from studio.planning.kinematics_casadi import frame_placement

        q = ca.SX.sym("q", self.robot.nq)
        pos, rot = frame_placement(self.robot.model, "racket", q)
        fn = ca.Function("racket_pose", [q], [pos, ca.reshape(rot, 9, 1)])

        def poses(Q: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
            P, Rf = fn(np.asarray(Q, dtype=float).T)
            R = np.asarray(Rf).T.reshape(-1, 3, 3).transpose(0, 2, 1)  # column-major 3x3 blocks
            return np.asarray(P).T, R

        return poses

    @cached_property
    def collision(self) -> Any:
        """The coal collision checker (built on first use)."""
        from studio.robot.collision import CollisionChecker

        return CollisionChecker(self.robot)

    def toss_collision(self, side: TossSide, n: int) -> Any:
        """Collision report of the first ``n`` samples of a side's toss (cached)."""
        key = f"{side}:{n}"
        if key not in self._toss_reports:
            prim = self.toss_model(side).primitive
            self._toss_reports[key] = self.collision.check(prim.t[:n], prim.q[:n])
        return self._toss_reports[key]

    @cached_property
    def mujoco_scene(self) -> Any:
        """The compiled MuJoCo scene (built on first use)."""
        from studio.sim.scene import build_scene

        return build_scene()


@dataclass(frozen=True)
class BallMetrics:
    """Ball state summaries reported for every evaluation (world frame, SI)."""

    second_bounce: dict[str, Any] | None
    """At the second bounce: p, v, w after the bounce, topspin, sidespin, cork."""
    net: dict[str, Any] | None
    """At the net crossing: p, v, w, topspin, sidespin, cork, height, clearance."""
    bounces: tuple[tuple[float, float, float], ...]
    """Table bounce points after the strike."""
    net_clearance: float | None
    """Gap between ball bottom and net top at the crossing [m]."""
    max_height: float | None
    """Highest ball bottom above the table between first and second bounce [m]."""
    racket_speed_out: float | None
    """Ball speed just after the racket contact [m/s]."""


@dataclass(frozen=True)
class ServeMotion:
    """The planned robot motion of a serve (independent of which toss sample is used)."""

    serve: HandServe
    """The serve planned."""
    target: RacketTarget
    """Racket target at tau."""
    plan: Any | None
    """The strike plan (None if planning was not reached)."""
    t: npt.NDArray[np.float64] | None
    """Full-serve command times (M,) [s] (toss then strike), 1 kHz."""
    u: npt.NDArray[np.float64] | None
    """Joint commands (M, 8)."""
    q: npt.NDArray[np.float64] | None
    """Predicted joint positions (M, 8)."""
    collision: Any | None
    """Collision report of the whole motion."""
    failure: tuple[Status, str] | None
    """(status, reason) when the motion is not usable, else None."""
    racket: SampledRacketMotion | None
    """Racket motion around the strike, for the ball predictor."""
    timings_ms: dict[str, float]
    """Wall time per stage [ms]."""
    qd: npt.NDArray[np.float64] | None = None
    """Predicted joint velocities (M, 8) (the toss's and the plan's, exact), when planned."""
    preparation: Any = None
    """The :class:`studio.planning.preparation.PreparationPhase` before the toss (the context's), when planned."""

    def joint_states(self, t_end: float, dynamics: JointDynamics) -> npt.NDArray[np.float64]:
        """Predicted joint states [q, q'] (n, 8, 2) on the 1 kHz command grid from ``t[0]``
        up to (at least) ``t_end``: the planned motion, then the joint model holding the
        last command (the robot stays at rest pose ``u[-1]`` after the return).

        The ball may fly on long after the motion ends (the evaluation follows it
        :data:`FLIGHT_AFTER_CONTACT` after the contact; the return is usually shorter), so
        a MuJoCo rollout needs the robot beyond ``t[-1]``."""
        if self.t is None or self.u is None or self.q is None or self.qd is None:
            raise InvalidInputError("joint_states: the motion was not planned")
        t = np.asarray(self.t)
        X = np.stack([np.asarray(self.q), np.asarray(self.qd)], axis=2)
        dt = float(t[1] - t[0])
        n_total = int(np.ceil((t_end - float(t[0])) / dt - 1e-9)) + 1
        extra = n_total - X.shape[0]
        if extra > 0:
            # X[k+1] = A X[k] + B u[k]: the state one sample after X[-1], then holding u[-1]
            hold = np.repeat(np.asarray(self.u)[-1:], extra + 1, axis=0)
            X = np.concatenate([X, dynamics.simulate(hold, dt, X[-1])[1:]])
        return X


@dataclass(frozen=True)
class Evaluation:
    """Everything one serve evaluation produced (on one toss)."""

    motion: ServeMotion
    """The planned robot motion (serve, target, plan, commands, collision report)."""
    status: Status
    """Overall verdict."""
    reason: str
    """One-line explanation of the verdict."""
    ball: Trajectory | None
    """Predicted ball path after lift (analytic predictor)."""
    toss_t: npt.NDArray[np.float64]
    """Toss path times before lift (K,) [s] (ball riding in the cup)."""
    toss_p: npt.NDArray[np.float64]
    """Toss path positions before lift (K, 3) [m]."""
    rollout: Any | None
    """MuJoCo rollout result when requested."""
    legality: LegalityReport | None
    """Legality chain (of the rollout if there is one, else of the prediction)."""
    reward: RewardTerms
    """Reward F and its terms."""
    metrics: BallMetrics | None
    """Ball state summaries."""
    timings_ms: dict[str, float]
    """Wall time per stage [ms]."""
    cup_hold: Any = None
    """Ball-in-cup check of the side's preparation + toss up to the release
    (:class:`studio.robot.cup_hold.CupHoldCheck`, serve clock); not part of the legality chain."""

    @property
    def serve(self) -> HandServe:
        return self.motion.serve

    @property
    def target(self) -> RacketTarget:
        return self.motion.target

    @property
    def plan(self) -> Any | None:
        return self.motion.plan

    @property
    def t(self) -> npt.NDArray[np.float64] | None:
        return self.motion.t

    @property
    def u(self) -> npt.NDArray[np.float64] | None:
        return self.motion.u

    @property
    def q(self) -> npt.NDArray[np.float64] | None:
        return self.motion.q

    @property
    def collision(self) -> Any | None:
        return self.motion.collision

    @property
    def legal(self) -> bool:
        return self.status == "legal"

    @property
    def failed_check(self) -> str | None:
        """Name of the first failing legality check, ``planner_failed`` or ``collision``; None when legal."""
        if self.legality is not None and self.legality.first_failure is not None:
            return str(self.legality.first_failure.name)
        if self.status in ("planner_failed", "collision"):
            return str(self.status)
        return None

    def to_json(self) -> dict[str, Any]:
        """The metrics as a JSON-ready dict (CLI ``--json``)."""
        m = self.metrics
        failed = self.failed_check
        plan = self.plan
        return {
            "name": self.serve.name,
            "side": self.serve.side,
            "status": self.status,
            "reason": self.reason,
            "legal": self.legal,
            "failed_check": failed,
            "reward": self.reward.total,
            "terms": self.reward.as_dict(),
            "second_bounce": m.second_bounce if m else None,
            "net": m.net if m else None,
            "bounces": [list(b) for b in m.bounces] if m else [],
            "net_clearance": m.net_clearance if m else None,
            "max_height": m.max_height if m else None,
            "planner": {
                "status": getattr(plan, "status", None),
                "reason": getattr(plan, "reason", None),
                "solve_ms": getattr(plan, "solve_time_ms", None),
            },
            "checks": [
                {"name": c.name, "passed": c.passed, "penalty": c.penalty, "detail": c.detail}
                for c in (self.legality.checks if self.legality else ())
            ],
            "timings_ms": self.timings_ms,
            "cup_hold": self.cup_hold.to_json() if self.cup_hold is not None else None,
        }


def _vec(a: npt.ArrayLike) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=float)]


def _state_summary(p: npt.ArrayLike, v: npt.ArrayLike, w: npt.ArrayLike) -> dict[str, Any]:
    tb, ss, ck = spin_components(v, w)
    return {
        "p": _vec(p),
        "v": _vec(v),
        "w": _vec(w),
        "speed": float(np.linalg.norm(v)),
        "topspin": float(tb),
        "sidespin": float(ss),
        "cork": float(ck),
    }


def _point3(p: npt.ArrayLike) -> tuple[float, float, float]:
    x, y, z = (float(c) for c in np.asarray(p, dtype=float).ravel()[:3])
    return (x, y, z)


def ball_metrics(traj: Trajectory | Any, *, strike_t: float | None) -> BallMetrics:
    """Summaries of a ball path (predictor trajectory or rollout result)."""
    contacts: tuple[Any, ...] = tuple(getattr(traj, "events", None) or getattr(traj, "contacts", None) or ())
    after = [c for c in contacts if strike_t is not None and c.t > strike_t]
    bounces = [c for c in after if c.kind == "table" and getattr(c, "part", "top") != "side"]
    second = None
    if len(bounces) >= 2:
        b = bounces[1]
        second = _state_summary(b.p, b.v_after, b.w_after)
    t, p, v, w = (np.asarray(a) for a in (traj.t, traj.p, traj.v, traj.w))
    mask = t >= (strike_t if strike_t is not None else t[0])
    net = None
    clearance = None
    crossing = net_crossing(t[mask], p[mask]) if mask.sum() > 1 else None
    if crossing is not None:
        tc, pc = crossing
        i = int(np.clip(np.searchsorted(t, tc), 1, len(t) - 1))
        net = _state_summary(pc, v[i], w[i])
        clearance = float(pc[2] - C.BALL_RADIUS - DEFAULT_COURT.net_height)
        net["height"] = float(pc[2])
        net["clearance"] = clearance
    max_height = None
    if bounces:
        t_end = bounces[1].t if len(bounces) > 1 else t[-1]
        seg = (t >= bounces[0].t) & (t <= t_end)
        if seg.any():
            max_height = float(np.max(p[seg, 2]) - C.BALL_RADIUS)
    racket = [c for c in contacts if c.kind == "racket"]
    return BallMetrics(
        second_bounce=second,
        net=net,
        bounces=tuple(_point3(b.p) for b in bounces),
        net_clearance=clearance,
        max_height=max_height,
        racket_speed_out=float(np.linalg.norm(racket[0].v_after)) if racket else None,
    )


CONTACT_STANDOFF = C.BALL_RADIUS + C.RACKET_HALF_THICKNESS
"""Distance [m] from the racket's mid-plane to the centre of a ball touching its rubber:
ball radius 20 mm + half the racket thickness 7 mm (:mod:`studio.constants`)."""


def strike_target(serve: HandServe, toss: TossModel) -> RacketTarget:
    """Racket target at tau such that the ball on the mean toss path touches the rubber at tau.

    The serve's racket velocity v_tau and normal n_tau are those at that contact. The
    contact point on the face is the foot of the ball centre ``p_bar(tau)`` on the face
    plane, moved by the in-plane part of the offset delta_p; so the racket centre is::

        p_tau = p_bar(tau) + (delta_p - (delta_p . n) n) - s (r + h) n

    with ``r + h`` = :data:`CONTACT_STANDOFF` and ``s = +1`` when the ball meets the face
    n points out of (face A: the ball approaches against n relative to the racket), else -1.
    The normal part of delta_p would move the contact off tau and is not used (serve files
    from before this rule put the racket centre on ``p_bar(tau) + delta_p``: they load
    unchanged and are read by this rule, the ball now meeting the rubber at tau instead of
    3-14 ms earlier).
    """
    p = serve.params
    if not (toss.t[0] <= p.tau <= toss.t[-1]):
        raise InvalidInputError(
            f"tau = {p.tau:.3f} s is outside the toss model's time range [{toss.t[0]:.2f}, {toss.t[-1]:.2f}] s"
        )
    ball = toss.mean_state(p.tau)
    n = np.asarray(p.normal, dtype=float)
    n = n / np.linalg.norm(n)
    offset = np.asarray(p.offset, dtype=float)
    offset = offset - float(offset @ n) * n
    side = 1.0 if float((np.asarray(ball.v) - np.asarray(p.velocity)) @ n) <= 0.0 else -1.0
    pos = np.asarray(ball.p) + offset - side * CONTACT_STANDOFF * n
    return RacketTarget(tuple(_vec(pos)), tuple(_vec(n)), tuple(_vec(p.velocity)))  # type: ignore[arg-type]


def _failure(motion: ServeMotion, toss: TossModel, timings: dict[str, float]) -> Evaluation:
    """The evaluation of a motion that could not be planned or is unsafe: P_MPC, no ball."""
    assert motion.failure is not None
    status, reason = motion.failure
    lift = toss.t <= toss.t_lift
    return Evaluation(
        motion=motion,
        status=status,
        reason=reason,
        ball=None,
        toss_t=toss.t[lift],
        toss_p=toss.p[lift],
        rollout=None,
        legality=None,
        reward=RewardTerms(s_leg=PLANNER_FAILURE_PENALTY),
        metrics=None,
        timings_ms=timings,
    )


def _lap(timings: dict[str, float], name: str, since: float) -> float:
    """Add the time since ``since`` to ``timings[name]`` [ms]; returns now."""
    now = time.perf_counter()
    timings[name] = timings.get(name, 0.0) + 1000 * (now - since)
    return now


def _strike_goal(serve: HandServe, target: RacketTarget, t_switch: float, u_rest: Any) -> Any:
    """The planner's :class:`studio.planning.strike.StrikeTarget`, timed from the switch."""
    from studio.planning.strike import StrikeTarget

    p = serve.params
    return StrikeTarget(
        tau=p.tau - t_switch,
        position=np.asarray(target.position),
        normal=np.asarray(target.normal),
        velocity=np.asarray(target.velocity),
        tau_f=p.tau - t_switch + p.t_return,
        u_rest=u_rest,
    )


class _Commands(NamedTuple):
    """Full-serve command times, joint commands, predicted positions and velocities."""

    t: npt.NDArray[np.float64]
    u: npt.NDArray[np.float64]
    q: npt.NDArray[np.float64]
    qd: npt.NDArray[np.float64]


def _joined_commands(prim: Any, plan: Any, i_sw: int, t_switch: float) -> _Commands:
    """The toss's commands up to the switch followed by the strike plan's."""
    return _Commands(
        np.concatenate([prim.t[:i_sw], t_switch + np.asarray(plan.t)]),
        np.concatenate([prim.u[:i_sw], plan.u]),
        np.concatenate([prim.q[:i_sw], plan.q]),
        np.concatenate([prim.X[:i_sw, :, 1], plan.qd]),
    )


def _motion_collision(context: EvaluationContext, side: TossSide, i_sw: int, t_full: Any, q_full: Any) -> Any:
    """Collision report of the whole motion (the toss part is the same for every serve of a side: cached)."""
    report = context.toss_collision(side, i_sw)
    if not report.collides:
        report = context.collision.check(t_full[i_sw:], q_full[i_sw:])
    return report


def _racket_motion(
    context: EvaluationContext, toss: TossModel, tau: float, t_full: Any, q_full: Any
) -> SampledRacketMotion:
    """The racket poses from just before the lift to shortly after the contact, for the ball predictor."""
    window = (t_full >= toss.t_lift - 0.01) & (t_full <= tau + 0.25)
    positions, rotations = context.racket_poses(q_full[window])
    return SampledRacketMotion(t_full[window], positions, rotations)


def plan_motion(serve: HandServe, context: EvaluationContext, *, warm_start: Any | None = None) -> ServeMotion:
    """Decode the strike target, plan the strike from the toss and check for collisions.

    Never raises for a target that is merely unreachable or unsafe: the failure is in
    :attr:`ServeMotion.failure`.
    """
    from studio.planning.serve_plan import start_from_toss

    timings: dict[str, float] = {}
    clock = time.perf_counter()
    toss = context.toss_model(serve.side)
    target = strike_target(serve, toss)
    prim = toss.primitive
    p = serve.params
    t_switch = float(prim.t[prim.index_at(toss.t_lift + context.switch_delay)])
    unplanned = ServeMotion(serve, target, None, None, None, None, None, None, None, timings)
    if p.tau <= t_switch + 0.05:
        reason = f"contact time tau = {p.tau:.3f} s leaves no time to strike (lift at {toss.t_lift:.3f} s)"
        return replace(unplanned, failure=("planner_failed", reason))
    # The strike continues the toss commands u[:k] seamlessly from the predicted state at t_k.
    start, i_sw = start_from_toss(prim, t_switch)
    goal = _strike_goal(serve, target, t_switch, context.robot.q_rest)
    plan = context.planner_for(serve.limit_scale).plan(start, goal, warm_start=warm_start)
    clock = _lap(timings, "plan", clock)
    if not plan.ok:
        return replace(unplanned, plan=plan, failure=("planner_failed", f"planner: {plan.status}: {plan.reason}"))
    c = _joined_commands(prim, plan, i_sw, t_switch)
    planned = replace(unplanned, plan=plan, t=c.t, u=c.u, q=c.q, qd=c.qd)
    report = _motion_collision(context, serve.side, i_sw, c.t, c.q)
    clock = _lap(timings, "collision", clock)
    if report.collides:
        failure: tuple[Status, str] = ("collision", f"collision: {report.describe()}")
        return replace(planned, collision=report, failure=failure, preparation=context.preparation(serve.side))
    racket = _racket_motion(context, toss, p.tau, c.t, c.q)
    _lap(timings, "racket_fk", clock)
    return replace(planned, collision=report, racket=racket, preparation=context.preparation(serve.side))


def _check_toss_choice(serve: HandServe, toss: TossModel, toss_sample: int | None, mujoco: bool) -> None:
    """Refuse a recorded toss the side does not have, or one combined with the MuJoCo rollout."""
    if toss_sample is not None and not (0 <= toss_sample < toss.n_tosses):
        raise InvalidInputError(
            f"toss sample {toss_sample} out of range: the {serve.side} toss has {toss.n_tosses} recordings"
        )
    if mujoco and toss_sample is not None:
        raise InvalidInputError(
            f"the MuJoCo rollout tosses the ball from the cup as the motion predicts: it cannot replay recorded toss {toss_sample + 1}; "
            "evaluate the mean toss path with it, or the recorded toss without it"
        )


def _ball_start(
    toss: TossModel, context: EvaluationContext, tau: float, t_start: float, toss_sample: int | None
) -> Any:
    """The ball state at ``t_start`` whose flight passes through the mean path (or a recorded
    toss's own recorded state) at tau, so that the ball touches the racket at tau (strike_target)."""
    if toss_sample is None:
        return toss.mean_start_state(t_start, tau, flight=context.flight)
    return toss.recorded_start_state(toss_sample, t_start, tau, flight=context.flight)


def _mujoco_rollout(motion: ServeMotion, context: EvaluationContext, t_end: float) -> Any:
    """The MuJoCo rollout of the whole serve, the ball tossed from the cup, until ``t_end``."""
    from studio.sim.rollout import rollout

    assert motion.t is not None
    # the robot as planned, then at rest until the ball's flight ends (t_end > t_full[-1])
    X = motion.joint_states(t_end, context.robot.dynamics)
    return rollout(
        context.mujoco_scene,
        t=motion.t,
        X=X,
        ball="cup",
        t_end=t_end,
        flight=context.flight,
        racket_model=context.racket_model,
    )


def _release(rollout_result: Any, toss: TossModel, ball0: Any, t_start: float) -> tuple[float, float]:
    """(time, height) of the ball's release from the cup: the rollout's own, else the toss
    model's lift with the ball's height extrapolated back to it."""
    release = getattr(rollout_result, "release", None)
    if release is not None:  # the rollout's own release from the cup
        return float(release.time), float(release.position[2])
    # the toss model's lift, the ball's height extrapolated back to it
    release_t = float(toss.t_lift)
    return release_t, float(ball0.p[2] - ball0.v[2] * (t_start - release_t))


def _reward_terms(legality: LegalityReport, metrics: BallMetrics, weights: RewardWeights) -> RewardTerms:
    """The reward of a legal serve from its second bounce and net crossing, else the legality penalty."""
    if legality.legal and metrics.second_bounce is not None:
        sb = metrics.second_bounce
        net = metrics.net if metrics.net is not None else {}
        return reward(
            p2=sb["p"],
            v2=sb["v"],
            w2=sb["w"],
            max_height=metrics.max_height or 0.0,
            weights=weights,
            v_net=net.get("v"),
            w_net=net.get("w"),
        )
    return RewardTerms(s_leg=legality.penalty)


def _verdict(legality: LegalityReport) -> tuple[Status, str]:
    """(status, one-line reason) of a checked serve."""
    failure = legality.first_failure
    status: Status = "legal" if failure is None else "illegal"
    return status, "legal serve" if failure is None else f"{failure.label}: {failure.detail}"


def evaluate_motion(
    motion: ServeMotion,
    context: EvaluationContext,
    *,
    task: str | RewardWeights = "topspin_velocity",
    toss_sample: int | None = None,
    mujoco: bool = False,
) -> Evaluation:
    """Predict the ball for one toss (mean path or a recorded sample), check and score.

    With ``mujoco`` the verdict comes from the MuJoCo rollout (:func:`studio.sim.rollout.rollout`)
    of the whole serve: the ball rides in the cup of the predicted motion until it is
    released, then flies until ``tau + FLIGHT_AFTER_CONTACT`` (or the floor), the robot
    holding its rest pose after the motion ends. That toss is the predicted one, so it
    cannot be combined with a recorded ``toss_sample`` (InvalidInputError).
    """
    weights = task_weights(task) if isinstance(task, str) else task
    timings = dict(motion.timings_ms)
    clock = time.perf_counter()
    serve = motion.serve
    toss = context.toss_model(serve.side)
    _check_toss_choice(serve, toss, toss_sample, mujoco)
    if motion.failure is not None:
        return replace(_failure(motion, toss, timings), cup_hold=context.cup_hold(serve.side))
    assert motion.t is not None and motion.q is not None and motion.racket is not None
    t_start = toss.t_lift + 0.005
    ball0 = _ball_start(toss, context, serve.params.tau, t_start, toss_sample)
    t_end = serve.params.tau + FLIGHT_AFTER_CONTACT
    ball = simulate(
        BallState(ball0.p, ball0.v, np.zeros(3)),
        t_end - t_start,
        t0=t_start,
        flight=context.flight,
        racket_model=context.racket_model,
        racket=motion.racket,
        max_table_bounces=2,
    )
    clock = _lap(timings, "ball", clock)
    rollout_result = None
    source: Any = ball
    if mujoco:
        source = rollout_result = _mujoco_rollout(motion, context, t_end)
        clock = _lap(timings, "mujoco", clock)
    contacts = tuple(getattr(source, "events", None) or getattr(source, "contacts", None) or ())
    racket_hits = [c for c in contacts if c.kind == "racket"]
    release_t, release_z = _release(rollout_result, toss, ball0, t_start)
    outcome = ServeOutcome(
        t=np.asarray(source.t),
        p=np.asarray(source.p),
        contacts=contacts,
        release_t=release_t,
        release_z=release_z,
        robot_rest_t=float(motion.t[-1]),
    )
    legality = check_serve(outcome, params=context.rules)
    metrics = ball_metrics(source, strike_t=racket_hits[0].t if racket_hits else None)
    terms = _reward_terms(legality, metrics, weights)
    _lap(timings, "checks", clock)
    status, reason = _verdict(legality)
    lift = toss.t <= toss.t_lift
    return Evaluation(
        motion=motion,
        status=status,
        reason=reason,
        ball=ball,
        toss_t=toss.t[lift],
        toss_p=toss.p[lift],
        rollout=rollout_result,
        legality=legality,
        reward=terms,
        metrics=metrics,
        timings_ms=timings,
        cup_hold=context.cup_hold(serve.side),
    )


def evaluate_serve(
    serve: HandServe,
    context: EvaluationContext,
    *,
    task: str | RewardWeights = "topspin_velocity",
    toss_sample: int | None = None,
    mujoco: bool = False,
    warm_start: Any | None = None,
) -> Evaluation:
    """Evaluate one serve on the mean toss (``toss_sample=None``) or on a recorded toss.

    Never raises for a serve that is merely bad (unreachable, colliding, illegal): the
    verdict is in the result. Raises :class:`InvalidInputError` for malformed input.
    """
    motion = plan_motion(serve, context, warm_start=warm_start)
    return evaluate_motion(motion, context, task=task, toss_sample=toss_sample, mujoco=mujoco)


@dataclass(frozen=True)
class RobustEvaluation:
    """A serve evaluated on several recorded tosses (paper: multi-toss training)."""

    evaluations: tuple[Evaluation, ...]
    """One evaluation per toss sample (they share the plan)."""
    min_legal_fraction: float
    """Fraction p of legal tosses needed for the serve to count as legal."""
    samples: tuple[int, ...] = ()
    """Recorded toss index of each evaluation (0-based), when known."""

    @property
    def legal_fraction(self) -> float:
        return sum(e.legal for e in self.evaluations) / len(self.evaluations)

    @property
    def legal(self) -> bool:
        return self.legal_fraction >= self.min_legal_fraction

    @property
    def reward(self) -> float:
        """Mean reward over the toss samples (penalties included)."""
        return float(np.mean([e.reward.total for e in self.evaluations]))

    def failed_checks(self) -> dict[str, int]:
        """How many tosses failed each check (first failing check of each illegal toss)."""
        out: dict[str, int] = {}
        for e in self.evaluations:
            check = e.failed_check
            if check is not None:
                out[check] = out.get(check, 0) + 1
        return out

    def to_json(self) -> dict[str, Any]:
        """The first toss's metrics (``status``, ``reason``, checks, bounces, ... of the
        recorded toss ``metrics_toss_sample``), with the robust verdict on top: ``legal``,
        ``reward`` (mean), ``legal_fraction``, ``failed_check`` (None when robustly legal,
        else the check most tosses failed), ``failed_checks`` (counts) and ``per_toss``."""
        first = self.evaluations[0].to_json()
        counts = self.failed_checks()
        samples: list[int | None] = (
            list(self.samples) if len(self.samples) == len(self.evaluations) else [None] * len(self.evaluations)
        )
        first.update(
            {
                "metrics_toss_sample": samples[0],
                "legal": self.legal,
                "reward": self.reward,
                "legal_fraction": self.legal_fraction,
                "failed_check": None if self.legal or not counts else max(counts, key=lambda c: counts[c]),
                "failed_checks": counts,
                "tosses": len(self.evaluations),
                "per_toss": [
                    {"toss_sample": k, "legal": e.legal, "reward": e.reward.total, "failed_check": e.failed_check}
                    for k, e in zip(samples, self.evaluations)
                ],
            }
        )
        return first


def evaluate_robust(
    serve: HandServe,
    context: EvaluationContext,
    *,
    task: str | RewardWeights = "topspin_velocity",
    tosses: int = 10,
    min_legal_fraction: float = 0.8,
    rng: np.random.Generator | None = None,
) -> RobustEvaluation:
    """Evaluate a serve on ``tosses`` recorded tosses drawn without replacement.

    The motion is planned once (the target is tied to the mean toss path); only the
    ball prediction is repeated per toss: each toss's ball passes through that
    recording's own state at tau (:meth:`studio.toss.model.TossModel.recorded_start_state`).
    Rewards are averaged; the serve is legal when
    at least ``min_legal_fraction`` of the tosses are legal.
    """
    if not (0.0 < min_legal_fraction <= 1.0):
        raise InvalidInputError(f"min_legal_fraction must be in (0, 1], got {min_legal_fraction}")
    toss = context.toss_model(serve.side)
    if not (1 <= tosses <= toss.n_tosses):
        raise InvalidInputError(
            f"tosses must be in [1, {toss.n_tosses}] (recordings of the {serve.side} toss), got {tosses}"
        )
    rng = rng if rng is not None else np.random.default_rng(0)
    samples = rng.choice(toss.n_tosses, size=tosses, replace=False)
    motion = plan_motion(serve, context)
    evaluations = tuple(evaluate_motion(motion, context, task=task, toss_sample=int(k)) for k in samples)
    return RobustEvaluation(evaluations, min_legal_fraction, tuple(int(k) for k in samples))


# -- presentation helpers shared by the studio, the CLI and notebooks ---------------------


def report_markdown(ev: Evaluation) -> tuple[str, str, str]:
    """(status, checklist, metrics) as Markdown for GUI panels and notebooks."""
    badge = {"legal": "LEGAL", "illegal": "ILLEGAL", "planner_failed": "NO PLAN", "collision": "COLLISION"}[ev.status]
    plan = ev.plan
    plan_line = "planner not reached"
    if plan is not None:
        plan_line = f"planner: **{plan.status}** ({plan.solver or 'no solver'}, {plan.iterations} it.) in {plan.solve_time_ms:.1f} ms"
        if getattr(plan, "reason", ""):
            plan_line += f" ({plan.reason})"
    status = f"### {badge}: reward {ev.reward.total:+.3f}\n\n{ev.reason}\n\n{plan_line}"
    if ev.legality is None:
        checks = "_no ball simulated: the serve did not get past planning_"
    else:
        rows = ["| | check | penalty | detail |", "|---|---|---|---|"]
        for c in ev.legality.checks:
            rows.append(f"| {'pass' if c.passed else '**FAIL**'} | {c.label} | {c.penalty:g} | {c.detail} |")
        checks = "\n".join(rows)
    if ev.cup_hold is not None:  # the robot's own check, outside the ITTF chain (no penalty)
        cup = f"{'pass' if ev.cup_hold.passed else '**FAIL**'} | ball stays in cup (preparation + toss) | none | {ev.cup_hold.detail}"
        checks += (
            f"\n| {cup} |"
            if ev.legality is not None
            else f"\n\n| | robot check | penalty | detail |\n|---|---|---|---|\n| {cup} |"
        )
    m = ev.metrics
    lines = ["| metric | value |", "|---|---|"]
    for k, val in ev.reward.as_dict().items():
        lines.append(f"| {k} | {val:+.3f} |")
    if m is not None:
        if m.net is not None:
            lines.append(f"| net crossing speed | {m.net['speed']:.2f} m/s |")
            lines.append(
                f"| net top/side/cork spin | {m.net['topspin']:+.0f} / {m.net['sidespin']:+.0f} / {m.net['cork']:+.0f} rad/s |"
            )
        if m.net_clearance is not None:
            lines.append(f"| net clearance | {100 * m.net_clearance:.1f} cm |")
        if m.second_bounce is not None:
            sb = m.second_bounce
            lines.append(f"| 2nd bounce at | ({sb['p'][0]:+.2f}, {sb['p'][1]:+.2f}) m |")
            lines.append(f"| 2nd bounce velocity | ({sb['v'][0]:+.2f}, {sb['v'][1]:+.2f}, {sb['v'][2]:+.2f}) m/s |")
            lines.append(
                f"| 2nd bounce top/side/cork | {sb['topspin']:+.0f} / {sb['sidespin']:+.0f} / {sb['cork']:+.0f} rad/s |"
            )
        if m.max_height is not None:
            lines.append(f"| max height after bounce 1 | {100 * m.max_height:.1f} cm |")
        for i, b in enumerate(m.bounces[:2]):
            lines.append(f"| bounce {i + 1} | ({b[0]:+.2f}, {b[1]:+.2f}) m |")
    for k, val in ev.timings_ms.items():
        lines.append(f"| time: {k} | {val:.1f} ms |")
    return status, checks, "\n".join(lines)
