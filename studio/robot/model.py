"""The 8-DoF serve robot: kinematics (pinocchio), joint limits and joint dynamics.

:func:`load_robot` builds a :class:`Robot` from ``robots/serve_robot.urdf`` (kinematics)
and ``robots/serve_robot.toml`` (limits, dynamics, named poses; the single source of
truth, see :mod:`studio.robot.description`). Joint order: ``gantry_x`` [m],
``gantry_y`` [m], ``a1`` ... ``a6`` [rad] (KUKA KR 6 R900 sixx axes, KUKA signs).

Frames: all positions and velocities are in the world frame of ``DESIGN.md`` (origin
at the table centre, +X towards the receiver, +Z up). The racket frame ``racket`` has
its origin at the blade centre on the mid-plane, z = face-A normal, y along the handle
towards the blade tip; ``ball_cup`` is the centre of the ball resting in the cup.

Joint dynamics (:class:`JointDynamics`): each joint follows its position command u
through the linear second-order model

    q'' = wn^2 (u - q) - 2 zeta wn q'

with per-joint state X = [q, q'] (the paper's 8 x 2 augmented state). The ``wn`` and
``zeta`` shipped in the TOML are stand-in values, to be identified on the real robot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np
import numpy.typing as npt
import pinocchio as pin
import scipy.linalg

from studio.errors import InvalidInputError, RobotModelError
from studio.paths import robots_dir
from studio.robot.description import (
    BALL_CUP_FRAME,
    RACKET_FRAME,
    TOML_NAME,
    URDF_NAME,
    RobotSpec,
    load_spec,
)

FloatArray = npt.NDArray[np.float64]

NQ: Final[int] = 8
"""Number of actuated joints (2 gantry + 6 arm)."""

_LIMIT_TOL: Final[float] = 1e-9
"""Tolerance of the position-limit check [m | rad] (absorbs rounding of clipped values)."""


def _frozen(a: npt.ArrayLike, shape: tuple[int, ...], what: str) -> FloatArray:
    arr = np.array(a, dtype=float)
    if arr.shape != shape:
        raise InvalidInputError(f"{what}: expected shape {shape}, got {arr.shape}")
    arr.setflags(write=False)
    return arr


# --------------------------------------------------------------------------------------
# Limits
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Kinodynamic limits of the 8 joints (read-only arrays, joint order of the robot)."""

    names: tuple[str, ...]
    """Joint names (8)."""
    lower: FloatArray
    """Lower position limits (8,) [m | rad]."""
    upper: FloatArray
    """Upper position limits (8,) [m | rad]."""
    velocity: FloatArray
    """Speed limits (8,) [m/s | rad/s], symmetric."""
    acceleration: FloatArray
    """Acceleration limits (8,) [m/s^2 | rad/s^2], symmetric."""
    jerk: FloatArray
    """Jerk limits (8,) [m/s^3 | rad/s^3], symmetric."""

    def __post_init__(self) -> None:
        n = len(self.names)
        for fname in ("lower", "upper", "velocity", "acceleration", "jerk"):
            arr = _frozen(getattr(self, fname), (n,), f"JointLimits.{fname}")
            if not np.all(np.isfinite(arr)):
                raise InvalidInputError(f"JointLimits.{fname}: values must be finite, got {arr}")
            object.__setattr__(self, fname, arr)
        for k, name in enumerate(self.names):
            if not self.lower[k] < self.upper[k]:
                raise InvalidInputError(f"JointLimits: joint {name!r} lower {self.lower[k]} >= upper {self.upper[k]}")
            for fname in ("velocity", "acceleration", "jerk"):
                if not getattr(self, fname)[k] > 0:
                    raise InvalidInputError(f"JointLimits.{fname}: joint {name!r} must be > 0")

    def expanded(
        self,
        scale: float | npt.ArrayLike,
        *,
        orders: tuple[str, ...] = ("velocity", "acceleration", "jerk"),
    ) -> JointLimits:
        """The paper's "dynamic limit expansion": derivative limits times ``scale``.

        Args:
            scale: factor > 0, a scalar or one per joint (8,). Position limits never change.
            orders: which derivative limits to scale (subset of velocity, acceleration, jerk).

        Raises:
            InvalidInputError: scale not finite, <= 0, or of the wrong shape; unknown order.
        """
        s = np.asarray(scale, dtype=float)
        if s.ndim == 0:
            s = np.full(len(self.names), float(s))
        if s.shape != (len(self.names),):
            raise InvalidInputError(f"expanded: scale must be a scalar or shape ({len(self.names)},), got {s.shape}")
        bad = ~(np.isfinite(s) & (s > 0))
        if np.any(bad):
            k = int(np.argmax(bad))
            raise InvalidInputError(f"expanded: scale for joint {self.names[k]!r} must be finite and > 0, got {s[k]}")
        allowed = ("velocity", "acceleration", "jerk")
        for o in orders:
            if o not in allowed:
                raise InvalidInputError(f"expanded: unknown order {o!r} (allowed: {', '.join(allowed)})")
        kw = {o: getattr(self, o) * (s if o in orders else 1.0) for o in allowed}
        return JointLimits(names=self.names, lower=self.lower, upper=self.upper, **kw)


