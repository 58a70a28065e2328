"""Forward kinematics of a pinocchio model as casadi functions (for the strike planner).

The PyPI ``pin`` wheel ships without ``pinocchio.casadi``, so this module walks the
pinocchio :class:`pinocchio.Model` itself (parents, joint placements, joint types and
axes, frame placements) and builds the same forward kinematics in casadi ``SX``
symbols. Supported joints: revolute and prismatic about any axis (``R{X,Y,Z}``,
``RevoluteUnaligned``, ``P{X,Y,Z}``, ``PrismaticUnaligned``) and the continuous
(unbounded) revolute joints ``RUB{X,Y,Z}`` (cos/sin parametrisation, ``nq = 2``).

Frames and units: every output is in the world frame of the model (for the serve
robot: ``DESIGN.md``'s world frame, origin at the centre of the playing surface, +X to
the receiver, +Z up), lengths in m, velocities in m/s. The "velocity" of a frame is the
linear velocity of its origin in the world frame, i.e. pinocchio's
``getFrameVelocity(..., LOCAL_WORLD_ALIGNED).linear`` = ``dp/dq(q) qd``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import numpy.typing as npt
import pinocchio as pin

from studio.errors import RobotModelError

FloatArray = npt.NDArray[np.float64]

_AXES: dict[str, tuple[float, float, float]] = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}

_FUNCTION_OPTIONS: dict[str, bool] = {"cse": True}
"""casadi Function options: common-subexpression elimination (fewer operations)."""


def _skew(a: FloatArray) -> FloatArray:
    """Cross-product matrix ``[a]_x`` (3, 3) of a vector ``a`` (3,)."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _rotation_cs(axis: FloatArray, c: ca.SX, s: ca.SX) -> ca.SX:
    """Rotation matrix (3, 3) about the unit ``axis`` with ``cos = c``, ``sin = s``
    (Rodrigues: ``I + s K + (1 - c) K^2``)."""
    k = _skew(axis)
    return ca.DM(np.eye(3)) + s * ca.DM(k) + (1.0 - c) * ca.DM(k @ k)


def _joint_motion(joint: pin.JointModel, q: ca.SX) -> tuple[ca.SX | None, ca.SX | None]:
    """Relative motion of one joint: (rotation (3, 3) or None, translation (3,) or None).

    Raises:
        RobotModelError: the joint type is not supported.
    """
    name = joint.shortname()
    iq = joint.idx_q
    if name.startswith("JointModelRUB") and name[-1] in _AXES:
        axis = np.array(_AXES[name[-1]])
        return _rotation_cs(axis, q[iq], q[iq + 1]), None
    if name in ("JointModelRX", "JointModelRY", "JointModelRZ"):
        axis = np.array(_AXES[name[-1]])
        return _rotation_cs(axis, ca.cos(q[iq]), ca.sin(q[iq])), None
    if name == "JointModelRevoluteUnaligned":
        axis = np.asarray(joint.extract().axis, dtype=float)
        axis = axis / np.linalg.norm(axis)
        return _rotation_cs(axis, ca.cos(q[iq]), ca.sin(q[iq])), None
    if name in ("JointModelPX", "JointModelPY", "JointModelPZ"):
        axis = np.array(_AXES[name[-1]])
        return None, ca.DM(axis) * q[iq]
    if name == "JointModelPrismaticUnaligned":
        axis = np.asarray(joint.extract().axis, dtype=float)
        axis = axis / np.linalg.norm(axis)
        return None, ca.DM(axis) * q[iq]
    raise RobotModelError(
        f"kinematics_casadi: joint type {name} is not supported (revolute/prismatic about one axis only)"
    )


def joint_placement(model: pin.Model, joint: int, q: ca.SX) -> tuple[ca.SX, ca.SX]:
    """Symbolic world placement ``(p (3,), R (3, 3))`` of joint ``joint``'s frame
    (pinocchio's ``oMi[joint]``) for the symbolic configuration q (model.nq,).

    Raises:
        RobotModelError: bad joint index or unsupported joint type.
    """
    if not 0 <= joint < model.njoints:
        raise RobotModelError(f"kinematics_casadi: joint index {joint} out of range 0..{model.njoints - 1}")
    chain: list[int] = []
    j = int(joint)
    while j > 0:
        chain.append(j)
        j = int(model.parents[j])
    chain.reverse()
    rot: ca.SX = ca.SX(ca.DM(np.eye(3)))
    pos: ca.SX = ca.SX(ca.DM(np.zeros(3)))
    for j in chain:
        placement = model.jointPlacements[j]
        # oMi = oMparent * jointPlacement * motion(q)
        pos = pos + rot @ ca.DM(placement.translation)
        rot = rot @ ca.DM(placement.rotation)
        r_j, t_j = _joint_motion(model.joints[j], q)
        if t_j is not None:
            pos = pos + rot @ t_j
        if r_j is not None:
            rot = rot @ r_j
    return pos, rot


