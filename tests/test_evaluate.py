"""Serve evaluation: shipped examples are legal, failures are verdicts, JSON and scene output."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from studio.errors import InvalidInputError
from studio.serve.evaluate import EvaluationContext, evaluate_robust, evaluate_serve, report_markdown
from studio.serve.params import HandServe, ServeParams, load_serve
from studio.serve.reward import PLANNER_FAILURE_PENALTY
from studio.ui.scene import scene_frame

EXAMPLES = sorted((Path(__file__).resolve().parent.parent / "examples" / "serves").glob("*.json"))


@pytest.fixture(scope="module")
def context() -> EvaluationContext:
    return EvaluationContext.default()


def test_examples_cover_the_spins() -> None:
    serves = [load_serve(p) for p in EXAMPLES]
    assert len({s.params for s in serves}) == len(serves)  # six different serves
    kinds = {(s.side, s.extra.get("spin")) for s in serves}
    for side in ("right", "left"):
        for spin in ("topspin", "backspin", "sidespin"):
            assert (side, spin) in kinds, f"no {spin} example for the {side} toss"


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_every_example_serve_is_legal(path: Path, context: EvaluationContext) -> None:
    serve = load_serve(path)
    ev = evaluate_serve(serve, context, task=serve.task or "topspin_velocity")
    assert ev.legal, ev.reason
    assert ev.plan is not None and ev.plan.ok
    sb = ev.metrics.second_bounce  # type: ignore[union-attr]
    assert sb is not None and sb["p"][0] > 0  # second bounce on the receiver's court
    spin = serve.extra["spin"]
    if spin == "topspin":
        assert sb["topspin"] > 50
    elif spin == "backspin":
        # the ball crosses the net with backspin; the two table bounces erode it
        assert ev.metrics.net["topspin"] < -50  # type: ignore[union-attr,index]
        assert sb["topspin"] < 10
    else:
        assert abs(sb["sidespin"]) > 100 and abs(sb["sidespin"]) > 0.9 * abs(sb["topspin"])
    assert ev.reward.s_leg == 0.0 and ev.reward.total > 0


def test_unreachable_serve_is_a_verdict_not_an_error(context: EvaluationContext) -> None:
    # contact right after the lift: no time to strike
    early = HandServe(name="early", side="right", params=ServeParams(tau=0.40, velocity=(3.0, 0, 0), yaw=math.pi / 2, roll=0.0))
    ev = evaluate_serve(early, context)
    assert ev.status == "planner_failed" and "no time" in ev.reason
    assert ev.reward.total == PLANNER_FAILURE_PENALTY
    # racket faster than the arm can move
    fast = HandServe(name="fast", side="right", params=ServeParams(tau=0.85, velocity=(10.0, -5.0, 5.0), yaw=-1.0, roll=2.5))
    ev = evaluate_serve(fast, context)
    assert ev.status in ("planner_failed", "collision")
    assert ev.reward.total == PLANNER_FAILURE_PENALTY
    assert ev.to_json()["failed_check"] in ("planner_failed", "collision")
    status, checks, _ = report_markdown(ev)
    assert "NO PLAN" in status or "COLLISION" in status


def test_contact_time_outside_the_toss_is_rejected(context: EvaluationContext) -> None:
    serve = HandServe(name="late", side="left", params=ServeParams(tau=2.9, velocity=(3.0, 0, 0), yaw=math.pi / 2, roll=0.0))
    with pytest.raises(InvalidInputError, match="tau = 2.900 s is outside"):
        evaluate_serve(serve, context)


def test_json_and_scene_of_a_legal_serve(context: EvaluationContext) -> None:
    serve = load_serve(EXAMPLES[0])
    ev = evaluate_serve(serve, context)
    out = ev.to_json()
    for key in ("legal", "failed_check", "reward", "terms", "second_bounce", "net_clearance", "max_height", "planner"):
        assert key in out
    # the robot's own check beside the ITTF chain: the ball stays in the cup until the release
    assert out["cup_hold"]["passed"] and out["cup_hold"]["worst_ratio"] <= out["cup_hold"]["limit"]
    assert "pass | ball stays in cup (preparation + toss) | none | worst f_t/f_n" in report_markdown(ev)[1]
    assert out["failed_check"] is None and out["planner"]["status"] == "ok"
    for key in ("p", "v", "w", "topspin", "sidespin"):
        assert key in out["second_bounce"]
    frame = scene_frame(ev, context)
    names = [s.name for s in frame.segments]
    assert names[:2] == ["toss", "flight"]
    assert [m.label for m in frame.markers][:3] == ["racket", "bounce 1", "bounce 2"]
    assert frame.playback is not None and frame.playback.q is not None
    assert frame.playback.q.shape == (len(frame.playback.t), 8)
    # the ball is drawn in the cup before lift and in flight after
    assert np.isfinite(frame.playback.ball).all(axis=1).mean() > 0.5


def test_robust_evaluation_plans_once(context: EvaluationContext) -> None:
    serve = load_serve(EXAMPLES[0])
    robust = evaluate_robust(serve, context, tosses=5, rng=np.random.default_rng(3))
    assert len(robust.evaluations) == 5
    plans = {id(e.plan) for e in robust.evaluations}
    assert len(plans) == 1
    rewards = [e.reward.total for e in robust.evaluations]
    assert robust.reward == pytest.approx(np.mean(rewards))
    assert 0.0 <= robust.legal_fraction <= 1.0
    j = robust.to_json()
    assert sum(j["failed_checks"].values()) == sum(not e.legal for e in robust.evaluations)
    assert j["failed_check"] is None if robust.legal else j["failed_check"] == max(j["failed_checks"], key=j["failed_checks"].get)
    with pytest.raises(InvalidInputError, match="tosses must be in"):
        evaluate_robust(serve, context, tosses=999)


def test_vectorized_racket_poses_match_pinocchio(context: EvaluationContext) -> None:
    robot = context.robot
    rng = np.random.default_rng(7)
    Q = np.array([robot.clip_to_limits(robot.q_flat + rng.normal(0.0, 0.4, 8)) for _ in range(20)])
    P, R = context.racket_poses(Q)
    for i, q in enumerate(Q):
        pose = robot.fk(q)
        np.testing.assert_allclose(P[i], pose.position, atol=1e-12)
        np.testing.assert_allclose(R[i], pose.rotation, atol=1e-12)


def test_backspin_net_task_rewards_the_backspin_at_the_net(context: EvaluationContext) -> None:
    serve = load_serve(Path(__file__).resolve().parent.parent / "examples" / "serves" / "backspin_right.json")
    paper = evaluate_serve(serve, context, task="backspin")
    net = evaluate_serve(serve, context, task="backspin_net")
    assert paper.legal and net.legal
    tb_net = net.metrics.net["topspin"]  # type: ignore[union-attr,index]
    assert tb_net < -50
    assert net.reward.r_topback == pytest.approx(min(-tb_net, 500.0) / 500.0)
    assert net.reward.r_topback > paper.reward.r_topback + 0.1


def test_dynamic_limit_expansion_plans_what_the_robots_limits_cannot(context: EvaluationContext) -> None:
    """The paper's dynamic limit expansion: a fast strike (8.5 m/s racket, 0.9 s back to rest)
    is beyond the robot's acceleration/jerk limits and within 1.5 times them; the expanded
    plan keeps the expanded limits at 1 kHz and uses more than the robot's own."""
    from dataclasses import replace

    from studio.serve.evaluate import plan_motion
    from studio.serve.params import LimitScale

    x = [0.8769, 8.5431, -0.5962, 4.5459, 1.5701, -0.4698, 0.8962, 0.0693, 0.0629, -0.0056]
    serve = HandServe(name="fast", side="right", params=ServeParams.from_vector(x))
    base = plan_motion(serve, context)
    assert base.failure is not None and base.failure[0] == "planner_failed"  # SQP: limits; IPOPT fallback: outside the tolerances
    scale = LimitScale.uniform(1.5)
    fast = plan_motion(replace(serve, limit_scale=scale), context)
    assert fast.failure is None and fast.plan is not None and fast.plan.ok
    assert context.planner_for(scale) is context.planner_for(LimitScale.uniform(1.5))  # built once
    assert context.planner_for(LimitScale()) is context.planner
    robot, plan = context.robot.limits, fast.plan
    expanded = scale.apply(robot)
    tol = 1 + 1e-6
    assert np.all(np.abs(plan.ud) <= expanded.velocity * tol)
    assert np.all(np.abs(plan.udd) <= expanded.acceleration * tol)
    assert np.all(np.abs(plan.jerk) <= expanded.jerk * tol)
    used = max(float(np.max(np.abs(plan.udd) / robot.acceleration)), float(np.max(np.abs(plan.jerk) / robot.jerk)))
    assert used > 1.05  # the plan needs the expansion
    assert evaluate_serve(replace(serve, limit_scale=scale), context).plan is not None


