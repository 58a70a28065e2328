"""casadi forward kinematics (studio.planning.kinematics_casadi) against pinocchio."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from studio.errors import RobotModelError
from studio.planning.kinematics_casadi import build_kinematics
from studio.robot.model import load_robot


@pytest.fixture(scope="module")
def robot():  # type: ignore[no-untyped-def]
    return load_robot()


@pytest.fixture(scope="module")
def kin(robot):  # type: ignore[no-untyped-def]
    return build_kinematics(robot.model, "racket")


def _pin_frame(model: pin.Model, frame: str, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    data = model.createData()
    fid = model.getFrameId(frame)
    pin.forwardKinematics(model, data, q, qd)
    pin.updateFramePlacements(model, data)
    v = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED).linear
    return data.oMf[fid].translation.copy(), data.oMf[fid].rotation.copy(), np.array(v)


def test_racket_pose_velocity_match_pinocchio(robot, kin) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(3)
    m = robot.model
    for _ in range(50):
        q = rng.uniform(m.lowerPositionLimit, m.upperPositionLimit)
        qd = rng.normal(size=8) * 3.0
        p_ref, R_ref, v_ref = _pin_frame(m, "racket", q, qd)
        p, R = kin.pose(q)
        np.testing.assert_allclose(np.asarray(p).ravel(), p_ref, atol=1e-9)
        np.testing.assert_allclose(np.asarray(R), R_ref, atol=1e-9)
        np.testing.assert_allclose(kin.normal_np(q), R_ref[:, 2], atol=1e-9)
        np.testing.assert_allclose(kin.velocity_np(q, qd), v_ref, atol=1e-9)


def test_jacobians_match_pinocchio_and_finite_differences(robot, kin) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(4)
    m = robot.model
    for _ in range(10):
        q = rng.uniform(m.lowerPositionLimit, m.upperPositionLimit)
        qd = rng.normal(size=8)
        p, n, v, jp, jn, jvq, jvqd = kin.strike_terms_np(q, qd)
        np.testing.assert_allclose(jp, robot.racket_jacobian(q)[:3], atol=1e-9)
        np.testing.assert_allclose(jvqd, jp, atol=1e-12)
        h = 1e-6
        for i in range(8):
            e = np.zeros(8)
            e[i] = h
            dn = (kin.normal_np(q + e) - kin.normal_np(q - e)) / (2 * h)
            dv = (kin.velocity_np(q + e, qd) - kin.velocity_np(q - e, qd)) / (2 * h)
            np.testing.assert_allclose(jn[:, i], dn, atol=1e-7)
            np.testing.assert_allclose(jvq[:, i], dv, atol=1e-7)


def test_unaligned_axes_and_continuous_joints() -> None:
    """A hand-built chain with unaligned prismatic/revolute axes and a RUBZ joint."""
    model = pin.Model()
    rng = np.random.default_rng(5)
    joints = [
        pin.JointModelPrismaticUnaligned(0.6, 0.0, 0.8),
        pin.JointModelRevoluteUnaligned(0.0, -0.6, 0.8),
        pin.JointModelRY(),
        pin.JointModelPZ(),
        pin.JointModelRUBZ(),
    ]
    parent = 0
    for k, jm in enumerate(joints):
        parent = model.addJoint(parent, jm, pin.SE3.Random(), f"j{k}")
    model.addFrame(pin.Frame("tip", parent, 0, pin.SE3.Random(), pin.FrameType.OP_FRAME))
    kin = build_kinematics(model, "tip")
    data = model.createData()
    fid = model.getFrameId("tip")
    for _ in range(20):
        q = rng.uniform(-1, 1, model.nq)
        ang = rng.uniform(-np.pi, np.pi)
        q[-2:] = [np.cos(ang), np.sin(ang)]
        pin.framesForwardKinematics(model, data, q)
        p, R = kin.pose(q)
        np.testing.assert_allclose(np.asarray(p).ravel(), data.oMf[fid].translation, atol=1e-9)
        np.testing.assert_allclose(np.asarray(R), data.oMf[fid].rotation, atol=1e-9)


def test_unsupported_joint_and_unknown_frame_raise() -> None:
    model = pin.Model()
    j = model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    model.addFrame(pin.Frame("tip", j, 0, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
    with pytest.raises(RobotModelError, match="JointModelSpherical"):
        build_kinematics(model, "tip")
    with pytest.raises(RobotModelError, match="nope"):
        build_kinematics(model, "nope")