def frame_placement(model: pin.Model, frame: str, q: ca.SX) -> tuple[ca.SX, ca.SX]:
    """Symbolic world placement of a frame: ``(p (3,), R (3, 3))`` as casadi ``SX``.

    Args:
        model: pinocchio model (joint tree, placements).
        frame: name of a frame of ``model``.
        q: symbolic configuration, ``(model.nq,)``.

    Raises:
        RobotModelError: unknown frame or unsupported joint type.
    """
    if not model.existFrame(frame):
        raise RobotModelError(f"kinematics_casadi: frame {frame!r} not found in model {model.name!r}")
    fid = model.getFrameId(frame)
    f = model.frames[fid]
    pos, rot = joint_placement(model, int(f.parentJoint), q)
    pos = pos + rot @ ca.DM(f.placement.translation)
    rot = rot @ ca.DM(f.placement.rotation)
    return pos, rot


@dataclass(frozen=True)
class CasadiKinematics:
    """casadi functions of the kinematics of one frame (numeric calls take numpy arrays).

    Inputs are ``q`` (nq,) [m | rad] and ``qd`` (nv,) [m/s | rad/s] (nq = nv for the
    supported joints except ``RUB*``, for which only position/rotation are meaningful).
    """

    nq: int
    """Configuration size of the model."""
    frame: str
    """Name of the frame (e.g. ``racket``)."""
    normal_axis: int
    """Column of the frame rotation used as "normal" (2: the frame z axis)."""
    pose: ca.Function
    """``q -> (p (3,), R (3, 3))``: world position [m] and rotation (frame to world)."""
    normal: ca.Function
    """``q -> n (3,)``: unit normal (column ``normal_axis`` of R), world frame."""
    position_jacobian: ca.Function
    """``q -> J_v (3, nq)``: ``dp/dq`` [m per unit of q], so that ``v = J_v qd``."""
    velocity: ca.Function
    """``(q, qd) -> v (3,)``: linear velocity of the frame origin [m/s], world frame."""
    strike_terms: ca.Function
    """``(q, qd) -> (p, n, v, dp/dq (3, nq), dn/dq (3, nq), dv/dq (3, nq), dv/dqd (3, nq))``:
    everything the strike planner linearises at the contact time, in one call."""

    def position_np(self, q: npt.ArrayLike) -> FloatArray:
        """Frame position [m], ``(3,)``."""
        return np.asarray(self.pose(np.asarray(q, dtype=float))[0]).reshape(3)

    def normal_np(self, q: npt.ArrayLike) -> FloatArray:
        """Frame normal, ``(3,)``."""
        return np.asarray(self.normal(np.asarray(q, dtype=float))).reshape(3)

    def velocity_np(self, q: npt.ArrayLike, qd: npt.ArrayLike) -> FloatArray:
        """Frame origin velocity [m/s], ``(3,)``."""
        return np.asarray(self.velocity(np.asarray(q, dtype=float), np.asarray(qd, dtype=float))).reshape(3)

    def strike_terms_np(
        self, q: npt.ArrayLike, qd: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """Numeric :attr:`strike_terms`: ``p, n, v`` (3,) and four (3, nq) Jacobians."""
        out = self.strike_terms(np.asarray(q, dtype=float), np.asarray(qd, dtype=float))
        p, n, v = (np.asarray(o).reshape(3) for o in out[:3])
        jp, jn, jvq, jvqd = (np.asarray(o) for o in out[3:])
        return p, n, v, jp, jn, jvq, jvqd


def build_kinematics(model: pin.Model, frame: str, *, normal_axis: int = 2) -> CasadiKinematics:
    """Build the casadi kinematics of ``frame`` of a pinocchio ``model``.

    Args:
        model: pinocchio model; only revolute/prismatic joints about one axis (and
            ``RUB*``) are supported.
        frame: frame name (the racket frame for the planner).
        normal_axis: which axis of the frame is its "normal" (0, 1 or 2).

    Raises:
        RobotModelError: unknown frame, unsupported joint, or ``normal_axis`` not in 0..2.
    """
    if normal_axis not in (0, 1, 2):
        raise RobotModelError(f"kinematics_casadi: normal_axis must be 0, 1 or 2, got {normal_axis!r}")
    nq, nv = int(model.nq), int(model.nv)
    q = ca.SX.sym("q", nq)
    qd = ca.SX.sym("qd", nv)
    p, r = frame_placement(model, frame, q)
    n = r[:, normal_axis]
    if nq == nv:
        jp = ca.jacobian(p, q)
        v = jp @ qd
    else:  # RUB joints: tangent differs from configuration; velocity not provided.
        jp = ca.jacobian(p, q)
        v = ca.SX.nan(3)
    jn = ca.jacobian(n, q)
    jvq = ca.jacobian(v, q)
    jvqd = ca.jacobian(v, qd)
    opts = _FUNCTION_OPTIONS
    return CasadiKinematics(
        nq=nq,
        frame=frame,
        normal_axis=normal_axis,
        pose=ca.Function("pose", [q], [p, r], ["q"], ["p", "R"], opts),
        normal=ca.Function("normal", [q], [n], ["q"], ["n"], opts),
        position_jacobian=ca.Function("position_jacobian", [q], [jp], ["q"], ["J_v"], opts),
        velocity=ca.Function("velocity", [q, qd], [v], ["q", "qd"], ["v"], opts),
        strike_terms=ca.Function(
            "strike_terms",
            [q, qd],
            [p, n, v, jp, jn, jvq, jvqd],
            ["q", "qd"],
            ["p", "n", "v", "dp_dq", "dn_dq", "dv_dq", "dv_dqd"],
            opts,
        ),
    )
