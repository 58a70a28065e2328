"""Tests of the serve robot model: generator, kinematics, limits, joint dynamics."""

from __future__ import annotations

import math
import tomllib
import warnings
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from scipy.optimize import least_squares

from studio import constants as C
from studio.cli import main as cli_main
from studio.errors import InvalidInputError, RobotModelError
from studio.paths import robots_dir
from studio.robot import description as rd
from studio.robot.model import JointDynamics, JointLimits, Robot, load_robot

TOML_PATH = robots_dir() / rd.TOML_NAME


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot()


@pytest.fixture(scope="module")
def raw_toml() -> dict:
    return tomllib.loads(TOML_PATH.read_text(encoding="utf-8"))


def _random_qs(robot: Robot, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(robot.limits.lower, robot.limits.upper, size=(n, robot.nq))


# --- generated files ----------------------------------------------------------------


def test_generated_files_up_to_date() -> None:
    assert rd.check_files() == []
    assert cli_main(["robot-files", "--check"]) == 0


def test_check_detects_stale_file(tmp_path: Path) -> None:
    rd.write_files(tmp_path)
    assert rd.check_files(tmp_path) == []
    urdf = tmp_path / rd.URDF_NAME
    urdf.write_text(urdf.read_text().replace('name="a3"', 'name="a3x"'))
    assert rd.check_files(tmp_path) == [rd.URDF_NAME]
    assert cli_main(["robot-files", "--check", "--out", str(tmp_path)]) == 1


def test_pinocchio_and_mujoco_agree(robot: Robot) -> None:
    model = mujoco.MjModel.from_xml_path(str(robots_dir() / rd.MJCF_NAME))
    data = mujoco.MjData(model)
    adr = [model.joint(name).qposadr[0] for name in robot.joint_names]
    assert [model.actuator(i).name for i in range(model.nu)] == list(robot.joint_names)
    sr, sc = model.site("racket").id, model.site("ball_cup").id
    for q in _random_qs(robot, 50, seed=1):
        data.qpos[adr] = q
        mujoco.mj_kinematics(model, data)
        pose = robot.fk(q)
        np.testing.assert_allclose(data.site_xpos[sr], pose.position, atol=1e-6)
        np.testing.assert_allclose(data.site_xmat[sr].reshape(3, 3), pose.rotation, atol=1e-6)
        np.testing.assert_allclose(data.site_xpos[sc], robot.cup_position(q), atol=1e-6)


def test_mujoco_ball_rests_in_cup(robot: Robot) -> None:
    """Composed scene (module docstring recipe): a ball dropped off-centre into the cup
    at q_flat self-centres on the rim, at the ball_cup site."""
    scene = mujoco.MjSpec()
    scene.option.timestep = 0.001
    frame = scene.worldbody.add_frame()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene.attach(rd.robot_mjspec(), frame=frame, prefix="")
        cup = robot.cup_position(robot.q_flat)
        ball = scene.worldbody.add_body(name="ball", pos=cup + np.array([0.006, -0.004, 0.01]))
        ball.add_freejoint()
        ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[C.BALL_RADIUS, 0, 0], mass=C.BALL_MASS)
        model = scene.compile()
    data = mujoco.MjData(model)
    adr = [model.joint(name).qposadr[0] for name in robot.joint_names]
    data.qpos[adr] = robot.q_flat
    data.ctrl[:] = robot.q_flat
    for _ in range(1000):
        mujoco.mj_step(model, data)
    ball_pos = data.body("ball").xpos
    assert np.linalg.norm(ball_pos - data.site("ball_cup").xpos) < 1e-3
    np.testing.assert_allclose(data.qpos[adr], robot.q_flat, atol=1e-4)  # gravcomp: only the ball sags it


def test_urdf_loads_in_yourdfpy() -> None:
    import yourdfpy

    urdf = yourdfpy.URDF.load(str(robots_dir() / rd.URDF_NAME))
    assert tuple(urdf.actuated_joint_names) == load_robot().joint_names
    assert {"racket", "ball_cup", "gantry_bridge", "gantry_carriage"} <= set(urdf.link_map)
    assert urdf.scene is not None