# --------------------------------------------------------------------------------------
# Dynamics
# --------------------------------------------------------------------------------------


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not (math.isfinite(dt) and dt > 0):
        raise InvalidInputError(f"time step dt must be finite and > 0, got {dt}")
    return dt


@dataclass(frozen=True, slots=True)
class JointDynamics:
    """Per-joint command -> position model q'' = wn^2 (u - q) - 2 zeta wn q'.

    State per joint X = [q, q'] ([m, m/s] or [rad, rad/s]); the robot's augmented state
    is the (8, 2) matrix of the paper. ``wn`` and ``zeta`` are stand-in values until
    identified on the real robot.
    """

    names: tuple[str, ...]
    """Joint names (8)."""
    wn: FloatArray
    """Natural frequencies (8,) [rad/s]."""
    zeta: FloatArray
    """Damping ratios (8,) [-]."""

    def __post_init__(self) -> None:
        n = len(self.names)
        for fname in ("wn", "zeta"):
            arr = _frozen(getattr(self, fname), (n,), f"JointDynamics.{fname}")
            if not np.all(np.isfinite(arr) & (arr > 0)):
                raise InvalidInputError(f"JointDynamics.{fname}: values must be finite and > 0, got {arr}")
            object.__setattr__(self, fname, arr)

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.names)

    def continuous(self) -> tuple[FloatArray, FloatArray]:
        """Continuous-time matrices: X' = A X + B u per joint; A (n, 2, 2), B (n, 2)."""
        A = np.zeros((self.n, 2, 2))
        A[:, 0, 1] = 1.0
        A[:, 1, 0] = -(self.wn**2)
        A[:, 1, 1] = -2.0 * self.zeta * self.wn
        B = np.zeros((self.n, 2))
        B[:, 1] = self.wn**2
        return A, B

    def discretize(self, dt: float) -> tuple[FloatArray, FloatArray]:
        """Exact zero-order-hold discretization over ``dt`` [s].

        Returns:
            A (n, 2, 2), B (n, 2) with X[k+1] = A X[k] + B u[k] per joint.
        """
        dt = _check_dt(dt)
        Ac, Bc = self.continuous()
        return _expm_blocks(Ac, Bc, dt)

    def jerk_chain_continuous(self) -> tuple[FloatArray, FloatArray]:
        """Continuous matrices of the chain Z = [u, u', u'', q, q'] driven by jerk j = u'''.

        Returns:
            A (n, 5, 5), B (n, 5) with Z' = A Z + B j per joint.
        """
        A = np.zeros((self.n, 5, 5))
        A[:, 0, 1] = 1.0
        A[:, 1, 2] = 1.0
        A[:, 3, 4] = 1.0
        A[:, 4, 0] = self.wn**2
        A[:, 4, 3] = -(self.wn**2)
        A[:, 4, 4] = -2.0 * self.zeta * self.wn
        B = np.zeros((self.n, 5))
        B[:, 2] = 1.0
        return A, B

    def jerk_chain(self, dt: float) -> tuple[FloatArray, FloatArray]:
        """Exact discrete chain for jerk held constant over ``dt`` [s].

        State per joint Z = [u, u', u'', q, q'] (command, its two derivatives, actual
        position and velocity); Z[k+1] = A Z[k] + B j[k]. Computed with ``expm`` of the
        augmented continuous matrix, so u is exactly the cubic of the held jerk and
        (q, q') the exact response of the joint model to it.

        Returns:
            A (n, 5, 5), B (n, 5).
        """
        dt = _check_dt(dt)
        Ac, Bc = self.jerk_chain_continuous()
        return _expm_blocks(Ac, Bc, dt)

    def simulate(self, u: npt.ArrayLike, dt: float, X0: npt.ArrayLike) -> FloatArray:
        """Response to commands held constant over each step (zero-order hold).

        Args:
            u: commands (N, n) [m | rad]; u[k] is held on [k dt, (k+1) dt).
            dt: sample period [s].
            X0: state at t = 0, (n, 2) = [q, q'] per joint.

        Returns:
            X (N, n, 2): X[k] is the state at t = k dt (X[0] = X0), so that X[k] is the
            predicted joint state at the time the command u[k] is sent.
        """
        dt = _check_dt(dt)
        U = np.asarray(u, dtype=float)
        X0a = np.asarray(X0, dtype=float)
        if U.ndim != 2 or U.shape[1] != self.n:
            raise InvalidInputError(f"simulate: u must have shape (N, {self.n}), got {U.shape}")
        if X0a.shape != (self.n, 2):
            raise InvalidInputError(f"simulate: X0 must have shape ({self.n}, 2), got {X0a.shape}")
        for arr, what in ((U, "u"), (X0a, "X0")):
            if not np.all(np.isfinite(arr)):
                bad = np.argwhere(~np.isfinite(arr))[0]
                raise InvalidInputError(f"simulate: {what} is not finite at index {tuple(int(b) for b in bad)}")
        A, B = self.discretize(dt)
        N = U.shape[0]
        X = np.empty((N, self.n, 2))
        if N == 0:
            return X
        a00, a01, a10, a11 = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
        b0, b1 = B[:, 0], B[:, 1]
        q, qd = X0a[:, 0].copy(), X0a[:, 1].copy()
        for k in range(N):
            X[k, :, 0] = q
            X[k, :, 1] = qd
            q, qd = a00 * q + a01 * qd + b0 * U[k], a10 * q + a11 * qd + b1 * U[k]
        return X


