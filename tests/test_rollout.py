"""Tests of studio.sim.rollout: the MuJoCo scene and the rollout of robot + ball."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from studio import constants as C
from studio.errors import InvalidInputError
from studio.physics import ball as B
from studio.robot.description import BALL_CUP_FRAME
from studio.robot.model import load_robot
from studio.sim.options import RolloutOptions
from studio.sim.rollout import rollout
from studio.sim.scene import build_scene
from studio.toss.defaults import load_default_toss_model
from studio.toss.primitive import TOSS_SIDES
from studio.toss.release import find_release
from studio.toss.synthesis import make_toss
from studio.toss.synthetic import nominal_ball_path

DT = 1e-3


@pytest.fixture(scope="module")
def robot():
    return load_robot()


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _still(robot, duration: float) -> tuple[np.ndarray, np.ndarray]:
    """Time grid and commands holding the robot at rest at q_rest."""
    t = np.arange(int(round(duration / DT)) + 1) * DT
    return t, np.tile(robot.q_rest, (t.size, 1))


# --------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------


def test_scene_geometry(robot, scene) -> None:
    m = scene.model
    assert scene.joint_names == robot.joint_names
    assert build_scene() is scene  # cached

    def gid(name: str) -> int:
        return scene.geom_id(name)

    top = gid("table_top")
    assert m.geom_pos[top, 2] + m.geom_size[top, 2] == pytest.approx(0.0, abs=1e-12)
    assert m.geom_size[top, 0] == pytest.approx(C.TABLE_LENGTH / 2)
    assert m.geom_size[top, 1] == pytest.approx(C.TABLE_WIDTH / 2)
    floor = gid("floor")
    assert m.geom_type[floor] == mujoco.mjtGeom.mjGEOM_PLANE
    assert m.geom_pos[floor, 2] == pytest.approx(-0.76, abs=1e-12)
    net = gid("net")
    assert m.geom_pos[net, 2] + m.geom_size[net, 2] == pytest.approx(0.1525, abs=1e-12)
    for post in ("net_post_left", "net_post_right"):
        g = gid(post)
        assert m.geom_pos[g, 2] + m.geom_size[g, 2] == pytest.approx(0.1525, abs=1e-12)
        # outside of the post 15.25 cm beyond the side line
        assert abs(m.geom_pos[g, 1]) + m.geom_size[g, 1] == pytest.approx(C.TABLE_WIDTH / 2 + 0.1525, abs=1e-12)
    # ball: 40 mm sphere, 2.7 g, thin-shell inertia, free joint
    bg = scene.ball_geom
    assert m.geom_size[bg, 0] == pytest.approx(0.02)
    assert m.body_mass[scene.ball_body] == pytest.approx(0.0027)
    np.testing.assert_allclose(m.body_inertia[scene.ball_body], 2 / 3 * 0.0027 * 0.02**2, rtol=1e-12)
    assert m.jnt_type[scene.ball_joint] == mujoco.mjtJoint.mjJNT_FREE
    assert m.opt.gravity[2] == pytest.approx(-C.GRAVITY)
    # contact kinds: only the blade is "racket"; legs and lines never touch the ball
    kinds = {scene.geom_name(g): scene.geom_kind[g] for g in range(m.ngeom)}
    assert [n for n, k in kinds.items() if k == "racket"] == ["blade"]
    assert kinds["table_top"] == "table" and kinds["net"] == "net" and kinds["floor"] == "floor"
    assert kinds["net_post_left"] == "post" and kinds["handle"] == "robot"
    assert kinds["table_leg_0"] == "" and kinds["line_centre"] == "" and kinds["ball"] == ""
    visual = [g for g in range(m.ngeom) if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0]
    assert visual and all(scene.geom_kind[g] == "" for g in visual)
    # the MuJoCo cup site agrees with pinocchio's cup frame
    d = mujoco.MjData(m)
    d.qpos[scene.robot_qpos] = robot.q_flat
    mujoco.mj_kinematics(m, d)
    np.testing.assert_allclose(d.site_xpos[scene.cup_site], robot.cup_position(robot.q_flat), atol=1e-9)


# --------------------------------------------------------------------------------------
# Ball against the court: same physics as the predictor
# --------------------------------------------------------------------------------------


def test_drop_on_table_matches_predictor(robot, scene) -> None:
    t, u = _still(robot, 0.5)  # commands for 0.5 s, held until t_end = 1 s
    # ITTF drop test: ball bottom 30 cm above the surface
    s0 = B.BallState(np.array([0.6, 0.3, C.DROP_TEST_HEIGHT + C.BALL_RADIUS]), np.zeros(3), np.zeros(3))
    res = rollout(scene, t=t, u=u, ball=s0, t_end=1.0)
    ref = B.simulate(s0, 1.0)
    first = res.contacts[0]
    assert first.kind == "table" and first.part == "top" and first.side == "receiver"
    assert first.t == pytest.approx(ref.events[0].t, abs=1e-3)
    assert first.t == pytest.approx(ref.events[0].t, abs=1e-6)  # in fact far tighter
    assert first.p[2] == pytest.approx(C.BALL_RADIUS, abs=1e-6)
    np.testing.assert_allclose(first.v_after, ref.events[0].v_after, atol=1e-5)
    # rebound apex (ball bottom) as the predictor, and about the ITTF 23 cm
    k0, k1 = np.searchsorted(res.t, [res.contacts[0].t, res.contacts[1].t])
    apex = float(np.max(res.p[k0:k1, 2])) - C.BALL_RADIUS
    between = (ref.t > ref.events[0].t) & (ref.t < ref.events[1].t)
    apex_ref = float(np.max(ref.p[between, 2])) - C.BALL_RADIUS
    assert apex == pytest.approx(apex_ref, abs=5e-3)
    assert apex == pytest.approx(apex_ref, abs=1e-5)
    assert apex == pytest.approx(C.DROP_TEST_REBOUND, abs=0.01)
    assert res.end_reason == "t_end" and res.t.size == 1001 and res.t[-1] == pytest.approx(1.0)
    np.testing.assert_allclose(res.q, np.tile(robot.q_rest, (res.t.size, 1)), atol=1e-12)


def test_free_flight_with_spin_matches_predictor(robot, scene) -> None:
    t, u = _still(robot, 0.5)
    # serve-like: behind the end line, forward/sideways, top- and sidespin
    s0 = B.BallState(np.array([-1.45, -0.3, 0.30]), np.array([4.5, 0.8, 0.5]), np.array([-30.0, 250.0, 120.0]))
    res = rollout(scene, t=t, u=u, ball=s0)
    ref = B.simulate(s0, 0.5)
    on_grid = np.isin(np.round(ref.t, 9), np.round(res.t, 9))
    np.testing.assert_allclose(res.t, ref.t[on_grid], atol=1e-12)
    err = np.max(np.linalg.norm(res.p - ref.p[on_grid], axis=1))
    assert err < 3e-3
    assert err < 1e-5  # same flight equations and integrator: round-off only
    # a bounce on the server's half, then the net (the predictor files posts under "net")
    assert [c.kind for c in res.contacts] == [e.kind for e in ref.events] == ["table", "net"]
    for c, e in zip(res.contacts, ref.events, strict=True):
        assert c.t == pytest.approx(e.t, abs=1e-6)
        np.testing.assert_allclose(c.normal, e.normal, atol=1e-6)
        np.testing.assert_allclose(c.v_after, e.v_after, atol=1e-4)
        np.testing.assert_allclose(c.w_after, e.w_after, atol=1e-3)


def test_net_post_and_floor_contacts(robot, scene) -> None:
    t, u = _still(robot, 0.6)
    net = rollout(scene, t=t, u=u, ball=B.BallState(np.array([-0.4, 0.1, 0.09]), np.array([18.0, 0.0, 0.0]), np.zeros(3)))
    c = net.contacts[0]
    assert c.kind == "net" and c.geom == "net"
    assert c.p[0] == pytest.approx(-C.NET_THICKNESS / 2 - C.BALL_RADIUS, abs=1e-6)
    assert c.v_after[0] == pytest.approx(-0.1 * c.v_before[0], rel=1e-6)  # net restitution 0.1
    y_post = C.TABLE_WIDTH / 2 + C.NET_POST_OFFSET - C.NET_POST_SIZE / 2
    post = rollout(scene, t=t, u=u, ball=B.BallState(np.array([-0.4, y_post, 0.09]), np.array([6.0, 0.0, 0.0]), np.zeros(3)))
    assert post.contacts[0].kind == "post" and post.contacts[0].geom == "net_post_left"
    assert post.contacts[0].v_after[0] == pytest.approx(-0.5 * post.contacts[0].v_before[0], rel=1e-6)
    # off the side of the table, onto the floor: recorded, and the rollout stops there
    fl = rollout(scene, t=t, u=u, ball=B.BallState(np.array([0.3, 1.0, 0.1]), np.array([0.0, 1.0, 0.0]), np.zeros(3)))
    assert [x.kind for x in fl.contacts] == ["floor"] and fl.end_reason == "floor"
    assert fl.contacts[0].p[2] == pytest.approx(-0.76 + C.BALL_RADIUS, abs=1e-6)
    assert fl.t[-1] <= fl.t_final < fl.t[-1] + DT


# --------------------------------------------------------------------------------------
# Ball and robot
# --------------------------------------------------------------------------------------


def test_ball_into_robot_link(robot, scene) -> None:
    t, u = _still(robot, 0.3)
    d = mujoco.MjData(scene.model)
    d.qpos[scene.robot_qpos] = robot.q_rest
    mujoco.mj_kinematics(scene.model, d)
    c = d.geom_xpos[scene.geom_id("link_2_arm")].copy()
    s0 = B.BallState(c + np.array([0.0, 0.5, 0.0]), np.array([0.0, -5.0, 0.0]), np.zeros(3))
    res = rollout(scene, t=t, u=u, ball=s0)
    first = res.contacts[0]
    assert first.kind == "robot" and first.geom == "link_2_arm" and first.body == "link_2"
    assert not res.contacts_of("racket")
    assert first.normal[1] == pytest.approx(1.0, abs=1e-6)  # the arm's +Y side
    assert first.v_after[1] == pytest.approx(-0.5 * first.v_before[1], rel=1e-3)  # restitution 0.5
    assert res.first("robot") is first


def test_fast_ball_on_still_blade(robot, scene) -> None:
    """20 m/s onto face A of the parked racket: one contact, on the face, exact rebound."""
    t, u = _still(robot, 0.1)
    pose = robot.fk(robot.q_rest)
    n, R = pose.normal, np.array(pose.rotation)
    hit = pose.position + 0.02 * R[:, 0] + 0.03 * R[:, 1]  # off-centre point of the face
    v_in = -20.0 * (0.8 * n + 0.6 * R[:, 0])  # oblique, towards face A
    s0 = B.BallState(hit + (C.RACKET_HALF_THICKNESS + C.BALL_RADIUS) * n - 0.03 * v_in, v_in, np.array([0.0, 0.0, 80.0]))
    res = rollout(scene, t=t, u=u, ball=s0)
    assert [c.kind for c in res.contacts] == ["racket"]
    c = res.contacts[0]
    assert c.part == "face_a"
    # ball centre on the face plane at r + half thickness, when the predictor says
    assert float((c.p - pose.position) @ n) == pytest.approx(C.RACKET_HALF_THICKNESS + C.BALL_RADIUS, abs=1e-6)
    still = B.SampledRacketMotion([0.0, 0.1], [pose.position] * 2, [R] * 2)
    ev = B.simulate(s0, 0.1, racket=still).events_of("racket")
    assert len(ev) == 1 and c.t == pytest.approx(ev[0].t, abs=1e-6)
    np.testing.assert_allclose(c.point, c.p - C.BALL_RADIUS * n, atol=1e-9)
    assert float(np.linalg.norm(c.point - C.RACKET_HALF_THICKNESS * n - hit)) < 0.015  # drag bends the 0.6 m path
    np.testing.assert_allclose(c.surface_velocity, 0.0, atol=1e-12)
    v_exp, w_exp = B.RacketModel.default().bounce_moving(c.v_before, c.w_before, R, np.zeros(3), 1.0)
    np.testing.assert_allclose(c.v_after, v_exp, atol=1e-6)
    np.testing.assert_allclose(c.w_after, w_exp, atol=1e-5)
    e = float(c.v_after @ n) / -float(c.v_before @ n)  # normal restitution at ~15 m/s
    assert 0.3 < e < 0.9


def _sweep(robot) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gantry-X sweep at q_rest (face B of the racket looks to +X): t, u, predicted X."""
    t = np.arange(801) * DT
    s = np.clip((t - 0.25) / 0.45, 0.0, 1.0)
    u = np.tile(robot.q_rest, (t.size, 1))
    u[:, 0] = -0.8 + 1.0 * (10 * s**3 - 15 * s**4 + 6 * s**5)
    X = robot.dynamics.simulate(u, DT, np.stack([u[0], np.zeros(8)], axis=1))
    return t, u, X