# --- kinematics ---------------------------------------------------------------------


def test_racket_frame_and_geometry(robot: Robot) -> None:
    assert robot.nq == 8 and len(robot.joint_names) == 8
    q = robot.q_flat
    pose = robot.fk(q)
    R = pose.rotation
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(pose.normal, R[:, 2])
    # ball_cup: on the handle side (-y), face-A side (+z), at the resting height.
    d = R.T @ (robot.cup_position(q) - pose.position)
    r = robot.spec.racket
    rim_top = 0.5 * r.handle_thickness + r.cup_plate_thickness + r.cup_wall_height
    assert d[1] == pytest.approx(r.cup_y, abs=1e-9)
    assert d[2] == pytest.approx(rim_top + math.sqrt(C.BALL_RADIUS**2 - r.cup_rim_radius**2), abs=1e-9)
    # The handle continues the flange axis: flange -> racket along racket y.
    f = robot.frame_pose("flange", q)
    np.testing.assert_allclose(f.rotation[:, 2], R[:, 1], atol=1e-9)
    np.testing.assert_allclose(pose.position - f.position, r.mount_offset * R[:, 1], atol=1e-9)


def test_kuka_geometry_at_home(robot: Robot) -> None:
    """KUKA home (A2 = -90, A3 = +90 deg): upper arm vertical, forearm horizontal."""
    q = np.zeros(8)
    q[3], q[4] = -np.pi / 2, np.pi / 2
    base = robot.frame_position("arm_base", q)
    wrist = robot.frame_position("link_5", q)
    flange = robot.frame_position("flange", q)
    np.testing.assert_allclose(wrist - base, [0.025 + 0.420, 0.0, 0.400 + 0.455 + 0.035], atol=1e-9)
    np.testing.assert_allclose(flange - wrist, [0.080, 0.0, 0.0], atol=1e-9)
    # Positive A1 turns clockwise seen from above (KUKA): +x swings towards -y.
    q[2] = 0.1
    assert robot.frame_position("link_5", q)[1] < base[1] - 0.01


def test_velocity_and_jacobian_match_finite_differences(robot: Robot) -> None:
    rng = np.random.default_rng(2)
    h = 1e-6
    for q in _random_qs(robot, 10, seed=3):
        qd = rng.normal(size=8)
        J = robot.racket_jacobian(q)
        v, w = robot.racket_velocity(q, qd)
        np.testing.assert_allclose(J[:3] @ qd, v, atol=1e-10)
        np.testing.assert_allclose(J[3:] @ qd, w, atol=1e-10)
        p_plus, p_minus = robot.fk(q + h * qd), robot.fk(q - h * qd)
        v_fd = (p_plus.position - p_minus.position) / (2 * h)
        R0 = robot.fk(q).rotation
        dR = (p_plus.rotation - p_minus.rotation) / (2 * h)
        W = dR @ R0.T  # skew(omega) in world
        w_fd = np.array([W[2, 1], W[0, 2], W[1, 0]])
        np.testing.assert_allclose(v, v_fd, atol=1e-6)
        np.testing.assert_allclose(w, w_fd, atol=1e-6)
        assert np.linalg.norm(robot.fk(q).normal) == pytest.approx(1.0, abs=1e-12)


def test_check_configuration_and_clip(robot: Robot) -> None:
    q = robot.q_rest.copy()
    np.testing.assert_array_equal(robot.check_configuration(q), q)
    q[5] = np.nan
    with pytest.raises(InvalidInputError, match="'a4'"):
        robot.check_configuration(q)
    with pytest.raises(InvalidInputError, match="'a4'"):
        robot.fk(q)
    q = robot.q_rest.copy()
    q[1] = 5.0
    with pytest.raises(InvalidInputError, match="'gantry_y'.*outside"):
        robot.check_configuration(q)
    clipped = robot.clip_to_limits(q)
    assert clipped[1] == robot.limits.upper[1]
    robot.check_configuration(clipped)
    with pytest.raises(InvalidInputError, match="shape"):
        robot.fk(np.zeros(7))
    with pytest.raises(InvalidInputError, match="unknown robot frame"):
        robot.frame_position("no_such_frame", robot.q_rest)


