"""Strike motion planner (studio.planning): constraints, tolerances, limits, continuity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from studio.errors import InvalidInputError
from studio.planning.chain import chain_transition
from studio.planning.planner import StrikePlanner
from studio.planning.strike import StrikeStart, StrikeTarget
from studio.robot.model import JointDynamics, load_robot

DT = 1e-3


@pytest.fixture(scope="module")
def robot():  # type: ignore[no-untyped-def]
    return load_robot()


@pytest.fixture(scope="module")
def planner(robot):  # type: ignore[no-untyped-def]
    return StrikePlanner(robot)


@pytest.fixture(scope="module")
def start(robot):  # type: ignore[no-untyped-def]
    """A moving start state (as at the switch from the toss)."""
    q0 = robot.q_flat.copy()
    ud0 = np.array([0.2, -0.1, 0.3, -0.4, 0.5, 0.2, -0.3, 0.4])
    udd0 = np.array([1.0, 0.0, -2.0, 1.0, 0.0, 3.0, -1.0, 0.5])
    return StrikeStart(u=q0, ud=ud0, udd=udd0, X=np.stack([q0 - 0.01 * ud0, 0.9 * ud0], axis=1))


def _target(robot, q_tau, qd_tau, tau=0.45, tau_f=1.2):  # type: ignore[no-untyped-def]
    pose = robot.fk(q_tau)
    v, _ = robot.racket_velocity(q_tau, qd_tau)
    return StrikeTarget(tau=tau, position=pose.position, normal=pose.normal, velocity=v, tau_f=tau_f)


@pytest.fixture(scope="module")
def easy(robot, start):  # type: ignore[no-untyped-def]
    """Target reachable without active limits (the reduced problem suffices); tau off
    the 1 kHz grid."""
    q_tau = robot.q_flat + np.array([0.25, 0.1, 0.4, 0.3, -0.3, 0.5, 0.4, -0.6])
    return _target(robot, q_tau, np.array([1.5, 0.5, 2.0, 1.0, -1.5, 2.0, 3.0, 1.0]), tau=0.4537, tau_f=1.2213)


@pytest.fixture(scope="module")
def hard(robot, start):  # type: ignore[no-untyped-def]
    """Target whose joint-space minimum-jerk motion overshoots the gantry's x limit."""
    q_tau = robot.q_flat + np.array([0.25, 0.1, 0.4, 0.3, -0.3, 0.5, 0.4, -0.6])
    q_tau[0] = robot.limits.upper[0] - 0.02
    return _target(robot, q_tau, np.array([2.5, 0.5, 2.0, 1.0, -1.5, 2.0, 3.0, 1.0]))


@pytest.fixture(scope="module")
def plans(planner, start, easy, hard):  # type: ignore[no-untyped-def]
    return {"easy": planner.plan(start, easy), "hard": planner.plan(start, hard)}


def test_chain_transition_equals_expm(robot) -> None:  # type: ignore[no-untyped-def]
    for dyn in (
        robot.dynamics,
        JointDynamics(names=("a", "b", "c"), wn=np.array([40.0, 30.0, 20.0]), zeta=np.array([0.5, 1.0, 1.7])),
    ):
        for h in (1e-3, 0.0137, 0.05, 0.3):
            A, B = chain_transition(dyn, np.array(h))
            A0, B0 = dyn.jerk_chain(h)
            np.testing.assert_allclose(A, A0, atol=1e-12)
            np.testing.assert_allclose(B, B0, atol=1e-12)


def test_hard_target_needs_the_full_problem(planner, start, hard, robot) -> None:  # type: ignore[no-untyped-def]
    q_tau = robot.q_flat + np.array([0.25, 0.1, 0.4, 0.3, -0.3, 0.5, 0.4, -0.6])
    q_tau[0] = robot.limits.upper[0] - 0.02
    joint_space = planner.plan_joint_target(start, hard, q_tau, np.array([2.5, 0.5, 2.0, 1.0, -1.5, 2.0, 3.0, 1.0]))
    assert joint_space.status == "limits" and "gantry_x" in joint_space.reason