def test_racket_sweep_hits_falling_ball_once(robot, scene) -> None:
    t, u, X = _sweep(robot)
    k = int(np.argmax(X[:, 0, 1]))  # fastest gantry sample
    target = robot.fk(X[k, :, 0]).position + np.array([0.03, 0.01, 0.02])
    z0 = target[2] + 0.5 * C.GRAVITY * t[k] ** 2
    for _ in range(4):  # drop height that brings the ball (with drag) to the target at t[k]
        z0 += target[2] - B.simulate(B.BallState(np.array([*target[:2], z0]), np.zeros(3), np.zeros(3)), t[k]).p[-1, 2]
    s0 = B.BallState(np.array([*target[:2], z0]), np.zeros(3), np.zeros(3))
    res = rollout(scene, t=t, u=u, ball=s0, t_end=0.8)
    rk = res.racket_contacts
    assert len(rk) == 1 and not res.contacts_of("robot")
    c = rk[0]
    assert c.part == "face_b" and c.geom == "blade"
    assert abs(c.t - t[k]) < 0.01
    # outgoing state from the calibrated racket model, with the racket state computed
    # independently (pinocchio) at the contact instant
    qc = np.array([np.interp(c.t, t, X[:, j, 0]) for j in range(8)])
    qdc = np.array([np.interp(c.t, t, X[:, j, 1]) for j in range(8)])
    pose = robot.fk(qc)
    v_r, w_r = robot.racket_velocity(qc, qdc)
    v_point = v_r + np.cross(w_r, c.point - pose.position)
    np.testing.assert_allclose(c.surface_velocity, v_point, atol=2e-3)
    np.testing.assert_allclose(c.normal, -pose.normal, atol=1e-6)  # face B = -z of the racket
    v_exp, w_exp = B.RacketModel.default().bounce_moving(c.v_before, c.w_before, pose.rotation, v_point, -1.0)
    np.testing.assert_allclose(c.v_after, v_exp, atol=5e-3)
    np.testing.assert_allclose(c.w_after, w_exp, atol=0.5)
    # and with the predictor's own racket contact search (thin slab, sampled racket)
    win = slice(k - 150, k + 150)
    poses = [robot.fk(q) for q in X[win, :, 0]]
    vel = [robot.racket_velocity(q, qd) for q, qd in zip(X[win, :, 0], X[win, :, 1], strict=True)]
    motion = B.SampledRacketMotion(
        t[win], np.array([p.position for p in poses]), np.array([p.rotation for p in poses]),
        v=np.array([v for v, _ in vel]), omega=np.array([w for _, w in vel]),
    )
    ref = B.simulate(s0, 0.8, racket=motion)
    ev = ref.events_of("racket")
    assert len(ev) == 1 and ev[0].part == "face_b"
    assert c.t == pytest.approx(ev[0].t, abs=1e-4)
    np.testing.assert_allclose(c.v_after, ev[0].v_after, atol=0.02)
    # physics: the ball leaves faster than the racket along the face normal, topspin-free
    assert c.v_after[0] > c.surface_velocity[0] > 1.5