# --- limits -------------------------------------------------------------------------


def test_limits_come_from_the_toml(robot: Robot, raw_toml: dict) -> None:
    actuated = [j for j in raw_toml["joints"] if j["type"] != "fixed"]
    assert robot.joint_names == tuple(j["name"] for j in actuated)
    for field in ("lower", "upper", "velocity", "acceleration", "jerk"):
        np.testing.assert_array_equal(getattr(robot.limits, field), [j[field] for j in actuated])
    np.testing.assert_array_equal(robot.dynamics.wn, [j["wn"] for j in actuated])
    # Data-sheet values of the KR 6 R900 sixx (degrees).
    deg = np.degrees
    np.testing.assert_allclose(deg(robot.limits.upper[2:]), [170, 45, 156, 185, 120, 350], atol=1e-6)
    np.testing.assert_allclose(deg(robot.limits.lower[2:]), [-170, -190, -120, -185, -120, -350], atol=1e-6)
    np.testing.assert_allclose(deg(robot.limits.velocity[2:]), [360, 300, 360, 381, 388, 615], atol=1e-6)
    assert np.all(robot.limits.velocity[:2] >= 3.0) and np.all(robot.limits.acceleration[:2] >= 20.0)
    # URDF limits agree with the TOML (pinocchio's parsed model).
    np.testing.assert_allclose(robot.model.lowerPositionLimit, robot.limits.lower, atol=1e-9)
    np.testing.assert_allclose(robot.model.velocityLimit, robot.limits.velocity, atol=1e-9)


def test_limits_expanded(robot: Robot) -> None:
    lim = robot.limits
    e = lim.expanded(1.5)
    np.testing.assert_allclose(e.velocity, 1.5 * lim.velocity)
    np.testing.assert_allclose(e.acceleration, 1.5 * lim.acceleration)
    np.testing.assert_allclose(e.jerk, 1.5 * lim.jerk)
    np.testing.assert_array_equal(e.lower, lim.lower)
    np.testing.assert_array_equal(e.upper, lim.upper)
    per_joint = np.linspace(1.0, 2.0, 8)
    e2 = lim.expanded(per_joint, orders=("acceleration", "jerk"))
    np.testing.assert_allclose(e2.jerk, per_joint * lim.jerk)
    np.testing.assert_array_equal(e2.velocity, lim.velocity)
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(InvalidInputError, match="scale"):
            lim.expanded(bad)
    with pytest.raises(InvalidInputError, match="'a6'"):
        lim.expanded([1, 1, 1, 1, 1, 1, 1, 0])
    with pytest.raises(InvalidInputError, match="shape"):
        lim.expanded([1.0, 2.0])
    with pytest.raises(ValueError):  # read-only arrays: the dataclass is truly frozen
        lim.velocity[0] = 1.0


# --- joint dynamics -----------------------------------------------------------------


def _rk4(f, x0: np.ndarray, t0: float, t1: float, n: int) -> np.ndarray:
    x, h, t = x0.copy(), (t1 - t0) / n, t0
    for _ in range(n):
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x, t = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), t + h
    return x


def test_discretize_matches_rk4(robot: Robot) -> None:
    dyn = robot.dynamics
    dt = 0.004
    A, B = dyn.discretize(dt)
    rng = np.random.default_rng(4)
    X0 = rng.normal(size=(8, 2))
    u = rng.normal(size=8)
    wn, z = dyn.wn, dyn.zeta

    def f(_t: float, X: np.ndarray) -> np.ndarray:
        return np.stack([X[:, 1], wn**2 * (u - X[:, 0]) - 2 * z * wn * X[:, 1]], axis=1)

    X1 = _rk4(f, X0, 0.0, dt, 400)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", A, X0) + B * u[:, None], X1, atol=1e-10)


