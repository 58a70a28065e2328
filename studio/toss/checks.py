"""The checks a designed toss must pass: joint limits, a vertical release without sideways
cup acceleration, a flat lift behind the end line, and a racket that clears the falling
ball's path. Each raises :class:`~studio.errors.InvalidInputError` naming what failed.

World frame, SI units.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Final

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import InvalidInputError
from studio.toss.flight import free_flights, hermite_interpolate
from studio.toss.release import Release

if TYPE_CHECKING:
    from studio.robot.model import JointLimits, Robot

FloatArray = npt.NDArray[np.float64]

MAX_FLAT_TILT_DEG: Final[float] = 2.0
"""Largest tilt of the racket normal from vertical allowed during the lift [deg]."""

MAX_RELEASE_SIDEWAYS_ACCELERATION: Final[float] = 0.5
"""Largest cup acceleration perpendicular to its normal at the release [m/s^2] that
:func:`studio.toss.synthesis.make_toss` accepts: the release model assumes the rim does not push the
ball sideways (see :mod:`studio.toss.release`)."""

CLEAR_MARGIN: Final[float] = 0.01
"""Least horizontal gap [m] between the falling ball and the cup's base plate that
:func:`studio.toss.synthesis.make_toss` accepts after the racket cleared the ball's path."""


def limit_violations(
    u: FloatArray,
    ud: FloatArray,
    udd: FloatArray,
    uddd: FloatArray,
    limits: JointLimits,
    *,
    q: FloatArray | None = None,
) -> list[str]:
    """Joint-limit violations of a command trajectory, as readable messages.

    Args:
        u, ud, udd, uddd: commands and their derivatives, each (N, 8).
        limits: the robot's :class:`~studio.robot.model.JointLimits`.
        q: optional predicted positions (N, 8), checked against the position limits too.

    Returns:
        One message per violated (joint, quantity), empty if all are within limits.
    """
    out: list[str] = []
    tol = 1e-9
    checks: list[tuple[str, FloatArray, FloatArray, FloatArray]] = [
        ("command position", u, limits.lower, limits.upper),
        ("velocity", ud, -limits.velocity, limits.velocity),
        ("acceleration", udd, -limits.acceleration, limits.acceleration),
        ("jerk", uddd, -limits.jerk, limits.jerk),
    ]
    if q is not None:
        checks.append(("predicted position", q, limits.lower, limits.upper))
    for what, arr, lo, hi in checks:
        for j, name in enumerate(limits.names):
            worst_hi = float(np.max(arr[:, j] - hi[j]))
            worst_lo = float(np.max(lo[j] - arr[:, j]))
            if worst_hi > tol or worst_lo > tol:
                val = float(np.max(arr[:, j])) if worst_hi > worst_lo else float(np.min(arr[:, j]))
                out.append(f"joint {name!r} {what} {val:.4g} outside [{lo[j]:.4g}, {hi[j]:.4g}]")
    return out


