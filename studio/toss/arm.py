"""Arm kinematics of the toss: the cup point's Jacobian, a pose IK, the start pose and the
joint directions that lift the cup without turning the racket.

Joint order and units of :mod:`studio.robot.model`; world frame, SI units.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.toss.design import TossPose
from studio.toss.primitive import TossSide

if TYPE_CHECKING:
    from studio.robot.model import Robot

FloatArray = npt.NDArray[np.float64]


def rotation_error(R_target: FloatArray, R: FloatArray) -> FloatArray:
    """Small-angle rotation error vector (3,) [rad] taking R to R_target (world frame)."""
    return 0.5 * (
        np.cross(R[:, 0], R_target[:, 0]) + np.cross(R[:, 1], R_target[:, 1]) + np.cross(R[:, 2], R_target[:, 2])
    )


def cup_jacobian(robot: Robot, q: FloatArray) -> FloatArray:
    """(6, 8) world-aligned Jacobian of the cup point: rows [v_cup (3); omega (3)]."""
    J = robot.racket_jacobian(q)
    r = robot.cup_position(q) - np.asarray(robot.fk(q).position)
    return np.vstack([J[:3] - np.cross(r, J[3:].T).T, J[3:]])


def pose_ik(
    robot: Robot,
    q0: FloatArray,
    cup_target: FloatArray,
    R_target: FloatArray,
    *,
    joints: npt.NDArray[np.intp],
    tol: float = 1e-12,
    max_iter: int = 50,
) -> FloatArray:
    """Newton IK: move ``joints`` of ``q0`` so the cup centre is at ``cup_target`` (3,)
    [m] and the racket rotation is ``R_target`` (3, 3). Jacobian from pinocchio (racket
    frame, shifted to the cup point). Raises InvalidInputError if it does not converge."""
    q = np.array(q0, dtype=float)
    for _ in range(max_iter):
        pose = robot.fk(q)
        cup = robot.cup_position(q)
        err = np.concatenate([cup_target - cup, rotation_error(R_target, pose.rotation)])
        if float(np.max(np.abs(err))) < tol:
            return q
        dq, *_ = np.linalg.lstsq(cup_jacobian(robot, q)[:, joints], err, rcond=None)
        q[joints] += dq
    raise InvalidInputError(
        f"toss IK did not converge for cup target {np.round(cup_target, 4)} (residual {float(np.max(np.abs(err))):.2e}); "
        "the toss leaves the robot's workspace: lower the rise or the lateral offset"
    )


def toss_start(robot: Robot, side: TossSide, pose: TossPose) -> FloatArray:
    """Start configuration of a toss, derived from ``robot.q_flat``.

    The gantry's Y axis moves the cup to ``y = -pose.lateral`` (right) or
    ``+pose.lateral`` (left); if ``pose.gantry_x`` is given the gantry's X axis moves
    there and the arm (IK, racket orientation of ``q_flat`` kept) puts the cup back at
    its ``q_flat`` x; with ``pose.start_height`` the arm also moves the cup centre to that
    height.
    """
    lateral, start_height, gantry_x = pose.lateral, pose.start_height, pose.gantry_x
    q = np.array(robot.q_flat, dtype=float)
    cup = robot.cup_position(q)
    R = np.array(robot.fk(q).rotation)
    y_target = -lateral if side == "right" else lateral
    q[robot.joint_names.index("gantry_y")] += y_target - cup[1]
    if gantry_x is not None or start_height is not None:
        if gantry_x is not None:
            q[robot.joint_names.index("gantry_x")] = gantry_x
        target = np.array([cup[0], y_target, cup[2] if start_height is None else start_height])
        q = pose_ik(robot, q, target, R, joints=np.arange(2, 8))
    return robot.check_configuration(q)


def flat_plane_basis(robot: Robot, q: FloatArray) -> FloatArray:
    """(8, 2) orthonormal joint directions (arm joints only) that move the cup in the
    vertical x-z plane without turning the racket: null space of [omega; v_y]."""
    Jc = cup_jacobian(robot, q)
    A = np.vstack([Jc[3:6, 2:], Jc[1:2, 2:]])
    _, sv, Vt = np.linalg.svd(A)
    if sv[-1] < 1e-6 * sv[0]:
        raise InvalidInputError("make_toss: the start pose is singular for a flat vertical lift")
    basis = np.zeros((8, 2))
    basis[2:, :] = Vt[4:6].T
    return basis