def test_step_response_settles(robot: Robot) -> None:
    dyn = robot.dynamics
    dt, N = 0.001, 1000
    target = robot.q_flat
    X0 = np.stack([robot.q_rest, np.zeros(8)], axis=1)
    X = dyn.simulate(np.tile(target, (N, 1)), dt, X0)
    assert X.shape == (N, 8, 2)
    np.testing.assert_array_equal(X[0], X0)
    np.testing.assert_allclose(X[-1, :, 0], target, atol=1e-6)
    np.testing.assert_allclose(X[-1, :, 1], 0.0, atol=1e-4)
    # Underdamped (zeta < 1): overshoot exp(-pi zeta / sqrt(1 - zeta^2)) of the step.
    k = 3  # a2
    step = target[k] - X0[k, 0]
    zeta = dyn.zeta[k]
    overshoot = (X[:, k, 0].max() - target[k]) / step if step > 0 else (target[k] - X[:, k, 0].min()) / -step
    assert overshoot == pytest.approx(math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2)), rel=0.02)
    with pytest.raises(InvalidInputError, match="not finite"):
        dyn.simulate(np.full((3, 8), np.nan), dt, X0)
    with pytest.raises(InvalidInputError, match="dt"):
        dyn.discretize(0.0)


def test_jerk_chain_matches_exact_cubic(robot: Robot) -> None:
    dyn = robot.dynamics
    h = 0.03
    A, B = dyn.jerk_chain(h)
    rng = np.random.default_rng(5)
    Z0 = rng.normal(size=(8, 5))
    j = rng.normal(size=8) * 50
    Z1 = np.einsum("nij,nj->ni", A, Z0) + B * j[:, None]
    u0, u1, u2, q0, qd0 = Z0.T
    # Command: the exact cubic of the held jerk.
    np.testing.assert_allclose(Z1[:, 0], u0 + u1 * h + u2 * h**2 / 2 + j * h**3 / 6, atol=1e-12)
    np.testing.assert_allclose(Z1[:, 1], u1 + u2 * h + j * h**2 / 2, atol=1e-12)
    np.testing.assert_allclose(Z1[:, 2], u2 + j * h, atol=1e-12)
    wn, z = dyn.wn, dyn.zeta

    def f(t: float, X: np.ndarray) -> np.ndarray:
        u = u0 + u1 * t + u2 * t**2 / 2 + j * t**3 / 6
        return np.stack([X[:, 1], wn**2 * (u - X[:, 0]) - 2 * z * wn * X[:, 1]], axis=1)

    X1 = _rk4(f, np.stack([q0, qd0], axis=1), 0.0, h, 3000)
    np.testing.assert_allclose(Z1[:, 3:], X1, atol=1e-9)
    # The (q, q') block with a constant command is the ZOH discretization.
    Ad, Bd = dyn.discretize(h)
    np.testing.assert_allclose(A[:, 3:, 3:], Ad, atol=1e-12)
    np.testing.assert_allclose(A[:, 3:, 0], Bd, atol=1e-12)


def test_joint_dynamics_validation() -> None:
    names = tuple("abcdefgh")
    with pytest.raises(InvalidInputError, match="wn"):
        JointDynamics(names=names, wn=np.zeros(8), zeta=np.ones(8))
    with pytest.raises(InvalidInputError, match="lower"):
        JointLimits(
            names=names,
            lower=np.ones(8),
            upper=np.zeros(8),
            velocity=np.ones(8),
            acceleration=np.ones(8),
            jerk=np.ones(8),
        )


# --- placement: reachability and named poses ----------------------------------------


def _ik(robot: Robot, p: np.ndarray, n: np.ndarray, starts: list[np.ndarray]) -> np.ndarray:
    lo, hi = robot.limits.lower, robot.limits.upper
    best = None

    def res(q: np.ndarray) -> np.ndarray:
        pose = robot.fk(q)
        return np.concatenate([pose.position - p, 0.3 * (pose.normal - n)])

    for q0 in starts:
        r = least_squares(res, q0, bounds=(lo, hi), xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100)
        if best is None or r.cost < best.cost:
            best = r
        if r.cost < 1e-14:
            break
    assert best is not None
    return best.x