def _vertical_lift(robot) -> tuple[np.ndarray, np.ndarray]:
    """A toss written here: the cup moves straight up, racket flat (pinocchio IK).

    Cup speed: smootherstep up to 2 m/s in 0.25 s, then down to 0 in 0.15 s (peak
    deceleration 25 m/s^2 > g: the ball leaves). Returns t (N,) and X (N, 8, 2).
    """
    t = np.arange(1101) * DT
    V, t1, Ta, Tb = 2.0, 0.05, 0.25, 0.15

    def integral(x):  # of the smootherstep 6x^5 - 15x^4 + 10x^3 from 0 to x
        return x**6 - 3 * x**5 + 2.5 * x**4

    xa = np.clip((t - t1) / Ta, 0, 1)
    xb = np.clip((t - t1 - Ta) / Tb, 0, 1)
    z = V * Ta * integral(xa) + V * Tb * (xb - integral(xb))
    q = np.array(robot.q_flat, dtype=float)
    p0 = robot.cup_position(q)
    R0 = np.array(robot.fk(q).rotation)
    Q = np.empty((t.size, 8))
    for i, dz in enumerate(z):
        target = p0 + np.array([0.0, 0.0, dz])
        for _ in range(20):
            R = np.array(robot.fk(q).rotation)
            e = np.concatenate([target - robot.cup_position(q), 0.5 * np.sum(np.cross(R, R0, axis=0), axis=1)])
            if np.linalg.norm(e) < 1e-12:
                break
            J = robot.frame_jacobian(BALL_CUP_FRAME, q)[:, 2:]
            q[2:] += np.linalg.solve(J, e)
        Q[i] = q
    QD = np.gradient(Q, t, axis=0, edge_order=2)
    return t, np.stack([Q, QD], axis=2)