def test_effort_report_of_a_planned_serve(context: EvaluationContext) -> None:
    from studio.serve.efforts import effort_report
    from studio.serve.evaluate import plan_motion

    motion = plan_motion(load_serve(Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json"), context)
    rep = effort_report(motion, context.robot)
    assert rep is not None and rep.names == context.robot.joint_names
    t_end = motion.preparation.duration + motion.t[-1] + 0.3  # on the exported clock: preparation first, final hold last
    assert np.all(rep.peak >= 0) and np.all((rep.at >= 0.0) & (rep.at <= t_end))
    np.testing.assert_allclose(rep.usage, rep.peak / context.robot.effort_limits)
    name, use = rep.worst
    assert use == pytest.approx(rep.usage.max()) and name in rep.names
    # the peaks are at least the static gravity loads of the motion's own configurations
    static = np.abs(context.robot.joint_efforts(motion.q[::50], np.zeros_like(motion.q[::50]), np.zeros_like(motion.q[::50]))).max(axis=0)
    assert np.all(rep.peak >= static - 1.0)
    assert set(rep.to_json()) == {"names", "peak", "at", "limit", "usage", "within", "exceeded", "raised"} and "Joint efforts" in rep.markdown()
    unplanned = plan_motion(HandServe(name="early", side="right", params=ServeParams(tau=0.40, velocity=(3.0, 0, 0), yaw=math.pi / 2, roll=0.0)), context)
    assert effort_report(unplanned, context.robot) is None


def test_mujoco_rollout_follows_the_ball_past_the_end_of_the_motion(context: EvaluationContext) -> None:
    """Regression (issue: "rollout: X covers 1496 samples, t_end = 2.5224 needs 2524"):
    the ball flies on after the robot is back at rest, so the rollout needs the robot's
    states beyond the motion: the plan's own, then the joint model holding the last command."""
    from studio.serve.evaluate import FLIGHT_AFTER_CONTACT, plan_motion

    serve = load_serve(Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json")
    t_end = serve.params.tau + FLIGHT_AFTER_CONTACT
    motion = plan_motion(serve, context)
    assert motion.t is not None and motion.q is not None and motion.qd is not None and motion.u is not None
    M = len(motion.t)
    assert motion.t[-1] < t_end  # the case of the issue
    X = motion.joint_states(t_end, context.robot.dynamics)
    assert X.shape == (math.ceil((t_end - motion.t[0]) / 1e-3 - 1e-9) + 1, 8, 2)  # the grid through t_end
    np.testing.assert_array_equal(X[:M, :, 0], motion.q)
    np.testing.assert_array_equal(X[:M, :, 1], motion.qd)
    # the exact velocities are those of the positions (central differences at 1 kHz)
    np.testing.assert_allclose(np.gradient(motion.q, motion.t, axis=0)[1:-1], motion.qd[1:-1], atol=0.02)
    # after the motion: continuous, settling on the last command, at rest
    seam = X[M - 3 : M + 3]  # positions advance by the mean velocity of each step, across the seam too
    np.testing.assert_allclose(np.diff(seam[:, :, 0], axis=0), 0.5e-3 * (seam[1:, :, 1] + seam[:-1, :, 1]), atol=1e-6)
    np.testing.assert_allclose(X[-1, :, 0], motion.u[-1], atol=1e-4)
    np.testing.assert_allclose(X[-1, :, 1], 0.0, atol=1e-3)

    ev = evaluate_serve(serve, context, task=serve.task or "topspin_velocity", mujoco=True)
    r = ev.rollout
    assert r is not None and ev.legal, ev.reason
    assert [c.kind for c in r.contacts][:3] == ["racket", "table", "table"] and r.contacts[0].part == "face_a"
    assert r.contacts[2].t > motion.t[-1]  # the second bounce comes after the motion's end
    assert r.end_reason == "floor" and r.t[-1] == pytest.approx(r.t_final, abs=1e-3) and r.t_final < t_end
    np.testing.assert_allclose(r.q[:M], motion.q, atol=1e-12)
    # the toss checks use the rollout's own release from the cup
    rise = next(c for c in ev.legality.checks if c.name == "toss_rise")  # type: ignore[union-attr]
    assert r.release is not None
    k = (r.t >= r.release.time) & (r.t <= r.contacts[0].t)
    assert rise.detail == f"rise {100 * (r.p[k, 2].max() - r.release.position[2]):.1f} cm"
    # the analytic verdict, about the same ball
    an = evaluate_serve(serve, context, task=serve.task or "topspin_velocity")
    assert an.legal and abs(ev.reward.total - an.reward.total) < 0.05
    np.testing.assert_allclose(np.array(ev.metrics.bounces[:2])[:, :2], np.array(an.metrics.bounces)[:, :2], atol=0.08)  # type: ignore[union-attr]


def test_mujoco_rollout_cannot_replay_a_recorded_toss(context: EvaluationContext) -> None:
    serve = load_serve(EXAMPLES[0])
    with pytest.raises(InvalidInputError, match="MuJoCo rollout tosses the ball from the cup"):
        evaluate_serve(serve, context, toss_sample=0, mujoco=True)


def test_robust_evaluation_flies_each_toss_through_its_own_recording(context: EvaluationContext) -> None:
    """Each recorded toss's ball reaches the strike where that recording has it (the state
    from its own samples around tau), not where a flight from its noisy state just after
    the lift would put it (39-49 mm away, median)."""
    serve = load_serve(EXAMPLES[0])
    tau = serve.params.tau
    toss = context.toss_model(serve.side)
    robust = evaluate_robust(serve, context, tosses=4, rng=np.random.default_rng(5))
    for k, ev in zip(robust.samples, robust.evaluations):
        assert ev.ball is not None
        start = toss.recorded_start_state(k, toss.t_lift + 0.005, tau, flight=context.flight)
        assert np.allclose(ev.ball.p[0], start.p) and np.allclose(ev.ball.v[0], start.v)
        t_before = tau - 0.01  # before the racket reaches the ball
        p_before = np.array([np.interp(t_before, ev.ball.t, ev.ball.p[:, j]) for j in range(3)])
        assert np.linalg.norm(p_before - toss.recorded_state_at(t_before, k).p) < 1.5e-3
        rec = toss.recordings.recordings[k]  # on the command clock: its raw samples around tau
        near = np.abs(rec.t - tau) <= 0.03
        p_rec = np.array([np.polyval(np.polyfit(rec.t[near] - tau, rec.p[near, j], 2), 0.0) for j in range(3)])
        hits = ev.ball.events_of("racket")
        assert hits and abs(hits[0].t - tau) < 0.01
        p_hit_rec = p_rec + toss.recorded_state_at(tau, k).v * (hits[0].t - tau)
        assert np.linalg.norm(hits[0].p - p_hit_rec) < 3e-3


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_ball_meets_the_rubber_at_tau_with_the_racket_state_the_file_asks(context: EvaluationContext, path: Path) -> None:
    """tau is the contact time: the simulated ball's racket event (the ball simulator's own
    root finding) against the racket pose from pinocchio FK of the planned joints."""
    serve = load_serve(path)
    ev = evaluate_serve(serve, context, task=serve.task)
    assert ev.ball is not None and ev.motion.t is not None and ev.motion.q is not None
    hit = next(e for e in ev.ball.events if e.kind == "racket")
    p = serve.params
    assert abs(hit.t - p.tau) < 1e-3
    t, q = np.asarray(ev.motion.t), np.asarray(ev.motion.q)
    i = int(np.searchsorted(t, hit.t))
    before, after = context.robot.fk(q[i - 1]), context.robot.fk(q[i])
    v = (after.position - before.position) / (t[i] - t[i - 1])
    assert np.linalg.norm(v - np.asarray(p.velocity)) < 0.02
    n_file = np.asarray(p.normal) / np.linalg.norm(p.normal)
    assert math.degrees(math.acos(min(1.0, float(after.normal @ n_file)))) < 0.5
    # the ball centre is one standoff (radius + half thickness) from the face plane at contact
    centre = before.position + v * (hit.t - t[i - 1])
    gap = abs(float((hit.p - centre) @ after.normal))
    assert gap == pytest.approx(0.027, abs=0.002)


def test_contact_at_tau_with_an_offset_and_with_face_b(context: EvaluationContext) -> None:
    """An offset with a normal part (dropped: the contact stays at tau) and the same stroke
    with the opposite normal (the ball then meets face B, one standoff on the other side)."""
    from dataclasses import replace

    serve = load_serve(EXAMPLES[0].parent / "topspin_right.json")
    p = serve.params
    cases = [(replace(p, offset=(0.02, -0.03, 0.01)), "face_a"), (replace(p, yaw=p.yaw + math.pi, roll=-p.roll), "face_b")]
    for params, face in cases:
        ev = evaluate_serve(replace(serve, params=params), context, task=serve.task)
        assert ev.ball is not None
        hit = next(e for e in ev.ball.events if e.kind == "racket")
        assert abs(hit.t - params.tau) < 1e-3 and hit.part == face