def test_contact_points_reachable(robot: Robot) -> None:
    """Contact points behind the end line, table level to 0.6 m, |y| <= 0.4, with racket
    normals within 10 deg of forward-ish directions (yaw 0, +-30 deg; pitch +-20 deg)."""
    rng = np.random.default_rng(6)
    directions = []
    for yaw, pitch in ((0.0, 0.0), (30.0, 0.0), (-30.0, 0.0), (0.0, 20.0), (0.0, -20.0)):
        a, b = math.radians(yaw), math.radians(pitch)
        directions.append(np.array([math.cos(b) * math.cos(a), math.cos(b) * math.sin(a), math.sin(b)]))
    points = [(x, y, z) for x in (-1.65, -1.45) for y in (-0.4, 0.0, 0.4) for z in (0.02, 0.6)]
    points += [(-1.55, 0.2, 0.3), (-1.55, -0.2, 0.3)]
    k = 0
    for p in points:
        n = directions[k % len(directions)]
        k += 1
        starts = [robot.q_flat, robot.q_rest] + [rng.uniform(robot.limits.lower, robot.limits.upper) for _ in range(4)]
        q = _ik(robot, np.array(p), n, starts)
        robot.check_configuration(q)
        pose = robot.fk(q)
        assert np.linalg.norm(pose.position - p) < 2e-3, p
        assert math.degrees(math.acos(min(1.0, float(pose.normal @ n)))) < 10.0, (p, n)
        # "Large racket speeds": forward speed available from joint speed limits alone.
        vmax = np.abs(robot.racket_jacobian(q)[:3].T @ np.array([1.0, 0.0, 0.0])) @ robot.limits.velocity
        assert vmax > 6.0, (p, vmax)


def _collision_pairs(robot: Robot) -> tuple[pin.GeometryModel, pin.GeometryData]:
    gm = pin.buildGeomFromUrdf(robot.model, str(robot.urdf_path), pin.COLLISION)
    parents = robot.model.parents
    for a in range(gm.ngeoms):
        for b in range(a + 1, gm.ngeoms):
            ja, jb = gm.geometryObjects[a].parentJoint, gm.geometryObjects[b].parentJoint
            if ja == jb or parents[ja] == jb or parents[jb] == ja:
                continue
            gm.addCollisionPair(pin.CollisionPair(a, b))
    return gm, pin.GeometryData(gm)


def test_named_poses(robot: Robot) -> None:
    # q_flat: face A up within 2 deg, ball above the table level, behind the end line.
    pose = robot.fk(robot.q_flat)
    assert math.degrees(math.acos(min(1.0, pose.normal[2]))) < 2.0
    cup = robot.cup_position(robot.q_flat)
    assert 0.0 + C.BALL_RADIUS < cup[2] < 0.2
    assert cup[0] < -1.37 - 0.2
    # q_rest: whole racket behind the end line, above the table level.
    rest = robot.fk(robot.q_rest)
    assert rest.position[0] < -1.37 - 0.15 and rest.position[2] > 0.1
    # Both poses free of self-collision (non-adjacent links, coal through pinocchio).
    gm, gd = _collision_pairs(robot)
    for q in (robot.q_rest, robot.q_flat):
        assert not pin.computeCollisions(robot.model, robot.data, gm, gd, q, True)


def test_base_behind_end_line(robot: Robot) -> None:
    for q in (robot.q_rest, robot.q_flat):
        qq = q.copy()
        qq[0] = robot.limits.upper[0]
        assert robot.frame_position("arm_base", qq)[0] + 0.175 < -1.37


# --- bad input ----------------------------------------------------------------------