def test_vertical_toss_release_and_apex(robot, scene) -> None:
    t, X = _vertical_lift(robot)
    res = rollout(scene, t=t, X=X, ball="cup")
    # the toss model on the same motion, with pinocchio's kinematics
    cup = np.array([robot.cup_position(q) for q in X[:, :, 0]])
    rot = np.array([robot.fk(q).rotation for q in X[:, :, 0]])
    rel = find_release(t, cup, rot[:, :, 2], rotation=rot)
    assert rel is not None and res.release is not None
    assert res.release_t == pytest.approx(rel.time, abs=1e-6)
    assert 0.30 < rel.time < 0.40  # during the deceleration phase
    np.testing.assert_allclose(res.release.velocity, rel.velocity, atol=1e-6)
    before = res.t < rel.time
    np.testing.assert_allclose(res.p[before], cup[: np.count_nonzero(before)], atol=1e-9)
    flight = B.simulate(B.BallState(rel.position, rel.velocity, rel.angular_velocity), 1.0, t0=rel.time)
    k_apex = int(np.argmax(res.p[:, 2]))
    apex_ref = float(np.max(flight.p[:, 2]))
    assert res.p[k_apex, 2] == pytest.approx(apex_ref, abs=0.01)
    assert res.p[k_apex, 2] == pytest.approx(apex_ref, abs=1e-4)
    assert res.p[k_apex, 2] - rel.position[2] > C.TOSS_MIN_RISE
    # nothing touched on the way up; the ball falls back onto the racket later
    assert all(c.t > res.t[k_apex] for c in res.contacts)
    assert res.contacts and res.contacts[0].kind in ("robot", "racket")
    up_down = res.t < res.contacts[0].t
    assert np.all(np.abs(res.p[up_down, 0:2] - cup[0, 0:2]) < 1e-6)  # straight up and down