_EXPM_CACHE: dict[tuple[bytes, bytes, float], tuple[FloatArray, FloatArray]] = {}


def _expm_blocks(Ac: FloatArray, Bc: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Exact ZOH discretization of n independent blocks x' = Ac[i] x + Bc[i] u over dt.

    Cached by (Ac, Bc, dt): the planner, tosses and rollouts discretize the same model
    with the same steps thousands of times, and ``expm`` is slow under BLAS threading.
    Returns read-only arrays A (n, m, m), B (n, m).
    """
    key = (Ac.tobytes() + str(Ac.shape).encode(), Bc.tobytes(), float(dt))
    hit = _EXPM_CACHE.get(key)
    if hit is not None:
        return hit
    n, m = Bc.shape
    A = np.empty_like(Ac)
    B = np.empty_like(Bc)
    M = np.zeros((m + 1, m + 1))
    for i in range(n):
        M[:m, :m] = Ac[i]
        M[:m, m] = Bc[i]
        E = scipy.linalg.expm(M * dt)
        A[i] = E[:m, :m]
        B[i] = E[:m, m]
    A.flags.writeable = False
    B.flags.writeable = False
    if len(_EXPM_CACHE) > 256:
        _EXPM_CACHE.clear()
    _EXPM_CACHE[key] = (A, B)
    return A, B


# --------------------------------------------------------------------------------------
# Robot
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RacketPose:
    """Pose of the racket frame in the world frame."""

    position: FloatArray
    """Racket origin (blade centre, mid-plane) (3,) [m], world frame."""
    rotation: FloatArray
    """Rotation (3, 3) whose columns are the racket x, y, z axes in the world frame."""

    @property
    def normal(self) -> FloatArray:
        """Face-A normal (3,) = rotation[:, 2], unit, world frame."""
        return self.rotation[:, 2]


@dataclass(eq=False)
class Robot:
    """Kinematic model of the serve robot with its limits, dynamics and named poses.

    Holds one pinocchio ``Data``: a ``Robot`` is not thread-safe (use one per thread).
    """

    model: pin.Model = field(repr=False)
    """Pinocchio model (fixed base = world)."""
    data: pin.Data = field(repr=False)
    """Pinocchio work data of ``model``."""
    spec: RobotSpec = field(repr=False)
    """The validated TOML description."""
    limits: JointLimits
    """Joint limits from the TOML."""
    dynamics: JointDynamics
    """Joint command->position dynamics from the TOML."""
    urdf_path: Path
    """The URDF the model was built from."""
    _frame_ids: dict[str, int] = field(default_factory=dict, repr=False)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Actuated joint names, in configuration order (8)."""
        return self.limits.names

    @property
    def nq(self) -> int:
        """Configuration dimension (8)."""
        return int(self.model.nq)

    @property
    def q_rest(self) -> FloatArray:
        """Rest configuration (8,) [m, m, rad x 6]: racket parked behind the end line."""
        return np.array(self.spec.q_rest)

    @property
    def q_flat(self) -> FloatArray:
        """Toss-start configuration (8,): racket face A up, ball resting in the cup."""
        return np.array(self.spec.q_flat)

    # -- helpers --------------------------------------------------------------------

    def frame_id(self, name: str) -> int:
        """Pinocchio frame index of a link/frame ``name``; InvalidInputError if unknown."""
        fid = self._frame_ids.get(name)
        if fid is None:
            if not self.model.existFrame(name):
                raise InvalidInputError(f"unknown robot frame {name!r}")
            fid = int(self.model.getFrameId(name))
            self._frame_ids[name] = fid
        return fid

    def _as_q(self, q: npt.ArrayLike, what: str = "q") -> FloatArray:
        arr = np.asarray(q, dtype=float)
        if arr.shape != (NQ,):
            raise InvalidInputError(f"{what}: expected shape ({NQ},), got {arr.shape}")
        bad = ~np.isfinite(arr)
        if np.any(bad):
            k = int(np.argmax(bad))
            raise InvalidInputError(f"{what}: joint {self.joint_names[k]!r} is not finite ({arr[k]})")
        return arr

    def check_configuration(self, q: npt.ArrayLike) -> FloatArray:
        """Validate a configuration (8,): finite and within the position limits.

        Returns:
            q as a float array.

        Raises:
            InvalidInputError: naming the first offending joint.
        """
        arr = self._as_q(q)
        lo, hi = self.limits.lower, self.limits.upper
        for k, name in enumerate(self.joint_names):
            if arr[k] < lo[k] - _LIMIT_TOL or arr[k] > hi[k] + _LIMIT_TOL:
                raise InvalidInputError(f"q: joint {name!r} = {arr[k]:.6g} outside [{lo[k]:.6g}, {hi[k]:.6g}]")
        return arr

    def clip_to_limits(self, q: npt.ArrayLike) -> FloatArray:
        """q clipped into the position limits; q: (8,) or (N, 8)."""
        arr = np.asarray(q, dtype=float)
        if arr.shape[-1:] != (NQ,):
            raise InvalidInputError(f"clip_to_limits: last dimension must be {NQ}, got shape {arr.shape}")
        return np.clip(arr, self.limits.lower, self.limits.upper)

    # -- kinematics -----------------------------------------------------------------

    def _fk(self, q: npt.ArrayLike) -> None:
        pin.framesForwardKinematics(self.model, self.data, self._as_q(q))

    def frame_pose(self, name: str, q: npt.ArrayLike) -> RacketPose:
        """Pose of any frame (link) ``name`` in the world: position (3,), rotation (3, 3)."""
        fid = self.frame_id(name)
        self._fk(q)
        M = self.data.oMf[fid]
        return RacketPose(
            position=_frozen(M.translation, (3,), "position"), rotation=_frozen(M.rotation, (3, 3), "rotation")
        )

    def frame_position(self, name: str, q: npt.ArrayLike) -> FloatArray:
        """World position (3,) [m] of the origin of frame ``name`` at configuration q (8,)."""
        fid = self.frame_id(name)
        self._fk(q)
        return np.array(self.data.oMf[fid].translation)

    def fk(self, q: npt.ArrayLike) -> RacketPose:
        """Racket pose (world frame) at configuration q (8,)."""
        return self.frame_pose(RACKET_FRAME, q)

    def cup_position(self, q: npt.ArrayLike) -> FloatArray:
        """World position (3,) [m] of the centre of the ball resting in the cup."""
        return self.frame_position(BALL_CUP_FRAME, q)

    def frame_jacobian(self, name: str, q: npt.ArrayLike) -> FloatArray:
        """World-aligned Jacobian (6, 8) of frame ``name``: rows = [v (3); omega (3)]."""
        fid = self.frame_id(name)
        qa = self._as_q(q)
        J = pin.computeFrameJacobian(self.model, self.data, qa, fid, pin.LOCAL_WORLD_ALIGNED)
        return np.array(J)

    def racket_jacobian(self, q: npt.ArrayLike) -> FloatArray:
        """(6, 8) Jacobian of the racket frame: rows 0-2 map qd to the world velocity of
        the racket origin [m/s], rows 3-5 to the racket angular velocity [rad/s] (world)."""
        return self.frame_jacobian(RACKET_FRAME, q)

    def racket_velocity(self, q: npt.ArrayLike, qd: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Racket origin linear velocity v (3,) [m/s] and angular velocity omega (3,)
        [rad/s], both in the world frame, at configuration q (8,) and joint speeds qd (8,)."""
        qa = self._as_q(q)
        qda = self._as_q(qd, "qd")
        fid = self.frame_id(RACKET_FRAME)
        pin.forwardKinematics(self.model, self.data, qa, qda)
        pin.updateFramePlacement(self.model, self.data, fid)
        nu = pin.getFrameVelocity(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED)
        return np.array(nu.linear), np.array(nu.angular)

    @property
    def effort_limits(self) -> FloatArray:
        """Nominal joint forces/torques (8,) [N | N m] from the TOML (``effort``: the URDF's
        attribute; stand-in values, not data-sheet figures)."""
        return np.array([j.effort for j in self.spec.actuated_joints])

    def joint_efforts(self, q: npt.ArrayLike, qd: npt.ArrayLike, qdd: npt.ArrayLike) -> FloatArray:
        """Inverse dynamics (pinocchio's RNEA on the URDF's rigid links, gravity -Z): the joint
        forces/torques (N, 8) [N | N m] that give accelerations qdd at (q, qd), each (N, 8).
        Not included: drive inertia (the MJCF's armature), friction, the ball."""
        Q, V, A = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (q, qd, qdd))
        if not (Q.shape == V.shape == A.shape and Q.shape[1:] == (NQ,)):
            raise InvalidInputError(
                f"joint_efforts: q, qd, qdd must all be (N, {NQ}), got {Q.shape}, {V.shape}, {A.shape}"
            )
        if not (np.all(np.isfinite(Q)) and np.all(np.isfinite(V)) and np.all(np.isfinite(A))):
            raise InvalidInputError("joint_efforts: q, qd and qdd must be finite")
        model, data = self.model, self.data
        return np.array([pin.rnea(model, data, Q[k], V[k], A[k]) for k in range(Q.shape[0])]).reshape(-1, NQ)


def _limits_from_spec(spec: RobotSpec) -> JointLimits:
    js = spec.actuated_joints
    return JointLimits(
        names=tuple(j.name for j in js),
        lower=np.array([j.lower for j in js]),
        upper=np.array([j.upper for j in js]),
        velocity=np.array([j.velocity for j in js]),
        acceleration=np.array([j.acceleration for j in js]),
        jerk=np.array([j.jerk for j in js]),
    )


def _dynamics_from_spec(spec: RobotSpec) -> JointDynamics:
    js = spec.actuated_joints
    return JointDynamics(
        names=tuple(j.name for j in js),
        wn=np.array([j.wn for j in js]),
        zeta=np.array([j.zeta for j in js]),
    )


def load_robot(urdf_path: str | Path | None = None, *, spec_path: str | Path | None = None) -> Robot:
    """Load the serve robot.

    Args:
        urdf_path: URDF file (default: the shipped ``robots/serve_robot.urdf``).
        spec_path: robot TOML with limits, dynamics and poses (default: the ``.toml``
            next to the URDF if present, else the shipped ``robots/serve_robot.toml``).

    Raises:
        RobotModelError: the URDF is missing or unreadable, or does not match the TOML
            (joint names, position and velocity limits); the message names the path.
    """
    path = Path(urdf_path) if urdf_path is not None else robots_dir() / URDF_NAME
    if not path.is_file():
        raise RobotModelError(f"{path}: URDF file not found")
    if spec_path is None:
        sibling = path.with_suffix(".toml")
        spec_path = sibling if sibling.is_file() else robots_dir() / TOML_NAME
    spec = load_spec(spec_path)
    try:
        model = pin.buildModelFromUrdf(str(path))
    except Exception as exc:  # pinocchio raises ValueError/RuntimeError on bad URDFs
        raise RobotModelError(f"{path}: cannot build the robot model: {exc}") from exc
    names = tuple(str(model.names[i]) for i in range(1, model.njoints))
    if model.nq != NQ or names != spec.joint_names:
        raise RobotModelError(
            f"{path}: expected joints {spec.joint_names} (nq = {NQ}), found {names} (nq = {model.nq})"
        )
    limits = _limits_from_spec(spec)
    for k, name in enumerate(names):
        urdf_vals = (model.lowerPositionLimit[k], model.upperPositionLimit[k], model.velocityLimit[k])
        toml_vals = (limits.lower[k], limits.upper[k], limits.velocity[k])
        if not np.allclose(urdf_vals, toml_vals, rtol=0, atol=1e-8):
            raise RobotModelError(
                f"{path}: joint {name!r} limits {urdf_vals} differ from {spec_path}: {toml_vals} "
                "(regenerate with serve-studio robot-files)"
            )
    for frame in (RACKET_FRAME, BALL_CUP_FRAME):
        if not model.existFrame(frame):
            raise RobotModelError(f"{path}: frame {frame!r} missing")
    return Robot(
        model=model,
        data=model.createData(),
        spec=spec,
        limits=limits,
        dynamics=_dynamics_from_spec(spec),
        urdf_path=path,
    )