@pytest.mark.parametrize("name", ["easy", "hard"])
def test_plan_meets_tolerances_rechecked_with_zoh_simulation(plans, robot, start, name) -> None:  # type: ignore[no-untyped-def]
    plan = plans[name]
    assert plan.ok, plan.reason
    tg = plan.target
    assert plan.position_error <= 5e-3 and plan.angle_error <= math.radians(0.5)
    assert plan.velocity_error <= max(0.01, 0.01 * np.linalg.norm(tg.velocity))
    # Independent re-check: the robot's own zero-order-hold simulation of the 1 kHz
    # commands, propagated to tau with the held command, then pinocchio FK.
    X = robot.dynamics.simulate(plan.u, DT, start.X)
    k = int(math.floor(tg.tau / DT + 1e-9))
    frac = tg.tau - k * DT
    if frac > 1e-12:
        A, B = robot.dynamics.discretize(frac)
        x_tau = np.einsum("nij,nj->ni", A, X[k]) + B * plan.u[k][:, None]
    else:
        x_tau = X[k]
    pose = robot.fk(x_tau[:, 0])
    v, _ = robot.racket_velocity(x_tau[:, 0], x_tau[:, 1])
    assert np.linalg.norm(pose.position - tg.position) <= 5e-3
    assert math.degrees(math.acos(min(1.0, pose.normal @ tg.normal))) <= 0.5
    assert np.linalg.norm(v - tg.velocity) <= max(0.01, 0.01 * np.linalg.norm(tg.velocity))
    # The held commands reproduce the planned prediction (midpoint sampling).
    assert np.max(np.abs(X[:, :, 0] - plan.q)) < 1e-5
    assert np.max(np.abs(X[:, :, 1] - plan.qd)) < 3e-3  # ~wn^2 u' dt^2 / 8 within a held step


@pytest.mark.parametrize("name", ["easy", "hard"])
def test_limits_respected_at_1khz(plans, robot, name) -> None:  # type: ignore[no-untyped-def]
    plan = plans[name]
    L = robot.limits
    tol = 1e-6
    assert np.all(plan.u >= L.lower - tol) and np.all(plan.u <= L.upper + tol)
    assert np.all(np.abs(plan.ud) <= L.velocity * (1 + tol))
    assert np.all(np.abs(plan.udd) <= L.acceleration * (1 + tol))
    assert np.all(np.abs(plan.jerk) <= L.jerk * (1 + tol))
    assert np.all(plan.q >= L.lower - tol) and np.all(plan.q <= L.upper + tol)
    assert np.all(np.abs(plan.qd) <= L.velocity * (1 + tol))
    if name == "hard":  # the gantry really works at its limit
        assert np.max(plan.u[:, 0]) > L.upper[0] - 0.01


