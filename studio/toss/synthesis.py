"""Synthesis of a toss primitive: :func:`make_toss` turns a :class:`~studio.toss.design.TossDesign`
into 1 kHz joint commands of a flat-racket upward swing that releases the ball vertically.

Design:

- start at rest at ``robot.q_flat`` moved sideways by the gantry (``side``,
  ``pose.lateral``) and re-posed by the arm (``pose.gantry_x``, ``pose.start_height``;
  the racket orientation of ``q_flat`` is kept), :func:`studio.toss.arm.toss_start`;
- the cup height follows a :class:`~studio.toss.lift_profile.LiftProfile` ``z(t)`` (C^2
  acceleration): accelerate up, then decelerate faster than gravity so the ball leaves
  the cup where ``z'' = -(g + k v^2)`` (:func:`studio.toss.release.find_release`: gravity
  and the air drag on the ball) at the speed giving ``rise`` in air (drag of the ball
  flight model), and stop;
- the arm joints move along a straight line in joint space ``q = q0 + s d``, with ``d``
  in the null space of the racket's angular velocity and of the cup's lateral velocity
  (on the KUKA arm: A2 and A3 with A5 compensating), so the racket stays exactly flat and
  the cup moves in a vertical plane on a gentle curve; ``s = S(z)`` (Chebyshev
  interpolant of the inverse of the cup height along the line,
  :mod:`studio.toss.lift_path`). The mix inside that plane is solved so the arm alone
  moves the cup vertically at the release height (the gantry is then at rest there). A
  joint-space line uses the arm far better than a straight vertical Cartesian line, which
  exceeds the A2/A3 acceleration and jerk limits;
- the gantry's X axis (prismatic along world X) cancels the cup's horizontal drift along
  that curve, ``gantry_x(t) = gantry_x - (Xc(z(t)) - Xc(z_0))`` (``Xc`` the cup x along
  the line, Chebyshev in ``z``): the cup moves on the exactly vertical line through its
  start point, with zero horizontal velocity *and acceleration* during the lift and the
  stop; the whole racket stays behind the end line. Without it the cup accelerated
  ~12 m/s^2 horizontally at the release, its rim kept pushing the ball and its wall hit
  the ball ~17 ms later (see :mod:`studio.toss.release` for the assumption this
  satisfies). The gantry moves back ~0.17 m during the lift;
- after the release the racket clears the falling ball's path
  (:class:`~studio.toss.design.ClearMove`): from ``clear.delay`` after the release (the
  ball has risen out of the cup) the gantry's Y axis moves the racket ``clear.side`` away
  from the table's centre line, and once the lift has stopped the cup is lowered by
  ``clear.drop`` (rest-to-rest degree-9 smoothsteps over ``clear.time``, C^4). The strike
  planner takes over from the toss shortly after the release (``studio.serve.evaluate``),
  so this part only matters for continuity and for toss-only executions;
- the commands invert the robot's joint model, ``u = q + (2 zeta / wn) q' + q'' / wn^2``
  with exact derivatives (Faa di Bruno on ``S(z(t))`` and ``Xc(z(t))``), evaluated half
  a sample late to compensate the zero-order hold, so the predicted joint motion is the
  designed one; ``u`` is continuous up to acceleration with bounded jerk;
- the release is then found with :func:`~studio.toss.release.find_release` on the
  predicted motion and checked (vertical, at the designed speed, no sideways cup
  acceleration), and so is the clearance of the falling ball
  (:mod:`studio.toss.checks`).

The defaults give a 0.35 m rise: release at x = -1.649 m (0.28 m behind the end line),
z = 0.419 m, 2.68 m/s, 0.359 s after the start; apex 0.769 m 0.27 s later; the ball falls
below z = 0.02 m 0.66 s after the release. Commands stay at <= 90 % of every velocity,
acceleration and jerk limit (binding: gantry X jerk, which cancels the arm's x drift, and
A5 jerk). Higher rises fail on those two limits and on the geometry of the joint-space
line, not on A2/A3.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import InvalidInputError
from studio.toss.arm import toss_start
from studio.toss.checks import (
    check_clearance,
    check_lift,
    check_release,
    limit_violations,
)
from studio.toss.design import DEFAULT_DESIGN, ClearMove, TossDesign
from studio.toss.flight import drag_constant, speed_for_rise
from studio.toss.lift_path import LiftPath, lift_direction
from studio.toss.lift_profile import LiftProfile, smoothstep9_move
from studio.toss.primitive import DEFAULT_DT, TOSS_SIDES, TossPrimitive, TossSide
from studio.toss.release import find_release

if TYPE_CHECKING:
    from studio.robot.model import Robot

FloatArray = npt.NDArray[np.float64]

DEFAULT_DURATION: float = 1.4
"""Default length of a toss primitive [s]: covers the ball's fall back to about table level."""