def test_malformed_toml_names_the_key(tmp_path: Path) -> None:
    text = TOML_PATH.read_text(encoding="utf-8")
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("velocity = 5.235987756", 'velocity = "fast"'))
    with pytest.raises(RobotModelError, match=r"joints\[4\]\.velocity"):
        rd.load_spec(bad)
    bad.write_text(text.replace("wall_count = 8", "wall_count = 1"))
    with pytest.raises(RobotModelError, match=r"cup\.wall_count"):
        rd.load_spec(bad)
    bad.write_text(text.replace("blade_width = 0.150", "blade_width = 0.170"))
    with pytest.raises(RobotModelError, match=r"racket\.blade_width"):
        rd.load_spec(bad)
    bad.write_text(text.replace("[poses]", "[poses]\nq_typo = [0.0]"))
    with pytest.raises(RobotModelError, match=r"poses\.q_typo"):
        rd.load_spec(bad)
    bad.write_text(text + "\n[[links]]\nname = 'oops'\nmass = 1.0\n")
    with pytest.raises(RobotModelError, match="root"):
        rd.load_spec(bad)
    bad.write_bytes(text.encode().replace(b"# ", b"# \xe9", 1))
    with pytest.raises(RobotModelError, match=r"bad\.toml: the robot description is not UTF-8 text \(byte 0xe9"):
        rd.load_spec(bad)
    bad.write_text("this is = not toml =")
    with pytest.raises(RobotModelError, match="not valid TOML"):
        rd.load_spec(bad)


def test_missing_or_broken_urdf(tmp_path: Path) -> None:
    missing = tmp_path / "nope.urdf"
    with pytest.raises(RobotModelError, match="nope.urdf"):
        load_robot(missing)
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot name='x'><link name='a'/>")
    with pytest.raises(RobotModelError, match="broken.urdf"):
        load_robot(broken, spec_path=TOML_PATH)
    stale = tmp_path / "stale.urdf"
    stale.write_text((robots_dir() / rd.URDF_NAME).read_text().replace('velocity="6.283185307"', 'velocity="1"', 1))
    with pytest.raises(RobotModelError, match="differ"):
        load_robot(stale, spec_path=TOML_PATH)


def test_joint_efforts_are_rigid_body_dynamics() -> None:
    """RNEA at rest equals the gradient of the potential energy; a gantry_x acceleration
    needs (mass it carries) x a; bad shapes and non-finite inputs are refused."""
    import pinocchio as pin

    robot = load_robot()
    rng = np.random.default_rng(3)
    lo, hi = robot.limits.lower, robot.limits.upper
    for _ in range(5):
        q = lo + (hi - lo) * rng.uniform(0.2, 0.8, 8)
        tau = robot.joint_efforts(q, np.zeros(8), np.zeros(8))[0]
        grad = np.zeros(8)
        for k in range(8):
            dq = np.zeros(8)
            dq[k] = 1e-6
            grad[k] = (
                pin.computePotentialEnergy(robot.model, robot.data, q + dq)
                - pin.computePotentialEnergy(robot.model, robot.data, q - dq)
            ) / 2e-6
        np.testing.assert_allclose(tau, grad, atol=1e-4)
    carried = sum(robot.model.inertias[j].mass for j in range(1, robot.model.njoints))
    a = np.zeros(8)
    a[0] = 2.0
    assert robot.joint_efforts(robot.q_rest, np.zeros(8), a)[0, 0] == pytest.approx(2.0 * carried, rel=1e-9)  # F = m a
    assert robot.joint_efforts(np.tile(robot.q_rest, (3, 1)), np.zeros((3, 8)), np.zeros((3, 8))).shape == (3, 8)
    with pytest.raises(InvalidInputError, match="joint_efforts"):
        robot.joint_efforts(np.zeros(7), np.zeros(7), np.zeros(7))
    with pytest.raises(InvalidInputError, match="finite"):
        robot.joint_efforts(robot.q_rest, np.full(8, np.nan), np.zeros(8))
    assert robot.effort_limits.shape == (8,) and np.all(robot.effort_limits > 0)