def test_continuity_up_to_acceleration(plans, start, robot) -> None:  # type: ignore[no-untyped-def]
    plan = plans["hard"]
    h = DT / 2
    j0 = plan.jerk[0]
    # First held command = cubic from the start state at the middle of the first period.
    np.testing.assert_allclose(plan.u[0], start.u + start.ud * h + start.udd * h**2 / 2 + j0 * h**3 / 6, atol=1e-12)
    np.testing.assert_allclose(plan.ud[0], start.ud + start.udd * h + j0 * h**2 / 2, atol=1e-10)
    np.testing.assert_allclose(plan.udd[0], start.udd + j0 * h, atol=1e-9)
    # Derivatives are consistent with the positions (no jumps anywhere).
    np.testing.assert_allclose(np.gradient(plan.u, DT, axis=0)[1:-1], plan.ud[1:-1], atol=2e-3)
    np.testing.assert_allclose(np.gradient(plan.ud, DT, axis=0)[1:-1], plan.udd[1:-1], atol=0.6)
    assert np.max(np.abs(np.diff(plan.udd, axis=0))) <= np.max(robot.limits.jerk) * DT * 1.000001
    # Rest at u_tauf with zero velocity and acceleration at tau_f.
    k_f = int(round(plan.target.tau_f / DT))
    np.testing.assert_allclose(plan.u[k_f:], np.broadcast_to(robot.q_rest, plan.u[k_f:].shape), atol=1e-9)
    np.testing.assert_allclose(plan.ud[-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(plan.udd[-1], 0.0, atol=1e-9)
    assert plan.t[-1] <= plan.target.tau_f + 1e-12 and plan.t.shape == (plan.u.shape[0],)


def test_unreachable_targets_come_back_with_a_reason(planner, start, easy) -> None:  # type: ignore[no-untyped-def]
    far = StrikeTarget(tau=0.45, position=[3.0, 0.0, 0.5], normal=[0, 0, 1], velocity=[0, 0, 0], tau_f=1.2)
    plan = planner.plan(start, far)
    assert not plan.ok and plan.status == "tolerance" and "position error" in plan.reason
    assert plan.u.shape[1] == 8  # the best compromise is still returned
    fast = StrikeTarget(tau=0.45, position=easy.position, normal=easy.normal, velocity=[60.0, 0, 0], tau_f=1.2)
    plan = planner.plan(start, fast)
    assert not plan.ok and plan.reason
    bad_start = StrikeStart(u=start.u, ud=start.ud * 100.0, udd=start.udd, X=start.X)
    plan = planner.plan(bad_start, easy)
    assert plan.status == "infeasible" and "velocity" in plan.reason


def test_identical_inputs_identical_plans(planner, start, easy, plans) -> None:  # type: ignore[no-untyped-def]
    again = planner.plan(start, easy)
    for field in ("u", "ud", "udd", "q", "qd", "jerk"):
        assert np.array_equal(getattr(again, field), getattr(plans["easy"], field))


def test_warm_start_and_ipopt_reference_agree(planner, start, easy, plans) -> None:  # type: ignore[no-untyped-def]
    base = plans["easy"]
    warm = planner.plan(start, easy, warm_start=base)
    assert warm.ok and abs(warm.jerk_cost - base.jerk_cost) <= 1e-3 * base.jerk_cost
    ref = planner.plan(start, easy, solver="ipopt")
    assert ref.ok and ref.solver == "ipopt"
    # IPOPT uses the tolerances (errors on their boundary x margin), the fast solver
    # aims at the centre: its jerk is at most a few % higher.
    assert ref.position_error > 1e-3
    assert ref.jerk_cost <= base.jerk_cost <= 1.1 * ref.jerk_cost


def test_nan_inputs_raise_naming_the_field(start) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInputError, match="StrikeTarget.position"):
        StrikeTarget(tau=0.4, position=[0, np.nan, 0], normal=[0, 0, 1], velocity=[0, 0, 0], tau_f=1.0)
    with pytest.raises(InvalidInputError, match="StrikeTarget.tau"):
        StrikeTarget(tau=float("nan"), position=[0, 0, 0], normal=[0, 0, 1], velocity=[0, 0, 0], tau_f=1.0)
    with pytest.raises(InvalidInputError, match="StrikeStart.X"):
        StrikeStart(u=start.u, ud=start.ud, udd=start.udd, X=np.full((8, 2), np.nan))
    with pytest.raises(InvalidInputError, match="tau < tau_f"):
        StrikeTarget(tau=1.0, position=[0, 0, 0], normal=[0, 0, 1], velocity=[0, 0, 0], tau_f=0.5)


def test_plan_serve_is_one_continuous_trajectory(robot, planner) -> None:  # type: ignore[no-untyped-def]
    from studio.planning.serve_plan import plan_serve
    from studio.toss.synthesis import make_toss

    toss = make_toss(robot, "right")
    t_sw = toss.release.time + 0.02
    k = toss.index_at(t_sw)
    q_tau = toss.q[k] + np.array([0.05, 0.05, 0.2, 0.1, -0.1, 0.3, 0.3, -0.3])
    target = _target(robot, q_tau, np.array([1.0, 0.3, 2.0, 1.0, -1.0, 2.0, 3.0, 1.0]), tau=0.5, tau_f=1.2)
    serve = plan_serve(planner, toss, target, t_switch=t_sw)
    assert serve.ok, serve.strike.reason
    L = robot.limits
    # Continuous up to acceleration everywhere: jumps bounded by the jerk limit x dt.
    assert np.all(np.abs(np.diff(serve.udd, axis=0)) <= L.jerk * DT * 1.01)
    assert np.all(np.abs(np.diff(serve.ud, axis=0)) <= L.acceleration * DT * 1.01)
    np.testing.assert_allclose(np.gradient(serve.u, DT, axis=0)[1:-1], serve.ud[1:-1], atol=1e-3)
    assert np.all(np.abs(serve.ud) <= L.velocity * (1 + 1e-6))
    # The toss is executed unchanged up to the switch, the strike ends at rest.
    i0 = int(round(serve.t_toss / DT))
    np.testing.assert_allclose(serve.u[i0:i0 + k], toss.u[:k], atol=0)
    np.testing.assert_allclose(serve.u[-1], robot.q_rest, atol=1e-9)
    assert serve.t_contact == pytest.approx(serve.t_switch + 0.5)
    assert serve.max_preparation_tilt < math.radians(5.0)
    # The ball stays in the cup up to the release; the arrays end with the joints at rest.
    assert serve.cup is not None and serve.cup.passed and serve.cup.t_end == pytest.approx(serve.t_toss + toss.release.time)
    assert serve.settle_samples > 50 and np.all(serve.u[-serve.settle_samples :] == serve.u[-1])
    assert np.all(np.abs(serve.q[-2:] - serve.u[-1]) <= 1e-4) and np.all(np.abs(serve.qd[-2:]) <= 1e-3)
    assert len(serve.t) == len(serve.u) == len(serve.q) == len(serve.qd) == len(serve.ud) == len(serve.udd)


def test_settle_hold_is_the_shortest_hold_to_rest(robot) -> None:  # type: ignore[no-untyped-def]
    from studio.planning.settle import SETTLE, SettleTolerance, settle_hold

    X0 = np.stack([robot.q_rest - 0.012, np.full(8, 0.4)], axis=1)  # the return's end: short and moving
    S = settle_hold(robot.q_rest, X0, robot.dynamics)
    n = S.shape[0]
    ref = robot.dynamics.simulate(np.repeat(robot.q_rest[None], n + 400, axis=0), DT, X0)  # exact ZOH, sample 0 = X0
    np.testing.assert_allclose(S, ref[1 : n + 1], atol=1e-12)

    def within(k):  # type: ignore[no-untyped-def]
        X, fd = ref[k], np.abs(ref[k, ..., 0] - ref[k - 1, ..., 0]) / DT  # exact and finite-difference speed
        return bool(np.all(np.abs(X[..., 0] - robot.q_rest) <= SETTLE.position) and np.all(np.abs(X[..., 1]) <= SETTLE.velocity)
                    and np.all(fd <= SETTLE.velocity))

    assert all(within(k) for k in range(n - 1, n + 201))  # the last two samples and the 0.2 s after them
    assert not within(n - 2)  # one sample shorter would not be
    assert 50 < n < 300
    assert settle_hold(robot.q_rest, np.stack([robot.q_rest, np.zeros(8)], axis=1), robot.dynamics).shape == (0, 8, 2)
    with pytest.raises(InvalidInputError, match="not within"):
        settle_hold(robot.q_rest, X0, robot.dynamics, tol=SettleTolerance(max_hold=0.05))


def test_preparation_keeps_the_ball_in_the_cup_within_the_limits(robot) -> None:  # type: ignore[no-untyped-def]
    from studio.planning.preparation import cup_check, held_quintic, preparation_phase
    from studio.robot.cup_hold import CupGrip
    from studio.toss.defaults import load_default_toss_model

    u0 = load_default_toss_model("right", robot).primitive.u[0]
    prep = preparation_phase(robot, u0)
    assert prep.cup is not None and prep.cup.passed and prep.cup.t_end == pytest.approx(prep.duration)
    L = robot.limits
    assert np.all(np.abs(prep.ud) <= L.velocity) and np.all(np.abs(prep.udd) <= L.acceleration)
    np.testing.assert_allclose(prep.q[-1], u0, atol=1e-6)  # at rest when the toss starts
    # the shortest on the 1 ms grid (the limits alone allowed 0.331 s, which breaks the cone)
    assert 0.4 < prep.motion_time < 0.7 and prep.duration == pytest.approx(prep.motion_time + 0.3)
    grip = CupGrip.of(robot)
    shorter = held_quintic(robot, robot.q_flat, u0, prep.motion_time - 0.002, 300, DT)
    assert not cup_check(robot, shorter, DT, grip).passed
    looser = preparation_phase(robot, u0, grip=CupGrip(grip.geometric, safety_factor=1.0))
    assert looser.cup is not None and looser.cup.passed and looser.motion_time < prep.motion_time