def make_toss(
    robot: Robot,
    side: TossSide,
    design: TossDesign = DEFAULT_DESIGN,
    *,
    duration: float = DEFAULT_DURATION,
    dt: float = DEFAULT_DT,
    name: str | None = None,
    check_limits: bool = True,
) -> TossPrimitive:
    """Build a toss primitive: a flat-racket upward swing that releases the ball vertically
    (the design is explained in the module docstring).

    Args:
        robot: the serve robot (:func:`studio.robot.model.load_robot`).
        side: ``"right"`` (cup at world ``y = -lateral``) or ``"left"`` (``y = +lateral``).
        design: rise, start pose, lift shape and clearing move (defaults: the shipped tosses).
        duration: length of the primitive [s] (covers the ball's fall back to about
            table level).
        dt: command period [s].
        name: identifier (default ``"toss_<side>"``).
        check_limits: raise if a joint limit is violated (``False`` only to explore
            designs: use :func:`studio.toss.checks.limit_violations` on the result).

    Raises:
        InvalidInputError: bad argument, IK failure, no flat line releasing vertically
            at the release height, a joint limit violated (the message lists them),
            racket tilt during the lift above :data:`~studio.toss.checks.MAX_FLAT_TILT_DEG`,
            no release, a non-vertical one or one with the cup accelerating sideways, a
            racket that does not clear the falling ball's path, or a ball in the cup below
            the playing surface / in front of the end line.
    """
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"make_toss: side must be one of {TOSS_SIDES}, got {side!r}")
    if not (math.isfinite(dt) and dt >= 1e-9):
        raise InvalidInputError(f"make_toss: dt must be finite and >= 1e-09, got {dt}")
    k_drag = drag_constant() if design.drag_k is None else float(design.drag_k)
    v_target = speed_for_rise(design.rise, drag_k=k_drag)
    q_start = toss_start(robot, side, design.pose)
    z0 = _flat_start_height(robot, q_start)
    # Height profile: its release (a = -(g + k v^2), see find_release) is at height h_rel
    # above the start, speed v_target.
    g_release = C.GRAVITY + k_drag * v_target**2
    profile = LiftProfile.design(v_target, design.lift, gravity=g_release)
    t_rel_design, h_rel = _designed_release(profile, design.clear, duration, g_release)
    d = lift_direction(robot, q_start, z0, profile.travel, h_rel)
    path = LiftPath.along(robot, q_start, d, z0, profile.travel)
    t = np.arange(int(round(duration / dt)) + 1, dtype=np.float64) * dt
    t_clear = t_rel_design + design.clear.delay
    qd = _joint_motion(robot, side, path, profile, design.clear, z0, t_clear, t + 0.5 * dt)  # half-sample lead: ZOH
    u, ud, udd, uddd = _invert_joint_model(robot, qd)
    X = robot.dynamics.simulate(u, dt, np.stack([q_start, np.zeros(8)], axis=1))
    cup_p, rot = _cup_motion(robot, X)
    normals = rot[:, :, 2].copy()
    release = check_release(find_release(t, cup_p, normals, rotation=rot, drag_k=k_drag), v_target)
    problems = limit_violations(u, ud, udd, uddd, robot.limits, q=X[:, :, 0]) if check_limits else []
    if problems:
        raise InvalidInputError("make_toss: toss violates the joint limits: " + "; ".join(problems))
    check_clearance(robot, t, cup_p, release, t_clear)
    check_lift(t, cup_p, normals, release)
    return TossPrimitive(
        name=name or f"toss_{side}",
        side=side,
        t=t,
        u=u,
        ud=ud,
        udd=udd,
        uddd=uddd,
        X=X,
        cup_p=cup_p,
        cup_normal=normals,
        release=release,
        profile=profile,
        dt=dt,
    )


def _flat_start_height(robot: Robot, q_start: FloatArray) -> float:
    """Cup height [m] of the start pose, which must hold the racket flat (within 0.5 deg)."""
    R_flat = np.array(robot.fk(q_start).rotation)
    tilt0 = math.degrees(math.acos(min(1.0, float(R_flat[2, 2]))))
    if tilt0 > 0.5:
        raise InvalidInputError(f"make_toss: the start pose is not flat (racket normal tilted {tilt0:.2f} deg)")
    return float(robot.cup_position(q_start)[2])


def _designed_release(profile: LiftProfile, clear: ClearMove, duration: float, g_release: float) -> tuple[float, float]:
    """Time [s] and height above the start [m] of the profile's release (where its
    acceleration crosses ``-g_release``), after checking that the primitive's
    ``duration`` [s] covers the lift and the clearing move and that the drop fits the lift."""
    if profile.duration + 0.05 > duration:
        raise InvalidInputError(f"make_toss: duration {duration} s shorter than the lift ({profile.duration:.3f} s)")
    t_rel_design = profile.release_estimate(g_release)[0]
    h_rel = float(profile.evaluate([t_rel_design])[0, 0])
    travel = profile.travel
    if clear.drop > travel:
        raise InvalidInputError(f"make_toss: ClearMove.drop {clear.drop} m exceeds the lift travel {travel:.3f} m")
    if max(t_rel_design + clear.delay, profile.duration) + clear.time + 0.05 > duration:
        raise InvalidInputError(f"make_toss: duration {duration} s too short for the clearing move after the release")
    return t_rel_design, h_rel


