"""Ball in the cup: the holding cone from the cup geometry, measured in a native MuJoCo
model of the cup, and every exported example serve replayed in it.

The MuJoCo model here is the test's own (not :mod:`studio.sim.rollout`'s): the cup's plate and
wall blocks built from the robot TOML's ``[cup]`` numbers on a heavy body whose pose and
velocity are written from the exported motion before every step (kinematic), the ball a
free body, frictionless contacts (the cone's conservative case). The exported motion is
read from the NPZ with numpy; the cup pose comes from pinocchio FK of the exported ``q``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import mujoco
import numpy as np
import numpy.typing as npt
import pinocchio as pin
import pytest

from studio.errors import InvalidInputError
from studio.robot.cup_hold import CUP_SAFETY_FACTOR, CupGrip, check_cup_hold
from studio.robot.description import BALL_CUP_FRAME, load_spec
from studio.robot.model import Robot, load_robot

EXAMPLES = sorted((Path(__file__).resolve().parent.parent / "examples" / "serves").glob("*.json"))
DT = 1e-3
G = 9.81
FloatArray = npt.NDArray[np.float64]


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot()


def _cup_mjcf(gravity: tuple[float, float, float] = (0.0, 0.0, -G), timestep: float = 2.5e-4) -> str:
    """Cup (origin at the resting ball centre, axes of the racket) and a free ball."""
    r = load_spec().racket
    z0 = r.ball_centre[2]
    n, r_mid = r.cup_wall_count, r.cup_rim_radius + 0.5 * r.cup_wall_thickness
    chord = 2.0 * (r.cup_rim_radius + r.cup_wall_thickness) * math.tan(math.pi / n)
    z_wall = 0.5 * r.handle_thickness + r.cup_plate_thickness + 0.5 * r.cup_wall_height - z0
    walls = "".join(
        f'<geom type="box" size="{r.cup_wall_thickness / 2} {chord / 2} {r.cup_wall_height / 2}" '
        f'pos="{r_mid * math.cos(a)} {r_mid * math.sin(a)} {z_wall}" euler="0 0 {a}"/>'
        for a in (2 * math.pi * k / n for k in range(n))
    )
    z_plate = 0.5 * r.handle_thickness + 0.5 * r.cup_plate_thickness - z0
    plate = f'<geom type="cylinder" size="{r.cup_plate_radius} {r.cup_plate_thickness / 2}" pos="0 0 {z_plate}"/>'
    m = 0.0027
    inertia = 2.0 / 3.0 * m * r.ball_radius**2  # thin shell
    return f"""<mujoco><compiler angle="radian"/>
<option timestep="{timestep}" gravity="{gravity[0]} {gravity[1]} {gravity[2]}" integrator="implicitfast"/>
<default><geom condim="1" solref="0.004 1"/></default>
<worldbody>
<body name="cup" gravcomp="1"><freejoint/><inertial pos="0 0 0" mass="10" diaginertia="0.1 0.1 0.1"/>{walls}{plate}</body>
<body name="ball"><freejoint/><inertial pos="0 0 0" mass="{m}" diaginertia="{inertia} {inertia} {inertia}"/>
<geom type="sphere" size="{r.ball_radius}"/></body>
</worldbody></mujoco>"""


def _ball_offset_after_static_tilt(tilt: float, azimuth: float, seconds: float = 1.0) -> float:
    """Distance [m] the ball moved from its seat in a fixed cup after ``seconds`` under
    gravity tilted by ``tilt`` towards ``azimuth`` (from wall block 0) [rad]."""
    g = (-G * math.sin(tilt) * math.cos(azimuth), -G * math.sin(tilt) * math.sin(azimuth), -G * math.cos(tilt))
    model = mujoco.MjModel.from_xml_string(_cup_mjcf(gravity=g))
    data = mujoco.MjData(model)
    for _ in range(int(round(seconds / model.opt.timestep))):
        data.qpos[:7] = (0, 0, 0, 1, 0, 0, 0)
        data.qvel[:6] = 0.0
        mujoco.mj_step(model, data)
    return float(np.linalg.norm(data.qpos[7:10]))


def _cup_poses(robot: Robot, q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """World position (N, 3) and rotation (N, 3, 3) of the ball-cup frame (pinocchio FK)."""
    fid = robot.model.getFrameId(BALL_CUP_FRAME)
    P, R = np.empty((len(q), 3)), np.empty((len(q), 3, 3))
    for k, qk in enumerate(q):
        pin.framesForwardKinematics(robot.model, robot.data, qk)
        P[k], R[k] = robot.data.oMf[fid].translation, robot.data.oMf[fid].rotation
    return P, R


def _replay(robot: Robot, q: FloatArray, n: int, sub: int = 4) -> FloatArray:
    """Ball offset from its seat in the cup frame (n,) [m] at samples 1..n of a motion q at
    1 kHz: the cup follows the FK pose (cubic Hermite position, constant angular velocity
    per interval), written into MuJoCo before each of ``sub`` steps per interval."""
    P, R = _cup_poses(robot, q[: n + 1])
    V = np.gradient(P, DT, axis=0)
    W = np.array([pin.log3(R[k].T @ R[k + 1]) / DT for k in range(n)])  # body frame
    model = mujoco.MjModel.from_xml_string(_cup_mjcf(timestep=DT / sub))
    data = mujoco.MjData(model)
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, R[0].ravel())
    data.qpos[:7] = (*P[0], *quat)
    data.qpos[7:14] = (*P[0], 1, 0, 0, 0)
    offset = np.empty(n)
    for k in range(n):
        for j in range(sub):
            s = j / sub
            h = np.array([2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2])
            dh = np.array([6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s])
            basis = np.stack([P[k], DT * V[k], P[k + 1], DT * V[k + 1]])
            mujoco.mju_mat2Quat(quat, (R[k] @ pin.exp3(W[k] * s * DT)).ravel())
            data.qpos[:7] = (*(h @ basis), *quat)
            data.qvel[:6] = (*(dh @ basis / DT), *W[k])
            mujoco.mj_step(model, data)
        offset[k] = np.linalg.norm(R[k + 1].T @ (data.qpos[7:10] - P[k + 1]))
    return offset


def _ratio_from_positions(robot: Robot, q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """|f_t| / f_n and f_n [m/s^2] at samples 1..N-2 from second differences of the FK cup
    positions: f = R^T (a + g e_z + k |v| v), k the ball's drag constant."""
    from studio.physics.ball import DEFAULT_FLIGHT

    P, R = _cup_poses(robot, q)
    v = (P[2:] - P[:-2]) / (2 * DT)
    a = (P[2:] - 2 * P[1:-1] + P[:-2]) / DT**2
    f_world = a + np.array([0.0, 0.0, G]) + DEFAULT_FLIGHT.drag_constant * np.linalg.norm(v, axis=1)[:, None] * v
    f = np.einsum("kji,kj->ki", R[1:-1], f_world)
    return np.hypot(f[:, 0], f[:, 1]) / f[:, 2], f[:, 2]