def test_make_toss_release_matches_primitive(robot, scene) -> None:
    prim = make_toss(robot, "right")
    res = rollout(scene, t=prim.t, u=prim.u, X0=prim.X[0], ball="cup")
    assert res.release_t == pytest.approx(prim.release.time, abs=1e-6)
    tn, pn, _ = nominal_ball_path(prim)
    first = res.contacts[0].t if res.contacts else math.inf
    m = min(len(tn), int(np.searchsorted(res.t, first)))
    np.testing.assert_allclose(res.p[:m], pn[:m], atol=1e-3)
    # stopped before the release: the ball is still in the cup
    early = rollout(scene, t=prim.t, X=prim.X, ball="cup", t_end=0.2)
    assert early.end_reason == "in_cup" and early.release is None and not early.contacts
    np.testing.assert_allclose(early.p, prim.cup_p[: early.t.size], atol=1e-9)


@pytest.mark.parametrize("side", TOSS_SIDES)
def test_default_toss_ball_flies_free_of_the_robot(scene, side) -> None:
    """The shipped toss: the ball leaves the cup when the toss module says, rises and
    falls back past the racket (which steps aside and down) without touching anything."""
    model = load_default_toss_model(side)
    prim = model.primitive
    t_rel = prim.release.time
    res = rollout(scene, t=prim.t, u=prim.u, X0=prim.X[0], ball="cup", t_end=t_rel + 1.0)
    assert res.release is not None
    assert res.release_t == pytest.approx(t_rel, abs=1e-3)
    # rises >= 16 cm above the release (ITTF 2.6.2), apex as the recordings' mean path
    apex = float(np.max(res.p[:, 2]))
    assert apex - res.release.position[2] >= C.TOSS_MIN_RISE
    assert apex == pytest.approx(float(np.max(model.p[:, 2])), abs=0.01)
    # no contact of any kind (cup, racket, arm, table, ...) until the ball falls below
    # the table level z = 0, or 1 s after the release
    below = np.flatnonzero((res.t > res.t[int(np.argmax(res.p[:, 2]))]) & (res.p[:, 2] < 0.0))
    t_free = min(float(res.t[below[0]]) if below.size else math.inf, t_rel + 1.0)
    assert below.size and res.t[below[0]] < t_rel + 1.0  # the ball does get below z = 0 here
    assert [c for c in res.contacts if c.t <= t_free] == []
    # straight up and down on the cup's vertical line (no push at the release)
    flight = (res.t > t_rel) & (res.t <= t_free)
    assert np.max(np.abs(res.p[flight, 0:2] - res.release.position[0:2])) < 1e-3