def check_clearance(robot: Robot, t: FloatArray, cup_p: FloatArray, release: Release, t_clear: float) -> None:
    """Check that the racket gets out of the way of the tossed ball (still air, no noise).

    1. When the clearing move starts (``t_clear`` [s]) the ball has risen out of the
       cup: its centre is above the cup's ball centre by more than the ball's sag below
       the rim (``R - sqrt(R^2 - r_rim^2)``).
    2. From the apex on, while the ball is at the height of the cup and handle
       (``z_cup - 0.065 m <= z <= z_cup + 0.04 m``, about 2 R + the racket's thickness
       below the cup centre), it is horizontally at least ``R + cup plate radius +``
       :data:`CLEAR_MARGIN` from the cup centre. The blade starts 5 cm further along the
       handle and the arm is farther back, so the cup and the handle are what the ball
       can hit; :mod:`studio.sim.rollout` checks the full geometry (tests).

    Raises:
        InvalidInputError: a check fails (raise ``ClearMove.side`` / ``ClearMove.delay``).
    """
    from studio.physics import ball

    rs = robot.spec.racket
    R = rs.ball_radius
    sag = R - math.sqrt(R * R - rs.cup_rim_radius**2)
    FT, FP, FV = free_flights(
        release.position[None, :],
        release.velocity[None, :],
        np.array([release.time]),
        max(float(t[-1]) - release.time, 1e-3),
        ball.DEFAULT_FLIGHT,
        h=5e-3,
    )  # RK4 at 5 ms: ~1e-8 m on this smooth, spinless flight
    ft, fp, fv = FT[0], FP[0], FV[0]
    sel = t > release.time
    tq = t[sel]
    tq = tq[tq <= ft[-1]]
    bp = hermite_interpolate(ft, fp, fv, tq)
    cp = cup_p[sel][: tq.size]
    k0 = int(np.searchsorted(tq, t_clear))
    if k0 < tq.size and float(bp[k0, 2] - cp[k0, 2]) <= sag:
        raise InvalidInputError(
            f"make_toss: the racket starts clearing the ball's path at {t_clear:.3f} s while the ball is still in "
            f"the cup ({(bp[k0, 2] - cp[k0, 2]) * 1e3:.1f} mm above its seat, sag {sag * 1e3:.1f} mm): raise ClearMove.delay"
        )
    after_apex = np.arange(tq.size) >= int(np.argmax(bp[:, 2]))
    band = after_apex & (bp[:, 2] >= cp[:, 2] - 0.065) & (bp[:, 2] <= cp[:, 2] + 0.04)
    need = R + rs.cup_plate_radius + CLEAR_MARGIN
    gap = np.hypot(bp[:, 0] - cp[:, 0], bp[:, 1] - cp[:, 1])
    if np.any(band) and float(np.min(gap[band])) < need:
        k = int(np.flatnonzero(band)[np.argmin(gap[band])])
        raise InvalidInputError(
            f"make_toss: the falling ball passes {gap[k] * 1e3:.0f} mm from the cup at {tq[k]:.3f} s "
            f"(< {need * 1e3:.0f} mm): raise ClearMove.side or start the clearing move earlier"
        )


def check_release(release: Release | None, v_target: float) -> Release:
    """The predicted release: there is one, vertical at the designed speed ``v_target``
    [m/s] (within 1 cm/s), with the cup's sideways acceleration below
    :data:`MAX_RELEASE_SIDEWAYS_ACCELERATION`."""
    if release is None:
        raise InvalidInputError("make_toss: the ball never leaves the cup")
    if release.horizontal_speed > 0.01 or abs(float(release.velocity[2]) - v_target) > 0.01:
        raise InvalidInputError(
            f"make_toss: the predicted release velocity {np.round(release.velocity, 4)} m/s is not the designed "
            f"vertical {v_target:.3f} m/s"
        )

    if release.sideways_acceleration > MAX_RELEASE_SIDEWAYS_ACCELERATION:
        raise InvalidInputError(
            f"make_toss: the cup accelerates {release.sideways_acceleration:.3f} m/s^2 sideways at the release "
            f"(> {MAX_RELEASE_SIDEWAYS_ACCELERATION} m/s^2): its rim would push the ball"
        )
    return release


def check_lift(t: FloatArray, cup_p: FloatArray, normals: FloatArray, release: Release) -> None:
    """Up to the release the racket stays flat (tilt <= :data:`MAX_FLAT_TILT_DEG`) and the
    ball in the cup stays above the playing surface level and behind the end line."""
    lift = t <= release.time
    tilt = np.degrees(np.arccos(np.clip(normals[lift, 2], -1.0, 1.0)))
    if float(np.max(tilt)) > MAX_FLAT_TILT_DEG:
        raise InvalidInputError(f"make_toss: racket tilts {float(np.max(tilt)):.2f} deg during the lift")
    if float(np.min(cup_p[lift, 2])) <= C.BALL_RADIUS:
        raise InvalidInputError("make_toss: the ball in the cup goes below the playing surface level")
    if float(np.max(cup_p[lift, 0])) >= -C.TABLE_LENGTH / 2 - C.BALL_RADIUS:
        raise InvalidInputError("make_toss: the ball in the cup is not behind the end line")