def _limits_only_preparation(robot: Robot, u_toss0: FloatArray) -> FloatArray:
    """The former preparation's predicted q: the quintic as short as the joint limits allow
    (0.331 s), then 0.3 s of hold."""
    D = np.abs(u_toss0 - robot.q_flat)
    L = robot.limits
    T = math.ceil(max(np.max(1.875 * D / L.velocity), np.max(np.sqrt(5.774 * D / L.acceleration)), np.max(np.cbrt(60 * D / L.jerk))) / DT) * DT
    s = (np.arange(round(T / DT)) + 0.5) * DT / T
    u = robot.q_flat + (10 * s**3 - 15 * s**4 + 6 * s**5)[:, None] * (u_toss0 - robot.q_flat)
    u = np.vstack([u, np.repeat(u_toss0[None], 300, axis=0)])
    return robot.dynamics.simulate(u, DT, np.stack([robot.q_flat, np.zeros(8)], axis=1))[:, :, 0]


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, dict, dict]]:
    """Every example serve exported to a library: (name, index entry, NPZ arrays)."""
    from studio.library.store import INDEX_NAME, ServeLibrary
    from studio.serve.efforts import effort_report
    from studio.serve.evaluate import EvaluationContext, evaluate_serve
    from studio.serve.params import load_serve

    folder = tmp_path_factory.mktemp("lib")
    context = EvaluationContext.default()
    for path in EXAMPLES:
        serve = load_serve(path)
        ev = evaluate_serve(serve, context, task=serve.task or "topspin_velocity")
        efforts = effort_report(ev.motion, context.robot)  # the x1.5 / x2 examples exceed gantry_x (test_efforts)
        ServeLibrary(folder).add(ev, effort_limits=efforts.peak_limits() if efforts is not None else {})
    out = []
    for entry in json.loads((folder / INDEX_NAME).read_text())["serves"]:
        with np.load(folder / entry["arrays"], allow_pickle=False) as npz:
            out.append((entry["name"], entry, {k: npz[k] for k in npz.files}))
    return out


def test_cone_follows_the_cup_geometry() -> None:
    racket = load_spec().racket
    grip = CupGrip.from_racket(racket)
    alpha = math.asin(racket.cup_rim_radius / racket.ball_radius)
    assert math.degrees(alpha) == pytest.approx(44.427, abs=1e-3)
    assert grip.geometric == pytest.approx(math.tan(alpha) * math.cos(math.pi / racket.cup_wall_count))
    assert grip.geometric == pytest.approx(0.9056, abs=1e-4)
    assert grip.limit == pytest.approx(grip.geometric / CUP_SAFETY_FACTOR) and CUP_SAFETY_FACTOR == 1.5
    with pytest.raises(InvalidInputError, match="CupGrip.safety_factor"):
        CupGrip(0.9, safety_factor=0.0)