# --------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------


def test_bad_input_names_the_argument(robot, scene) -> None:
    t, u = _still(robot, 0.1)
    s0 = B.BallState(np.zeros(3) + [0, 0, 0.3], np.zeros(3), np.zeros(3))
    with pytest.raises(InvalidInputError, match=r"\bu\b.*shape"):
        rollout(scene, t=t, u=u[:, :7], ball=s0)
    with pytest.raises(InvalidInputError, match=r"\bu\b.*shape"):
        rollout(scene, t=t, u=u[:-1], ball=s0)
    bad = u.copy()
    bad[5, 3] = np.nan
    with pytest.raises(InvalidInputError, match=r"\bu\b is not finite at index \(5, 3\)"):
        rollout(scene, t=t, u=bad, ball=s0)
    with pytest.raises(InvalidInputError, match=r"\bX0\b"):
        rollout(scene, t=t, u=u, X0=np.zeros((8, 3)), ball=s0)
    t_bad = t.copy()
    t_bad[10] += 3e-4
    with pytest.raises(InvalidInputError, match=r"\bt\b.*uniform"):
        rollout(scene, t=t_bad, u=u, ball=s0)
    with pytest.raises(InvalidInputError, match=r"\bball\b"):
        rollout(scene, t=t, u=u, ball="hand")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match=r"\bt_end\b"):
        rollout(scene, t=t, u=u, ball=s0, t_end=-1.0)
    with pytest.raises(InvalidInputError, match=r"\bX\b"):
        rollout(scene, t=t, X=np.zeros((t.size, 8, 2)), ball=s0, t_end=0.5)
    with pytest.raises(InvalidInputError, match="substep"):
        RolloutOptions(substep=0.0)