def _joint_motion(
    robot: Robot,
    side: TossSide,
    path: LiftPath,
    profile: LiftProfile,
    clear: ClearMove,
    z0: float,
    t_clear: float,
    te: FloatArray,
) -> list[FloatArray]:
    """Joint positions and their time derivatives of order 1-5, each (M, 8), at the times
    ``te`` (M,) [s]: the arm on the lift line, ``q_arm(t) = q_start + S(z(t)) d``; the
    gantry X cancelling the cup's x drift of the arm, ``gx(t) = gantry_x - (Xc(z(t)) -
    Xc(z0))``, so the cup moves on the vertical line through its start point (zero
    horizontal velocity and acceleration during the whole lift and stop); then gantry Y
    and a descent (``clear``, from ``t_clear`` [s]) clear the ball's path."""
    ix, iy = robot.joint_names.index("gantry_x"), robot.joint_names.index("gantry_y")
    zd = profile.evaluate(te)
    zd[0] += z0
    zd = zd + smoothstep9_move(te, max(t_clear, profile.duration), clear.time, -clear.drop)
    sd = faa_di_bruno([path.S[m](zd[0]) for m in range(6)], zd)  # s and its 5 time derivatives
    xd = faa_di_bruno([path.Xc[m](zd[0]) for m in range(6)], zd)  # arm-only cup x and derivatives
    yd = smoothstep9_move(te, t_clear, clear.time, (-1.0 if side == "right" else 1.0) * clear.side)
    qd = [sd[m][:, None] * path.d[None, :] for m in range(6)]
    for m in range(6):
        qd[m][:, ix] = -xd[m] + (float(path.Xc[0](z0)) if m == 0 else 0.0)
        qd[m][:, iy] = yd[m]
    qd[0] = qd[0] + path.q_start[None, :]
    return qd


def _invert_joint_model(robot: Robot, qd: list[FloatArray]) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Commands ``u = q + (2 zeta / wn) q' + q'' / wn^2`` and their derivatives 1-3 (each
    (M, 8)) that make the robot's joint model follow ``qd`` (positions and derivatives 1-5)."""
    wn = np.asarray(robot.dynamics.wn, dtype=float)
    zeta = np.asarray(robot.dynamics.zeta, dtype=float)
    c1 = 2.0 * zeta / wn
    c2 = 1.0 / wn**2
    u = qd[0] + c1 * qd[1] + c2 * qd[2]
    ud = qd[1] + c1 * qd[2] + c2 * qd[3]
    udd = qd[2] + c1 * qd[3] + c2 * qd[4]
    uddd = qd[3] + c1 * qd[4] + c2 * qd[5]
    return u, ud, udd, uddd


def _cup_motion(robot: Robot, X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Predicted cup centre (N, 3) [m] and racket rotation (N, 3, 3) of the joint states X (N, 8, 2)."""
    n_samples = X.shape[0]
    cup_p = np.empty((n_samples, 3))
    rot = np.empty((n_samples, 3, 3))
    for k in range(n_samples):
        qk = X[k, :, 0]
        cup_p[k] = robot.cup_position(qk)
        rot[k] = robot.fk(qk).rotation
    return cup_p, rot


def faa_di_bruno(Fd: list[FloatArray], zd: FloatArray) -> list[FloatArray]:
    """Time derivatives of f(t) = F(z(t)) up to order 5 (Faa di Bruno's formula).

    Args:
        Fd: [F, F', ..., F^(5)] derivatives of F with respect to z, each (M,).
        zd: (6, M) z and its time derivatives up to order 5.

    Returns:
        [f, f', ..., f^(5)], each (M,).
    """
    z1, z2, z3, z4, z5 = zd[1], zd[2], zd[3], zd[4], zd[5]
    F0, F1, F2, F3, F4, F5 = Fd
    return [
        F0,
        F1 * z1,
        F2 * z1**2 + F1 * z2,
        F3 * z1**3 + 3 * F2 * z1 * z2 + F1 * z3,
        F4 * z1**4 + 6 * F3 * z1**2 * z2 + F2 * (3 * z2**2 + 4 * z1 * z3) + F1 * z4,
        F5 * z1**5
        + 10 * F4 * z1**3 * z2
        + F3 * (15 * z1 * z2**2 + 10 * z1**2 * z3)
        + F2 * (10 * z2 * z3 + 5 * z1 * z4)
        + F1 * z5,
    ]