@pytest.mark.parametrize(("azimuth_deg", "widest"), [(22.5, False), (0.0, True)], ids=["between-blocks", "towards-a-block"])
def test_mujoco_ball_leaves_the_cup_where_the_cone_says(azimuth_deg: float, widest: bool) -> None:
    """Static cup, gravity tilted: the ball stays below the cone's angle and rolls out
    above it (between two blocks: tan a cos(pi/8); towards a block: tan a)."""
    racket = load_spec().racket
    alpha = math.asin(racket.cup_rim_radius / racket.ball_radius)
    bound = math.tan(alpha) * (1.0 if widest else math.cos(math.pi / racket.cup_wall_count))
    below, above = (0.95, 1.03) if widest else (0.97, 1.03)  # soft contacts: the widest edge gives way ~2 % early
    assert _ball_offset_after_static_tilt(below * math.atan(bound), math.radians(azimuth_deg)) < 1e-3
    assert _ball_offset_after_static_tilt(above * math.atan(bound), math.radians(azimuth_deg)) > 0.1


def test_a_static_tilt_gives_its_tangent(robot: Robot) -> None:
    q = robot.q_flat + np.array([0, 0, 0, 0, 0, 0, 0.3, 0])  # a5 tilts the racket
    tilt = math.acos(robot.fk(q).normal[2])
    Q = np.tile(q, (5, 1))
    check = check_cup_hold(robot, np.arange(5) * DT, Q, Q, np.zeros_like(Q))
    assert check.worst_ratio == pytest.approx(math.tan(tilt), rel=1e-9) and check.min_normal == pytest.approx(G * math.cos(tilt), rel=1e-6)
    assert check.passed is (math.tan(tilt) <= check.limit)


def test_preparation_from_a_pose_tilted_beyond_the_cone_is_refused(robot: Robot) -> None:
    from studio.planning.preparation import preparation_phase

    tilted = robot.q_flat + np.array([0, 0, 0, 0, 0, 0, 0.8, 0])  # 46 deg: the ball cannot sit there
    with pytest.raises(InvalidInputError, match="does not stay in the cup"):
        preparation_phase(robot, robot.q_flat, q_start=tilted)


def test_every_export_records_a_passed_cup_check(exported: list[tuple[str, dict, dict]]) -> None:
    assert len(exported) == len(EXAMPLES) >= 6
    for name, entry, arrays in exported:
        cup = entry["cup_hold"]
        assert cup["passed"] and cup["worst_ratio"] <= cup["limit"] < 0.61, name
        assert cup["t_start"] == 0.0 and float(arrays["t_toss"]) + 0.3 < cup["t_end"] < float(arrays["t_toss"]) + 0.4, name  # up to the release


def test_cone_ratio_recomputed_from_the_npz_stays_inside(robot: Robot, exported: list[tuple[str, dict, dict]]) -> None:
    """numpy on the NPZ (FK of the exported q, second differences): preparation and toss up
    to the release stay inside c = c_geom / 1.5 (1e-3 for the differences' error)."""
    racket = load_spec().racket
    limit = math.tan(math.asin(racket.cup_rim_radius / racket.ball_radius)) * math.cos(math.pi / racket.cup_wall_count) / 1.5
    for name, entry, arrays in exported:
        t = arrays["t"]
        n = int(np.searchsorted(t, entry["cup_hold"]["t_end"]))  # samples before the release
        ratio, fn = _ratio_from_positions(robot, arrays["q"][: n + 1])
        assert np.all(fn > 0) and ratio.max() <= limit + 1e-3, (name, ratio.max(), t[1 + int(np.argmax(ratio))])
        P = int(round(float(arrays["t_toss"]) / DT))
        assert ratio[: P - 1].max() > 0.5 * limit  # the preparation uses the cone, no needless slowness


def test_mujoco_ball_stays_in_the_cup_through_preparation_and_toss(robot: Robot, exported: list[tuple[str, dict, dict]]) -> None:
    for name, entry, arrays in exported:
        P = int(round(float(arrays["t_toss"]) / DT))
        n = int(np.searchsorted(arrays["t"], entry["cup_hold"]["t_end"])) - 1  # the last sample in the cup
        offset = _replay(robot, arrays["q"], n)
        assert offset[:P].max() < 2e-4, (name, offset[:P].max())  # preparation: within 0.2 mm of its seat
        assert offset.max() < 1e-3, (name, offset.max())  # and the toss up to its release


def test_mujoco_throws_the_ball_out_with_the_former_preparation(robot: Robot) -> None:
    """Negative control: the quintic the joint limits alone allowed (0.331 s) breaks the cone
    (ratio ~2) and the same MuJoCo model loses the ball (the issue: it leaves at ~0.18 s)."""
    from studio.toss.defaults import load_default_toss_model

    q = _limits_only_preparation(robot, load_default_toss_model("right", robot).primitive.u[0])
    ratio, _ = _ratio_from_positions(robot, q)
    assert ratio.max() > 1.8
    offset = _replay(robot, q, 250)
    assert offset[100] < 5e-3 and offset[-1] > 0.05  # still seated at 0.1 s, gone by 0.25 s
