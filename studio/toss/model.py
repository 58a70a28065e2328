"""Ball toss: release model, toss motion primitives, recordings and the toss model.

Paper, section "Ball toss using motion primitives": a toss is a fixed trajectory of
joint commands ``u_t(t)`` that starts with the racket "flat" (normal up, ball resting
in the ball cup on the handle), lifts the ball and releases it near vertically without
spin (ITTF Law 2.6.2). The toss is executed many times, the ball is tracked by
cameras, the recordings are time-aligned and averaged with a Savitzky-Golay filter
into a mean path ``p_bar(t)``, and ``t_lift`` is the time on the command clock at which
the ball's acceleration reaches gravity (free flight).

Contents:

- :func:`find_release` / :class:`Release`: when the ball leaves the cup along a
  (predicted) racket motion: the first instant the contact force along the cup
  normal, ``m (a_cup + g e_z + k |v| v) . n_cup`` (gravity and air drag), vanishes
  (assumes the cup does not accelerate sideways there, so the rim does not push the
  ball).
- :func:`make_toss` / :class:`TossPrimitive`: a flat, vertical-release toss for the
  right or left side: the cup rises on an exactly vertical line (arm on a joint-space
  line, gantry X cancelling its horizontal drift), then the racket steps aside and
  down out of the falling ball's path; commands at 1 kHz that invert the robot's
  joint model so the predicted motion is the designed one, within every joint limit.
- :func:`simulate_tosses` / :class:`TossNoise`: synthetic camera recordings of
  repeated tosses (vibration, release jitter, air flow, tracking noise, camera rate,
  phase and clock offset).
- :class:`TossModel`: alignment, Savitzky-Golay mean path, ``t_lift``, spread, and
  ball states (mean, per toss, random) for the strike planner.
- :func:`load_recordings_csv` / :func:`save_recordings_csv`: the ``toss_id,t,x,y,z``
  CSV format of real or synthetic recordings.
- :func:`load_default_toss_model`: models from the shipped ``studio/data/tosses``
  recordings, written by ``python -m studio.toss.model --generate``.

Frames and units: world frame of ``DESIGN.md`` (origin at the centre of the playing
surface, +X towards the receiver, +Z up), SI units. Times in a model or a primitive
are on the *command clock* of the toss primitive: ``t = 0`` is the first sample of
``u_t``; recordings carry their own clock until aligned.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Final, Literal

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import DataFileError, InvalidInputError
from studio.paths import DATA_DIR

if TYPE_CHECKING:
    from studio.physics.ball import BallState
    from studio.robot.model import JointLimits, Robot

FloatArray = npt.NDArray[np.float64]

# =====================================================================================
# Release model
# =====================================================================================


@dataclass(frozen=True, slots=True, eq=False)
class Release:
    """The instant the ball leaves the ball cup (see :func:`find_release`).

    All vectors are in the world frame.
    """

    time: float
    """Release time [s], on the clock of the samples given to :func:`find_release`."""
    index: int
    """Index ``i`` of the last sample at or before the release: ``t[i] <= time < t[i+1]``
    (``0`` if the ball is not supported from the first sample on)."""
    position: FloatArray
    """Ball centre at release [m], ``(3,)``: the cup's ball centre at ``time``."""
    velocity: FloatArray
    """Ball velocity at release [m/s], ``(3,)``. The ball rides with the cup until the
    contact force vanishes, so this equals the cup's velocity at ``time``."""
    cup_velocity: FloatArray
    """Velocity of the cup's ball centre at release [m/s], ``(3,)`` (same as ``velocity``;
    kept separately so callers that add a release perturbation can keep the cup's)."""
    cup_acceleration: FloatArray
    """Acceleration of the cup's ball centre at release [m/s^2], ``(3,)``."""
    normal: FloatArray
    """Unit cup/racket normal at release, ``(3,)``."""
    angular_velocity: FloatArray
    """Angular velocity of the racket at release [rad/s], ``(3,)``. The ball does not roll
    in the cup, so this is also the ball's spin at release; ITTF Law 2.6.2 wants it ~0.
    When only normals are given its component along the normal is not observable and is
    reported as 0 (only ``n x dn/dt`` is)."""

    @property
    def horizontal_speed(self) -> float:
        """Horizontal speed of the ball at release [m/s]."""
        return float(np.hypot(self.velocity[0], self.velocity[1]))

    @property
    def horizontal_acceleration(self) -> float:
        """Horizontal acceleration of the cup at release [m/s^2]."""
        return float(np.hypot(self.cup_acceleration[0], self.cup_acceleration[1]))

    @property
    def sideways_acceleration(self) -> float:
        """Cup acceleration perpendicular to the cup normal at release [m/s^2]: the push
        the rim would have to give the ball sideways. :func:`find_release` assumes it is
        ~0 (see there); :func:`make_toss` keeps it below
        :data:`MAX_RELEASE_SIDEWAYS_ACCELERATION`."""
        a = self.cup_acceleration
        return float(np.linalg.norm(a - float(a @ self.normal) * self.normal))

    @property
    def spin(self) -> float:
        """Magnitude of the spin at release [rad/s]."""
        return float(np.linalg.norm(self.angular_velocity))

    @property
    def free_rise(self) -> float:
        """Rise above the release point in vacuum, ``v_z^2 / (2 g)`` [m] (drag lowers it
        by a few per cent; the toss tests use the simulated flight instead)."""
        vz = max(float(self.velocity[2]), 0.0)
        return vz * vz / (2.0 * C.GRAVITY)


def contact_margin(
    cup_acceleration: npt.ArrayLike,
    cup_normal: npt.ArrayLike,
    *,
    gravity: float = C.GRAVITY,
    velocity: npt.ArrayLike | None = None,
    drag_k: float = 0.0,
) -> FloatArray:
    """Normal contact force per unit ball mass between cup and ball [m/s^2].

    ``m_i = (a_cup,i + g e_z + k |v_i| v_i) . n_i`` for ``a: (N, 3)``, ``n: (N, 3)`` (or
    single ``(3,)`` vectors): the force the cup must push on the ball, along its
    normal, to keep it riding along against gravity and the air drag
    ``-k |v| v`` (``drag_k`` = k [1/m], ``velocity`` = the ball's = the cup's velocity
    [m/s] in still air; no drag term without it). The ball stays in the cup while it
    is ``>= 0``.
    """
    a = np.asarray(cup_acceleration, dtype=float)
    n = np.asarray(cup_normal, dtype=float)
    a_plus_g = a.copy()
    a_plus_g[..., 2] += gravity
    if velocity is not None and drag_k != 0.0:
        v = np.asarray(velocity, dtype=float)
        a_plus_g = a_plus_g + drag_k * np.linalg.norm(v, axis=-1, keepdims=True) * v
    return np.einsum("...i,...i->...", a_plus_g, n)


def find_release(
    t: npt.ArrayLike,
    cup_p: npt.ArrayLike,
    cup_normal: npt.ArrayLike,
    *,
    gravity: float = C.GRAVITY,
    cup_v: npt.ArrayLike | None = None,
    cup_a: npt.ArrayLike | None = None,
    rotation: npt.ArrayLike | None = None,
    drag_k: float | None = None,
) -> Release | None:
    """Find when the ball leaves the ball cup along a (predicted) racket motion.

    Release model: the ball (a point of mass ``m`` at the cup's ball centre) rides in
    the cup while the cup pushes on it, i.e. while the normal contact force is
    non-negative::

        N / m = (a_cup + g e_z + k |v_cup| v_cup) . n_cup >= 0

    where ``a_cup`` and ``v_cup`` are the acceleration and velocity of the cup's ball
    centre, ``n_cup`` the unit cup/racket normal (face A, the cup's side) and ``k`` the
    ball's quadratic drag constant (still air): the drag on a rising ball presses it
    into the cup, so it leaves when the cup decelerates at ``g + k v^2`` (about
    10.5 m/s^2 at 2.7 m/s), where the free ball's own deceleration takes over without
    a jump (no ball-in-cup overlap right after the release). The ball leaves at the first
    instant this normal force vanishes (becomes negative): the crossing is located by
    linear interpolation of the margin between the two samples that bracket it; the
    release position is Hermite-interpolated from positions and velocities, the
    velocity linearly. After that the ball is in free flight (gravity, drag) from the
    returned state, with the racket's angular velocity as spin (no rolling in the cup).

    Assumption: the rim does not push the ball sideways at the release, i.e. the cup's
    acceleration perpendicular to ``n_cup`` is ~0 there
    (:attr:`Release.sideways_acceleration`). Only the normal force is modelled: the
    ball rests on the rim's inner edges (rim radius < ball radius), which could hold it
    sideways while it is pressed in, but once the normal force vanishes a sideways
    accelerating cup keeps pushing the ball with its rim and its wall soon hits it
    (the MuJoCo rollout sees that as a robot contact), so the free flight from the
    returned state would be wrong. Check ``sideways_acceleration`` of the result for
    motions not made by :func:`make_toss` (which keeps it below
    :data:`MAX_RELEASE_SIDEWAYS_ACCELERATION`).

    Robustness: the normal is renormalised per sample; a margin that is exactly 0 at
    a sample is still contact (``>= 0``); a ball that is not supported from the first
    sample on is released at ``t[0]``; the first crossing counts (a ball once free
    does not come back into the cup in this model).

    Feed it the *predicted* joint motion (after the joint dynamics model), not the
    commands: e.g. ``cup_p[i] = robot.cup_position(q[i])``.

    Args:
        t: sample times [s], ``(N,)``, strictly increasing, ``N >= 3``.
        cup_p: ball-centre position in the cup [m], world frame, ``(N, 3)``.
        cup_normal: cup/racket normal, world frame, ``(N, 3)`` (normalised here).
        gravity: gravitational acceleration [m/s^2] (along -Z).
        cup_v: optional exact cup velocities [m/s], ``(N, 3)``; else finite differences
            of ``cup_p`` (second-order, ``np.gradient``).
        cup_a: optional exact cup accelerations [m/s^2], ``(N, 3)``; else finite
            differences of the velocities.
        rotation: optional racket rotation matrices (racket to world), ``(N, 3, 3)``,
            for the full angular velocity ``omega^ = dR/dt R^T``; without it only the
            normal's turning rate ``n x dn/dt`` is reported.
        drag_k: drag constant ``k = rho C_D A / (2 m)`` [1/m] of the ball; ``None``: that
            of :data:`studio.physics.ball.DEFAULT_FLIGHT`; ``0``: no drag.

    Returns:
        The :class:`Release`, or ``None`` if the ball stays in the cup over all samples.

    Raises:
        InvalidInputError: shapes mismatch, fewer than 3 samples, non-finite values,
            non-increasing times or a zero normal.
    """
    tt = np.asarray(t, dtype=float)
    p = np.asarray(cup_p, dtype=float)
    n = np.asarray(cup_normal, dtype=float)
    if tt.ndim != 1 or tt.size < 3:
        raise InvalidInputError(f"find_release: t must be (N,) with N >= 3, got shape {tt.shape}")
    N = tt.size
    for name, arr in (("cup_p", p), ("cup_normal", n)):
        if arr.shape != (N, 3):
            raise InvalidInputError(f"find_release: {name} must be ({N}, 3), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise InvalidInputError(f"find_release: {name} has non-finite values")
    if not np.all(np.isfinite(tt)) or np.any(np.diff(tt) <= 0.0):
        raise InvalidInputError("find_release: t must be finite and strictly increasing")
    norms = np.linalg.norm(n, axis=1)
    if np.any(norms < 1e-9):
        raise InvalidInputError("find_release: cup_normal has zero-length vectors")
    n = n / norms[:, None]

    if cup_v is None:
        v = np.gradient(p, tt, axis=0, edge_order=2)
    else:
        v = np.asarray(cup_v, dtype=float)
        if v.shape != (N, 3):
            raise InvalidInputError(f"find_release: cup_v must be ({N}, 3), got {v.shape}")
    if cup_a is None:
        a = np.gradient(v, tt, axis=0, edge_order=2)
    else:
        a = np.asarray(cup_a, dtype=float)
        if a.shape != (N, 3):
            raise InvalidInputError(f"find_release: cup_a must be ({N}, 3), got {a.shape}")

    k_drag = _drag_constant() if drag_k is None else float(drag_k)
    if not (math.isfinite(k_drag) and k_drag >= 0.0):
        raise InvalidInputError(f"find_release: drag_k must be finite and >= 0, got {drag_k}")
    margin = contact_margin(a, n, gravity=gravity, velocity=v, drag_k=k_drag)
    negative = np.flatnonzero(margin < 0.0)
    if negative.size == 0:
        return None
    k = int(negative[0])

    if rotation is not None:
        R = np.asarray(rotation, dtype=float)
        if R.shape != (N, 3, 3):
            raise InvalidInputError(f"find_release: rotation must be ({N}, 3, 3), got {R.shape}")
        Rd = np.gradient(R, tt, axis=0, edge_order=2)
        W = Rd @ np.transpose(R, (0, 2, 1))
        W = 0.5 * (W - np.transpose(W, (0, 2, 1)))
        omega = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1)
    else:
        nd = np.gradient(n, tt, axis=0, edge_order=2)
        omega = np.cross(n, nd)

    if k == 0:
        return Release(
            time=float(tt[0]),
            index=0,
            position=p[0].copy(),
            velocity=v[0].copy(),
            cup_velocity=v[0].copy(),
            cup_acceleration=a[0].copy(),
            normal=n[0].copy(),
            angular_velocity=omega[0].copy(),
        )

    i = k - 1
    m0, m1 = float(margin[i]), float(margin[k])
    s = m0 / (m0 - m1)  # in [0, 1): m0 >= 0 > m1
    h = float(tt[k] - tt[i])
    t_rel = float(tt[i] + s * h)
    # Cubic Hermite position, linear velocity/acceleration/normal/omega.
    h00 = 2 * s**3 - 3 * s**2 + 1
    h10 = s**3 - 2 * s**2 + s
    h01 = -2 * s**3 + 3 * s**2
    h11 = s**3 - s**2
    pos = h00 * p[i] + h10 * h * v[i] + h01 * p[k] + h11 * h * v[k]
    vel = (1 - s) * v[i] + s * v[k]
    acc = (1 - s) * a[i] + s * a[k]
    nor = (1 - s) * n[i] + s * n[k]
    nor = nor / np.linalg.norm(nor)
    om = (1 - s) * omega[i] + s * omega[k]
    return Release(
        time=t_rel,
        index=i,
        position=pos,
        velocity=vel,
        cup_velocity=vel.copy(),
        cup_acceleration=acc,
        normal=nor,
        angular_velocity=om,
    )


# =====================================================================================
# Toss primitive
# =====================================================================================

TossSide = Literal["right", "left"]
TOSS_SIDES: Final[tuple[TossSide, ...]] = ("right", "left")
"""The two toss sides. Facing the receiver (+X), the robot's right is world -Y."""

DEFAULT_DT: Final[float] = 1e-3
"""Command period of the toss primitive [s] (the robot's 1 kHz command rate, paper)."""

MAX_FLAT_TILT_DEG: Final[float] = 2.0
"""Largest tilt of the racket normal from vertical allowed during the lift [deg]."""

MAX_RELEASE_SIDEWAYS_ACCELERATION: Final[float] = 0.5
"""Largest cup acceleration perpendicular to its normal at the release [m/s^2] that
:func:`make_toss` accepts: the release model assumes the rim does not push the ball
sideways (see :func:`find_release`)."""

CLEAR_MARGIN: Final[float] = 0.01
"""Least horizontal gap [m] between the falling ball and the cup's base plate that
:func:`make_toss` accepts after the racket cleared the ball's path."""


def _smootherstep_terms(tau: FloatArray) -> tuple[FloatArray, ...]:
    """Quintic smootherstep s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5, its derivatives
    s', s'', s''' and its first two integrals S1, S2 (S1(0) = S2(0) = 0)."""
    t2 = tau * tau
    t3 = t2 * tau
    t4 = t3 * tau
    t5 = t4 * tau
    s = 10 * t3 - 15 * t4 + 6 * t5
    s1 = 30 * t2 - 60 * t3 + 30 * t4
    s2 = 60 * tau - 180 * t2 + 120 * t3
    s3 = 60 - 360 * tau + 360 * t2
    i1 = 2.5 * t4 - 3 * t5 + t5 * tau
    i2 = 0.5 * t5 - 0.5 * t5 * tau + t5 * t2 / 7.0
    return s, s1, s2, s3, i1, i2


_SMOOTHSTEP9: Final = np.polynomial.Polynomial([0, 0, 0, 0, 0, 126, -420, 540, -315, 70])
"""Degree-9 smoothstep ``s(tau)``: s(0) = 0, s(1) = 1, derivatives 1-4 zero at both ends."""


def _smoothstep9_move(t: FloatArray, start: float, duration: float, distance: float) -> FloatArray:
    """A rest-to-rest move by ``distance`` over ``[start, start + duration]`` [s].

    Position is ``distance * s((t - start) / duration)`` with the degree-9 smoothstep,
    so position is C^4 (the 5th derivative is piecewise continuous): joint commands
    from the inverted joint model are then continuous up to acceleration.

    Returns:
        (6, M): the offset [m or rad] and its time derivatives of order 1-5 at ``t`` (M,).
    """
    tau = np.clip((np.asarray(t, dtype=float) - start) / duration, 0.0, 1.0)
    inside = (tau > 0.0) & (tau < 1.0)
    out = np.zeros((6, tau.size))
    poly = _SMOOTHSTEP9
    for m in range(6):
        vals = poly(tau) * distance / duration**m
        out[m] = vals if m == 0 else np.where(inside, vals, 0.0)
        poly = poly.deriv()
    return out


@dataclass(frozen=True, slots=True)
class LiftProfile:
    """Vertical motion of the ball cup during a toss, as a piecewise acceleration.

    The acceleration ``a(t)`` [m/s^2] (positive up) is a chain of constant holds joined
    by quintic smootherstep transitions, so ``a`` is C^2 and the height ``z(t)`` is C^4:
    the joint commands obtained by inverting the second-order joint model
    (``u = q + 2 zeta/wn q' + q''/wn^2``) are then continuous up to acceleration with
    bounded jerk. Phases (times in seconds from the start of the toss):

    rest ``hold_start`` -> ramp ``0 -> lift_acceleration`` over ``ramp_up`` -> hold
    ``lift_hold`` -> ramp ``lift_acceleration -> -stop_deceleration`` over
    ``ramp_release`` (the ball leaves the cup in this ramp, where ``a`` crosses
    ``-(g + k v^2)``, see :func:`find_release`)
    -> hold ``-stop_deceleration`` (length solved so that the cup ends at rest) -> ramp
    back to 0 over ``ramp_stop`` -> rest. :meth:`design` picks ``lift_hold`` and
    ``stop_deceleration`` for a wanted release speed.
    """

    hold_start: float
    """Rest before the lift [s]."""
    lift_acceleration: float
    """Upward acceleration of the lift [m/s^2]."""
    ramp_up: float
    """Duration of the 0 -> lift acceleration ramp [s]."""
    lift_hold: float
    """Duration of the constant lift acceleration [s] (sets the release speed)."""
    stop_deceleration: float
    """Deceleration of the stop [m/s^2], > g so that the ball leaves the cup."""
    ramp_release: float
    """Duration of the lift -> stop ramp [s], in which the ball is released."""
    ramp_stop: float
    """Duration of the final ramp back to zero acceleration [s]."""
    _knots: tuple[tuple[float, float, float, float, float, float], ...] = field(
        default=(), init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        for name in ("hold_start", "lift_hold"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise InvalidInputError(f"LiftProfile.{name} must be finite and >= 0, got {getattr(self, name)}")
        for name in ("lift_acceleration", "ramp_up", "stop_deceleration", "ramp_release", "ramp_stop"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise InvalidInputError(f"LiftProfile.{name} must be finite and > 0, got {getattr(self, name)}")
        A, D = self.lift_acceleration, self.stop_deceleration
        stop_hold = self._stop_hold(A, self.ramp_up, self.lift_hold, D, self.ramp_release, self.ramp_stop)
        if stop_hold < -1e-9:
            raise InvalidInputError(
                "LiftProfile: the stop ramps alone overshoot the lift speed "
                f"(stop hold {stop_hold:.4f} s < 0): lower stop_deceleration or shorten ramp_release/ramp_stop"
            )
        stop_hold = max(stop_hold, 0.0)
        # (t0, T, a0, a1, v0, z0) of each segment, z relative to the start height.
        segs: list[tuple[float, float, float, float, float, float]] = []
        t0, v0, z0 = 0.0, 0.0, 0.0
        for T, a0, a1 in (
            (self.hold_start, 0.0, 0.0),
            (self.ramp_up, 0.0, A),
            (self.lift_hold, A, A),
            (self.ramp_release, A, -D),
            (stop_hold, -D, -D),
            (self.ramp_stop, -D, 0.0),
        ):
            segs.append((t0, T, a0, a1, v0, z0))
            # Integrals of s over [0, 1]: S1(1) = 1/2, S2(1) = 1/2 - 1/2 + 1/7 = 1/7.
            z0 = z0 + v0 * T + a0 * T * T / 2 + (a1 - a0) * T * T / 7.0
            v0 = v0 + a0 * T + (a1 - a0) * T / 2
            t0 += T
        segs.append((t0, math.inf, 0.0, 0.0, 0.0, z0))
        object.__setattr__(self, "_knots", tuple(segs))

    @staticmethod
    def _stop_hold(A: float, T1: float, h: float, D: float, T2: float, T3: float) -> float:
        v_before_stop = A * (T1 / 2 + h) + (A - D) * T2 / 2
        return (v_before_stop - D * T3 / 2) / D

    @classmethod
    def design(
        cls,
        release_speed: float,
        *,
        lift_acceleration: float,
        ramp_up: float,
        ramp_release: float,
        ramp_stop: float,
        hold_start: float,
        gravity: float = C.GRAVITY,
    ) -> LiftProfile:
        """The profile whose cup crosses ``a = -g`` at ``release_speed`` [m/s] and stops
        with no deceleration hold: ``lift_hold`` and ``stop_deceleration`` are solved.

        Raises:
            InvalidInputError: no such profile (the ramps alone are too fast, or the
                stop deceleration would not exceed ``1.05 g``).
        """

        def make(h: float) -> LiftProfile:
            Vs = lift_acceleration * (ramp_up / 2 + h)
            D = (Vs + lift_acceleration * ramp_release / 2) / ((ramp_release + ramp_stop) / 2)
            return cls(
                hold_start=hold_start,
                lift_acceleration=lift_acceleration,
                ramp_up=ramp_up,
                lift_hold=h,
                stop_deceleration=D,
                ramp_release=ramp_release,
                ramp_stop=ramp_stop,
            )

        def ok_and_fast(h: float) -> bool:
            p = make(h)
            return p.stop_deceleration > 1.05 * gravity and p.release_estimate(gravity)[1] >= release_speed

        lo, hi = 0.0, 4.0
        if not ok_and_fast(hi):
            raise InvalidInputError(f"LiftProfile.design: release speed {release_speed} m/s not reachable")
        if ok_and_fast(lo):
            raise InvalidInputError(
                f"LiftProfile.design: the ramps alone exceed the release speed {release_speed} m/s: "
                "lower lift_acceleration or shorten ramp_up / ramp_release"
            )
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if ok_and_fast(mid):
                hi = mid
            else:
                lo = mid
        return make(hi)

    @property
    def duration(self) -> float:
        """Time at which the cup is back at rest [s]."""
        return self._knots[-1][0]

    @property
    def travel(self) -> float:
        """Total upward travel of the cup [m]."""
        return self._knots[-1][5]

    def evaluate(self, t: npt.ArrayLike) -> FloatArray:
        """Height offset and its derivatives at times ``t`` (M,) [s].

        Returns:
            (6, M): z - z_start [m], z' [m/s], z'' [m/s^2], z''' [m/s^3], z'''' [m/s^4],
            z''''' [m/s^5]. Before 0 and after :attr:`duration` the cup is at rest.
        """
        tt = np.atleast_1d(np.asarray(t, dtype=float))
        out = np.zeros((6, tt.size))
        for t0, T, a0, a1, v0, z0 in self._knots:
            m = tt >= t0
            if math.isfinite(T):
                m &= tt < t0 + T
            if not np.any(m):
                continue
            r = tt[m] - t0
            if not math.isfinite(T):
                out[0, m] = z0
                continue
            tau = r / T
            dA = a1 - a0
            s, s1, s2, s3, i1, i2 = _smootherstep_terms(tau)
            out[0, m] = z0 + v0 * r + a0 * r * r / 2 + dA * T * T * i2
            out[1, m] = v0 + a0 * r + dA * T * i1
            out[2, m] = a0 + dA * s
            out[3, m] = dA * s1 / T
            out[4, m] = dA * s2 / T**2
            out[5, m] = dA * s3 / T**3
        return out

    def release_estimate(self, gravity: float = C.GRAVITY) -> tuple[float, float]:
        """Time [s] and upward speed [m/s] at which the cup's acceleration crosses -g
        (the release of the ideal, lag-free motion)."""
        t0, T, a0, a1, _, _ = self._knots[3]
        # Solve a0 + (a1 - a0) s(tau) = -g for tau in (0, 1) (s is monotonic).
        target = (a0 + gravity) / (a0 - a1)
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if _smootherstep_terms(np.array(mid))[0] < target:
                lo = mid
            else:
                hi = mid
        t_rel = t0 + 0.5 * (lo + hi) * T
        return t_rel, float(self.evaluate([t_rel])[1, 0])


def _rotation_error(R_target: FloatArray, R: FloatArray) -> FloatArray:
    """Small-angle rotation error vector (3,) [rad] taking R to R_target (world frame)."""
    return 0.5 * (
        np.cross(R[:, 0], R_target[:, 0]) + np.cross(R[:, 1], R_target[:, 1]) + np.cross(R[:, 2], R_target[:, 2])
    )


def _cup_jacobian(robot: Robot, q: FloatArray) -> FloatArray:
    """(6, 8) world-aligned Jacobian of the cup point: rows [v_cup (3); omega (3)]."""
    J = robot.racket_jacobian(q)
    r = robot.cup_position(q) - np.asarray(robot.fk(q).position)
    return np.vstack([J[:3] - np.cross(r, J[3:].T).T, J[3:]])


def _pose_ik(
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
        err = np.concatenate([cup_target - cup, _rotation_error(R_target, pose.rotation)])
        if float(np.max(np.abs(err))) < tol:
            return q
        dq, *_ = np.linalg.lstsq(_cup_jacobian(robot, q)[:, joints], err, rcond=None)
        q[joints] += dq
    raise InvalidInputError(
        f"toss IK did not converge for cup target {np.round(cup_target, 4)} (residual {float(np.max(np.abs(err))):.2e}); "
        "the toss leaves the robot's workspace: lower the rise or the lateral offset"
    )


@dataclass(frozen=True, eq=False)
class TossPrimitive:
    """A toss motion primitive ``u_t(t)`` and its predicted execution (paper: "the
    resulting motion is a trajectory of joint commands that produces a ball toss").

    Commands are sampled at ``dt`` on the toss's command clock (``t[0] = 0``); command
    ``u[k]`` is held over ``[t[k], t[k] + dt)``. ``u`` is continuous up to acceleration:
    ``ud`` and ``udd`` are its exact derivatives, so a strike plan can take over from
    any sample ``k`` with the initial command state ``(u[k], ud[k], udd[k])`` and the
    predicted joint state ``X[k]``. Arrays are read-only.
    """

    name: str
    """Identifier, e.g. ``"toss_right"``."""
    side: TossSide
    """Toss side: ``"right"`` (world -Y of the robot's centre line) or ``"left"`` (+Y)."""
    t: FloatArray
    """Command times (N,) [s], ``t[k] = k dt``."""
    u: FloatArray
    """Joint position commands (N, 8) [m, m, rad x 6], robot joint order."""
    ud: FloatArray
    """Command velocities (N, 8) [m/s | rad/s]."""
    udd: FloatArray
    """Command accelerations (N, 8) [m/s^2 | rad/s^2]."""
    uddd: FloatArray
    """Command jerks (N, 8) [m/s^3 | rad/s^3] (piecewise continuous)."""
    X: FloatArray
    """Predicted joint state (N, 8, 2) = [q, q'] from the robot's joint dynamics
    (``robot.dynamics.simulate(u, dt, X0)``, starting at rest at ``u[0]``)."""
    cup_p: FloatArray
    """Predicted centre of the ball in the cup (N, 3) [m], world frame."""
    cup_normal: FloatArray
    """Predicted racket (face A) normal (N, 3), world frame."""
    release: Release
    """Predicted release of the ball (:func:`find_release` on the predicted motion)."""
    profile: LiftProfile
    """Vertical cup motion the commands realise."""
    dt: float = DEFAULT_DT
    """Command period [s]."""

    def __post_init__(self) -> None:
        if self.side not in TOSS_SIDES:
            raise InvalidInputError(f"TossPrimitive.side must be one of {TOSS_SIDES}, got {self.side!r}")
        n = self.t.shape[0]
        for fname, shape in (
            ("t", (n,)),
            ("u", (n, 8)),
            ("ud", (n, 8)),
            ("udd", (n, 8)),
            ("uddd", (n, 8)),
            ("X", (n, 8, 2)),
            ("cup_p", (n, 3)),
            ("cup_normal", (n, 3)),
        ):
            arr = np.array(getattr(self, fname), dtype=float)
            if arr.shape != shape:
                raise InvalidInputError(f"TossPrimitive.{fname}: expected shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise InvalidInputError(f"TossPrimitive.{fname}: values must be finite")
            arr.setflags(write=False)
            object.__setattr__(self, fname, arr)

    @property
    def q(self) -> FloatArray:
        """Predicted joint positions (N, 8)."""
        return self.X[:, :, 0]

    @property
    def duration(self) -> float:
        """Time of the last command [s]."""
        return float(self.t[-1])

    def index_at(self, time: float) -> int:
        """Index of the command sample at or just before ``time`` [s] (clipped to the
        primitive)."""
        k = int(math.floor(float(time) / self.dt + 1e-9))
        return min(max(k, 0), self.t.size - 1)

    def command_state(self, time: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Hand-over state at the sample at or before ``time``: ``(u, ud, udd, X)`` with
        shapes (8,), (8,), (8,), (8, 2)."""
        k = self.index_at(time)
        return self.u[k].copy(), self.ud[k].copy(), self.udd[k].copy(), self.X[k].copy()


def _faa_di_bruno(Fd: list[FloatArray], zd: FloatArray) -> list[FloatArray]:
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


def vertical_rise(vz: float, *, drag_k: float, gravity: float = C.GRAVITY) -> float:
    """Apex height above the start of a ball thrown straight up at ``vz`` [m/s] under
    gravity and quadratic drag ``a = -g - k v|v|``: ``ln(1 + k vz^2/g) / (2 k)`` [m].
    ``drag_k = rho C_D A / (2 m)`` [1/m]; ``drag_k = 0`` gives ``vz^2 / (2 g)``."""
    if vz <= 0.0:
        return 0.0
    if drag_k <= 0.0:
        return vz * vz / (2.0 * gravity)
    return math.log1p(drag_k * vz * vz / gravity) / (2.0 * drag_k)


def _speed_for_rise(rise: float, *, drag_k: float, gravity: float = C.GRAVITY) -> float:
    """Inverse of :func:`vertical_rise`: launch speed [m/s] for an apex ``rise`` [m]."""
    if drag_k <= 0.0:
        return math.sqrt(2.0 * gravity * rise)
    return math.sqrt(gravity * math.expm1(2.0 * drag_k * rise) / drag_k)


def _drag_constant() -> float:
    """Quadratic drag constant ``k = rho C_D A / (2 m)`` [1/m] of the ball flight model."""
    from studio.physics import ball

    return float(ball.FlightModel().drag_constant)


def limit_violations(
    u: FloatArray, ud: FloatArray, udd: FloatArray, uddd: FloatArray, limits: JointLimits, *, q: FloatArray | None = None
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


def _toss_start(
    robot: Robot,
    side: TossSide,
    *,
    lateral: float,
    start_height: float | None,
    gantry_x: float | None,
) -> FloatArray:
    """Start configuration of a toss, derived from ``robot.q_flat``.

    The gantry's Y axis moves the cup to ``y = -lateral`` (right) or ``+lateral``
    (left); if ``gantry_x`` is given the gantry's X axis moves there and the arm (IK,
    racket orientation of ``q_flat`` kept) puts the cup back at its ``q_flat`` x; with
    ``start_height`` the arm also moves the cup centre to that height.
    """
    q = np.array(robot.q_flat, dtype=float)
    cup = robot.cup_position(q)
    R = np.array(robot.fk(q).rotation)
    y_target = -lateral if side == "right" else lateral
    q[robot.joint_names.index("gantry_y")] += y_target - cup[1]
    if gantry_x is not None or start_height is not None:
        if gantry_x is not None:
            q[robot.joint_names.index("gantry_x")] = gantry_x
        target = np.array([cup[0], y_target, cup[2] if start_height is None else start_height])
        q = _pose_ik(robot, q, target, R, joints=np.arange(2, 8))
    return robot.check_configuration(q)


def _flat_plane_basis(robot: Robot, q: FloatArray) -> FloatArray:
    """(8, 2) orthonormal joint directions (arm joints only) that move the cup in the
    vertical x-z plane without turning the racket: null space of [omega; v_y]."""
    Jc = _cup_jacobian(robot, q)
    A = np.vstack([Jc[3:6, 2:], Jc[1:2, 2:]])
    _, sv, Vt = np.linalg.svd(A)
    if sv[-1] < 1e-6 * sv[0]:
        raise InvalidInputError("make_toss: the start pose is singular for a flat vertical lift")
    basis = np.zeros((8, 2))
    basis[2:, :] = Vt[4:6].T
    return basis


def _check_clearance(robot: Robot, t: FloatArray, cup_p: FloatArray, release: Release, t_clear: float) -> None:
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
        InvalidInputError: a check fails (raise ``clear_side``/``clear_delay``).
    """
    from studio.physics import ball

    rs = robot.spec.racket
    R = rs.ball_radius
    sag = R - math.sqrt(R * R - rs.cup_rim_radius**2)
    FT, FP, FV = _free_flights(
        release.position[None, :], release.velocity[None, :], np.array([release.time]),
        max(float(t[-1]) - release.time, 1e-3), ball.DEFAULT_FLIGHT, h=5e-3,
    )  # RK4 at 5 ms: ~1e-8 m on this smooth, spinless flight
    ft, fp, fv = FT[0], FP[0], FV[0]
    sel = t > release.time
    tq = t[sel]
    tq = tq[tq <= ft[-1]]
    bp = _hermite(ft, fp, fv, tq)
    cp = cup_p[sel][: tq.size]
    k0 = int(np.searchsorted(tq, t_clear))
    if k0 < tq.size and float(bp[k0, 2] - cp[k0, 2]) <= sag:
        raise InvalidInputError(
            f"make_toss: the racket starts clearing the ball's path at {t_clear:.3f} s while the ball is still in "
            f"the cup ({(bp[k0, 2] - cp[k0, 2]) * 1e3:.1f} mm above its seat, sag {sag * 1e3:.1f} mm): raise clear_delay"
        )
    after_apex = np.arange(tq.size) >= int(np.argmax(bp[:, 2]))
    band = after_apex & (bp[:, 2] >= cp[:, 2] - 0.065) & (bp[:, 2] <= cp[:, 2] + 0.04)
    need = R + rs.cup_plate_radius + CLEAR_MARGIN
    gap = np.hypot(bp[:, 0] - cp[:, 0], bp[:, 1] - cp[:, 1])
    if np.any(band) and float(np.min(gap[band])) < need:
        k = int(np.flatnonzero(band)[np.argmin(gap[band])])
        raise InvalidInputError(
            f"make_toss: the falling ball passes {gap[k] * 1e3:.0f} mm from the cup at {tq[k]:.3f} s "
            f"(< {need * 1e3:.0f} mm): raise clear_side or start the clearing move earlier"
        )


def make_toss(
    robot: Robot,
    side: TossSide,
    *,
    rise: float = 0.35,
    lateral: float = 0.30,
    start_height: float | None = 0.04,
    gantry_x: float | None = -0.40,
    lift_acceleration: float = 18.0,
    ramp_up: float = 0.20,
    ramp_release: float = 0.16,
    ramp_stop: float = 0.20,
    hold_start: float = 0.05,
    clear_side: float = 0.08,
    clear_drop: float = 0.15,
    clear_delay: float = 0.06,
    clear_time: float = 0.40,
    duration: float = 1.4,
    dt: float = DEFAULT_DT,
    drag_k: float | None = None,
    name: str | None = None,
    check_limits: bool = True,
) -> TossPrimitive:
    """Build a toss primitive: a flat-racket upward swing that releases the ball vertically.

    Design:

    - start at rest at ``robot.q_flat`` moved sideways by the gantry (``side``,
      ``lateral``) and re-posed by the arm (``gantry_x``, ``start_height``; the racket
      orientation of ``q_flat`` is kept);
    - the cup height follows a :class:`LiftProfile` ``z(t)`` (C^2 acceleration):
      accelerate up, then decelerate faster than gravity so the ball leaves the cup
      where ``z'' = -(g + k v^2)`` (:func:`find_release`: gravity and the air drag on
      the ball) at the speed giving ``rise`` in air (drag of the ball flight model),
      and stop;
    - the arm joints move along a straight line in joint space ``q = q0 + s d``, with
      ``d`` in the null space of the racket's angular velocity and of the cup's lateral
      velocity (on the KUKA arm: A2 and A3 with A5 compensating), so the racket stays
      exactly flat and the cup moves in a vertical plane on a gentle curve; ``s = S(z)``
      (Chebyshev interpolant of the inverse of the cup height along the line). The mix
      inside that plane is solved so the arm alone moves the cup vertically at the
      release height (the gantry is then at rest there). A joint-space line uses the arm
      far better than a straight vertical Cartesian line, which exceeds the A2/A3
      acceleration and jerk limits;
    - the gantry's X axis (prismatic along world X) cancels the cup's horizontal drift
      along that curve, ``gantry_x(t) = gantry_x - (Xc(z(t)) - Xc(z_0))`` (``Xc`` the
      cup x along the line, Chebyshev in ``z``): the cup moves on the exactly vertical
      line through its start point, with zero horizontal velocity *and acceleration*
      during the lift and the stop; the whole racket stays behind the end line.
      Without it the cup accelerated ~12 m/s^2 horizontally at the release, its rim
      kept pushing the ball and its wall hit the ball ~17 ms later (see
      :func:`find_release` for the assumption this satisfies). The gantry moves
      back ~0.17 m during the lift;
    - after the release the racket clears the falling ball's path: from
      ``clear_delay`` after the release (the ball has risen out of the cup) the gantry's
      Y axis moves the racket ``clear_side`` away from the table's centre line, and
      once the lift has stopped the cup is lowered by ``clear_drop`` (rest-to-rest
      degree-9 smoothsteps over ``clear_time``, C^4). The strike planner takes over
      from the toss shortly after the release (``studio.serve.evaluate``), so this part
      only matters for continuity and for toss-only executions;
    - the commands invert the robot's joint model,
      ``u = q + (2 zeta / wn) q' + q'' / wn^2`` with exact derivatives (Faa di Bruno on
      ``S(z(t))`` and ``Xc(z(t))``), evaluated half a sample late to compensate the
      zero-order hold, so the predicted joint motion is the designed one; ``u`` is
      continuous up to acceleration with bounded jerk;
    - the release is then found with :func:`find_release` on the predicted motion and
      checked (vertical, at the designed speed, no sideways cup acceleration), and so is
      the clearance of the falling ball (:func:`_check_clearance`).

    The defaults (found by a search over start pose and profile times on the shipped
    robot) give a 0.35 m rise: release at x = -1.649 m (0.28 m behind the end line),
    z = 0.419 m, 2.68 m/s, 0.359 s after the start; apex 0.769 m 0.27 s later; the
    ball falls below z = 0.02 m 0.66 s after the release. Commands stay at <= 90 %
    of every velocity, acceleration and jerk limit (binding: gantry X jerk, which
    cancels the arm's x drift, and A5 jerk). Higher rises fail on those two limits
    and on the geometry of the joint-space line, not on A2/A3.

    Args:
        robot: the serve robot (:func:`studio.robot.model.load_robot`).
        side: ``"right"`` (cup at world ``y = -lateral``) or ``"left"`` (``y = +lateral``).
        rise: rise of the ball above the release point [m]; >= 0.16 (ITTF 2.6.2).
        lateral: distance of the cup from the robot's centre line ``y = 0`` [m].
        start_height: cup centre height at the start [m] (``None``: that of ``q_flat``);
            low (4 cm: the ball 2 cm above the table level) so that the arm has room to
            lift the ball within its limits.
        gantry_x: gantry X position at the start [m] (``None``: that of ``q_flat``);
            the arm's start pose puts the cup at the ``q_flat`` x, and the cup stays on
            that x during the lift (the gantry moves back by the arm's x drift, ~0.17 m).
        lift_acceleration: upward cup acceleration of the lift [m/s^2].
        ramp_up, ramp_release, ramp_stop, hold_start: :class:`LiftProfile` times [s].
        clear_side: sideways move of the racket (gantry Y, away from ``y = 0``) that
            clears the falling ball's path [m].
        clear_drop: lowering of the cup after the lift has stopped [m].
        clear_delay: start of the sideways move after the (designed) release [s]; the
            ball must have risen out of the cup by then.
        clear_time: duration of the sideways move and of the lowering [s].
        duration: length of the primitive [s] (covers the ball's fall back to about
            table level).
        dt: command period [s].
        drag_k: ball drag constant [1/m] (default: the flight model's).
        name: identifier (default ``"toss_<side>"``).
        check_limits: raise if a joint limit is violated (``False`` only to explore
            designs: use :func:`limit_violations` on the result).

    Raises:
        InvalidInputError: bad argument, IK failure, no flat line releasing vertically
            at the release height, a joint limit violated (the message lists them),
            racket tilt during the lift above :data:`MAX_FLAT_TILT_DEG`, no release, a
            non-vertical one or one with the cup accelerating sideways, a racket that
            does not clear the falling ball's path, or a ball in the cup below the
            playing surface / in front of the end line.
    """
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"make_toss: side must be one of {TOSS_SIDES}, got {side!r}")
    for label, val, lo in (
        ("rise", rise, C.TOSS_MIN_RISE),
        ("lateral", lateral, 0.0),
        ("dt", dt, 1e-9),
        ("clear_side", clear_side, 0.0),
        ("clear_drop", clear_drop, 0.0),
        ("clear_delay", clear_delay, 0.0),
        ("clear_time", clear_time, 1e-3),
    ):
        if not (math.isfinite(val) and val >= lo):
            raise InvalidInputError(f"make_toss: {label} must be finite and >= {lo}, got {val}")
    k_drag = _drag_constant() if drag_k is None else float(drag_k)
    v_target = _speed_for_rise(rise, drag_k=k_drag)

    q_start = _toss_start(robot, side, lateral=lateral, start_height=start_height, gantry_x=gantry_x)
    R_flat = np.array(robot.fk(q_start).rotation)
    tilt0 = math.degrees(math.acos(min(1.0, float(R_flat[2, 2]))))
    if tilt0 > 0.5:
        raise InvalidInputError(f"make_toss: the start pose is not flat (racket normal tilted {tilt0:.2f} deg)")
    z0 = float(robot.cup_position(q_start)[2])

    # Height profile: its release (a = -(g + k v^2), see find_release) is at height h_rel
    # above the start, speed v_target.
    g_release = C.GRAVITY + k_drag * v_target**2
    profile = LiftProfile.design(
        v_target,
        lift_acceleration=lift_acceleration,
        ramp_up=ramp_up,
        ramp_release=ramp_release,
        ramp_stop=ramp_stop,
        hold_start=hold_start,
        gravity=g_release,
    )
    if profile.duration + 0.05 > duration:
        raise InvalidInputError(f"make_toss: duration {duration} s shorter than the lift ({profile.duration:.3f} s)")
    t_rel_design = profile.release_estimate(g_release)[0]
    h_rel = float(profile.evaluate([t_rel_design])[0, 0])
    travel = profile.travel
    if clear_drop > travel:
        raise InvalidInputError(f"make_toss: clear_drop {clear_drop} m exceeds the lift travel {travel:.3f} m")
    if max(t_rel_design + clear_delay, profile.duration) + clear_time + 0.05 > duration:
        raise InvalidInputError(f"make_toss: duration {duration} s too short for the clearing move after the release")

    # Joint-space line q(s) = q_start + s d(psi) in the flat, vertical-plane directions;
    # psi puts the point where the cup moves vertically at the release height.
    basis = _flat_plane_basis(robot, q_start)
    s_grid = np.linspace(0.0, 2.0, 201)

    def line(psi: float) -> tuple[FloatArray, FloatArray]:
        d = basis @ np.array([math.cos(psi), math.sin(psi)])
        P = np.array([robot.cup_position(q_start + s_i * d) for s_i in s_grid])
        return d, P

    def vertical_height(psi: float) -> tuple[float, float] | None:
        """(height of the first vertical-velocity point above the start, min dz/ds up
        to the top of the lift) along the line, or None (no such point / z not monotonic)."""
        d, P = line(psi)
        dP = np.gradient(P, s_grid, axis=0)
        if dP[0, 2] < 0.0:
            return None
        flips = np.flatnonzero(np.sign(dP[1:, 0]) != np.sign(dP[:-1, 0]))
        top = np.flatnonzero(P[:, 2] - z0 >= travel + 0.005)
        if flips.size == 0 or top.size == 0:
            return None
        i_top = int(top[0])
        if float(np.min(dP[: i_top + 1, 2])) <= 0.05:
            return None
        i = int(flips[0])
        # Linear interpolation of the flip of dx/ds.
        w = dP[i, 0] / (dP[i, 0] - dP[i + 1, 0])
        return float((1 - w) * P[i, 2] + w * P[i + 1, 2] - z0), float(np.min(dP[: i_top + 1, 2]))

    psis = np.linspace(-math.pi, math.pi, 73)
    heights = [vertical_height(float(p_)) for p_ in psis]
    brackets = []
    for k in range(len(psis) - 1):
        h0, h1 = heights[k], heights[k + 1]
        if h0 is not None and h1 is not None and (h0[0] - h_rel) * (h1[0] - h_rel) <= 0.0:
            brackets.append((min(h0[1], h1[1]), float(psis[k]), float(psis[k + 1])))
    if not brackets:
        reach = max((h[0] for h in heights if h is not None), default=0.0)
        raise InvalidInputError(
            f"make_toss: no flat joint-space lift from this start pose moves the cup vertically at the release "
            f"height {h_rel:.3f} m above the start (highest: {reach:.3f} m): raise lift_acceleration, shorten "
            "ramp_release or lower the rise"
        )
    _, lo_psi, hi_psi = max(brackets)  # the steepest lift (largest min dz/ds)
    f_lo = vertical_height(lo_psi)
    assert f_lo is not None
    for _ in range(40):
        mid = 0.5 * (lo_psi + hi_psi)
        f_mid = vertical_height(mid)
        if f_mid is None:
            break
        if (f_mid[0] - h_rel) * (f_lo[0] - h_rel) <= 0.0:
            hi_psi = mid
        else:
            lo_psi, f_lo = mid, f_mid
    psi = 0.5 * (lo_psi + hi_psi)
    d = basis @ np.array([math.cos(psi), math.sin(psi)])

    # Inverse map s = S(z) as a Chebyshev interpolant over the lift heights, and the
    # cup's x along the line (gantry fixed) as a function of the height, Xc(z).
    z_lo, z_hi = z0 - 1e-3, z0 + travel + 2e-3
    n_nodes = 40
    z_nodes = z_lo + (np.sort(np.polynomial.chebyshev.chebpts1(n_nodes)) + 1.0) * 0.5 * (z_hi - z_lo)
    s_nodes = np.empty(n_nodes)
    x_nodes = np.empty(n_nodes)
    s_prev = 0.0
    for i, zt in enumerate(z_nodes):
        s_i = s_prev
        for _ in range(50):
            qi = q_start + s_i * d
            err = zt - float(robot.cup_position(qi)[2])
            if abs(err) < 1e-13:
                break
            s_i += err / float(_cup_jacobian(robot, qi)[2] @ d)
        else:
            raise InvalidInputError(f"make_toss: cannot reach cup height {zt:.3f} m along the lift")
        s_nodes[i] = s_prev = s_i
        x_nodes[i] = float(robot.cup_position(q_start + s_i * d)[0])
    S = np.polynomial.Chebyshev.fit(z_nodes, s_nodes, n_nodes - 1, domain=[z_lo, z_hi])
    Xc = np.polynomial.Chebyshev.fit(z_nodes, x_nodes, n_nodes - 1, domain=[z_lo, z_hi])
    S_d = [S.deriv(m) if m else S for m in range(6)]
    Xc_d = [Xc.deriv(m) if m else Xc for m in range(6)]
    for zc in 0.5 * (z_nodes[1:] + z_nodes[:-1]):
        cup_c = robot.cup_position(q_start + float(S(zc)) * d)
        e = max(abs(float(cup_c[2]) - zc), abs(float(cup_c[0]) - float(Xc(zc))))
        if e > 1e-8:
            raise InvalidInputError(f"make_toss: path interpolant inaccurate at z = {zc:.3f} m ({e:.1e} m)")

    # Joint motion: arm on the line, q_arm(t) = q_start + S(z(t)) d; gantry X cancels the
    # cup's x drift of the arm, gx(t) = gantry_x - (Xc(z(t)) - Xc(z0)), so the cup moves
    # on the vertical line through its start point (zero horizontal velocity and
    # acceleration during the whole lift and stop); then gantry Y and a descent clear the
    # ball's path.
    ix, iy = robot.joint_names.index("gantry_x"), robot.joint_names.index("gantry_y")
    wn = np.asarray(robot.dynamics.wn, dtype=float)
    zeta = np.asarray(robot.dynamics.zeta, dtype=float)
    c1 = 2.0 * zeta / wn
    c2 = 1.0 / wn**2
    n_samples = int(round(duration / dt)) + 1
    t = np.arange(n_samples) * dt
    X0 = np.stack([q_start, np.zeros(8)], axis=1)

    te = t + 0.5 * dt  # half-sample lead compensates the zero-order hold
    zd = profile.evaluate(te)
    zd[0] += z0
    t_clear = t_rel_design + clear_delay
    zd = zd + _smoothstep9_move(te, max(t_clear, profile.duration), clear_time, -clear_drop)
    sd = _faa_di_bruno([S_d[m](zd[0]) for m in range(6)], zd)  # s and its 5 time derivatives
    xd = _faa_di_bruno([Xc_d[m](zd[0]) for m in range(6)], zd)  # arm-only cup x and derivatives
    yd = _smoothstep9_move(te, t_clear, clear_time, (-1.0 if side == "right" else 1.0) * clear_side)
    qd = [sd[m][:, None] * d[None, :] for m in range(6)]
    for m in range(6):
        qd[m][:, ix] = -xd[m] + (float(Xc(z0)) if m == 0 else 0.0)
        qd[m][:, iy] = yd[m]
    qd[0] = qd[0] + q_start[None, :]
    u = qd[0] + c1 * qd[1] + c2 * qd[2]
    ud = qd[1] + c1 * qd[2] + c2 * qd[3]
    udd = qd[2] + c1 * qd[3] + c2 * qd[4]
    uddd = qd[3] + c1 * qd[4] + c2 * qd[5]
    X = robot.dynamics.simulate(u, dt, X0)

    cup_p = np.empty((n_samples, 3))
    rot = np.empty((n_samples, 3, 3))
    for k in range(n_samples):
        qk = X[k, :, 0]
        cup_p[k] = robot.cup_position(qk)
        rot[k] = robot.fk(qk).rotation
    normals = rot[:, :, 2].copy()
    release = find_release(t, cup_p, normals, rotation=rot, drag_k=k_drag)
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

    problems = limit_violations(u, ud, udd, uddd, robot.limits, q=X[:, :, 0]) if check_limits else []
    if problems:
        raise InvalidInputError("make_toss: toss violates the joint limits: " + "; ".join(problems))
    _check_clearance(robot, t, cup_p, release, t_clear)
    lift = t <= release.time
    tilt = np.degrees(np.arccos(np.clip(normals[lift, 2], -1.0, 1.0)))
    if float(np.max(tilt)) > MAX_FLAT_TILT_DEG:
        raise InvalidInputError(f"make_toss: racket tilts {float(np.max(tilt)):.2f} deg during the lift")
    if float(np.min(cup_p[lift, 2])) <= C.BALL_RADIUS:
        raise InvalidInputError("make_toss: the ball in the cup goes below the playing surface level")
    if float(np.max(cup_p[lift, 0])) >= -C.TABLE_LENGTH / 2 - C.BALL_RADIUS:
        raise InvalidInputError("make_toss: the ball in the cup is not behind the end line")
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


# =====================================================================================
# Recordings (synthetic or real) and their CSV format
# =====================================================================================

MIN_SAMPLES_PER_TOSS: Final[int] = 20
"""Fewest samples a recorded toss must have (0.1 s at 200 Hz)."""

CSV_COLUMNS: Final[tuple[str, ...]] = ("toss_id", "t", "x", "y", "z")
"""Required columns of a toss recording CSV file."""


@dataclass(frozen=True, eq=False)
class TossRecording:
    """One recorded toss: ball centre positions from a tracking system.

    Times are on the recording's own clock (any origin); positions in the world frame.
    """

    toss_id: str
    """Identifier of the toss, unique within its :class:`TossRecordings`."""
    t: FloatArray
    """Sample times (M,) [s], strictly increasing, on the recording clock."""
    p: FloatArray
    """Ball centre positions (M, 3) [m], world frame."""

    def __post_init__(self) -> None:
        if not self.toss_id or any(ch in self.toss_id for ch in ",\n\r\"") or self.toss_id != self.toss_id.strip():
            raise InvalidInputError(f"TossRecording: toss_id {self.toss_id!r} must be non-empty, without commas, quotes, newlines or surrounding spaces")
        t = np.array(self.t, dtype=float)
        p = np.array(self.p, dtype=float)
        if t.ndim != 1 or p.shape != (t.size, 3):
            raise InvalidInputError(f"TossRecording {self.toss_id!r}: t must be (M,) and p (M, 3), got {t.shape}, {p.shape}")
        if t.size < MIN_SAMPLES_PER_TOSS:
            raise InvalidInputError(f"TossRecording {self.toss_id!r}: {t.size} samples < {MIN_SAMPLES_PER_TOSS}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise InvalidInputError(f"TossRecording {self.toss_id!r}: non-finite values")
        if np.any(np.diff(t) <= 0.0):
            k = int(np.argmax(np.diff(t) <= 0.0))
            raise InvalidInputError(f"TossRecording {self.toss_id!r}: times not strictly increasing at sample {k + 1}")
        t.setflags(write=False)
        p.setflags(write=False)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "p", p)


@dataclass(frozen=True, eq=False)
class TossTruth:
    """What really happened in a synthetic toss (unknown for real recordings)."""

    clock_offset: float
    """Recording clock minus command clock [s]."""
    release_time: float
    """Release time on the command clock [s] (after timing jitter)."""
    release_p: FloatArray
    """Ball position at release (3,) [m]."""
    release_v: FloatArray
    """Ball velocity at release (3,) [m/s] (after arm vibration)."""
    wind: FloatArray
    """Air velocity during the flight (3,) [m/s]."""


@dataclass(frozen=True, eq=False)
class TossRecordings:
    """A set of recorded executions of one toss primitive."""

    recordings: tuple[TossRecording, ...]
    """The tosses, in recording order; ids are unique."""
    truth: tuple[TossTruth, ...] | None = None
    """Ground truth per toss for synthetic recordings (same order), else ``None``."""

    def __post_init__(self) -> None:
        recs = tuple(self.recordings)
        if not recs:
            raise InvalidInputError("TossRecordings: no recordings")
        ids = [r.toss_id for r in recs]
        if len(set(ids)) != len(ids):
            dup = next(i for i in ids if ids.count(i) > 1)
            raise InvalidInputError(f"TossRecordings: duplicate toss_id {dup!r}")
        if self.truth is not None and len(self.truth) != len(recs):
            raise InvalidInputError("TossRecordings: truth must have one entry per recording")
        object.__setattr__(self, "recordings", recs)
        if self.truth is not None:
            object.__setattr__(self, "truth", tuple(self.truth))

    def __len__(self) -> int:
        return len(self.recordings)


def save_recordings_csv(path: str | Path, recordings: TossRecordings, *, decimals: int = 6, comment: str | None = None) -> None:
    """Write recordings as CSV (format of :func:`load_recordings_csv`).

    Args:
        path: output file; written atomically (temporary file, then rename).
        recordings: the tosses to write (the ground truth is not written).
        decimals: digits after the decimal point for t, x, y, z (4 = 0.1 mm / 0.1 ms).
        comment: optional text written as ``#`` comment lines before the header.
    """
    path = Path(path)
    if not (isinstance(decimals, int) and 1 <= decimals <= 12):
        raise InvalidInputError(f"save_recordings_csv: decimals must be an int in [1, 12], got {decimals!r}")
    lines: list[str] = []
    if comment:
        lines.extend(f"# {line}".rstrip() for line in comment.splitlines())
    lines.append(",".join(CSV_COLUMNS))
    fmt = f"{{:.{decimals}f}}"
    for rec in recordings.recordings:
        for ti, pi in zip(rec.t, rec.p):
            lines.append(",".join([rec.toss_id, fmt.format(ti), fmt.format(pi[0]), fmt.format(pi[1]), fmt.format(pi[2])]))
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def load_recordings_csv(path: str | Path) -> TossRecordings:
    """Read toss recordings from a CSV file.

    Format (UTF-8 text):

    - optional comment lines starting with ``#`` and blank lines anywhere (ignored);
    - a header line naming the columns; it must contain ``toss_id,t,x,y,z`` (any
      order). Extra columns (e.g. a tracker's confidence) are allowed and ignored;
    - one row per sample: ``toss_id`` (any text without commas/quotes), ``t`` time [s]
      on any clock (each toss may use its own origin), ``x, y, z`` ball centre [m] in
      the world frame (origin at the table centre, +X towards the receiver, +Z up).
      Values must be finite decimal numbers.
    - rows of a toss need not be contiguous, but its times must strictly increase in
      file order; each toss needs at least :data:`MIN_SAMPLES_PER_TOSS` samples.

    Raises:
        DataFileError: unreadable file or any violation above; the message names the
            file, the line number (1-based) and the column.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFileError(path, f"cannot read: {exc}") from exc
    header: list[str] | None = None
    col: dict[str, int] = {}
    data: dict[str, tuple[list[float], list[list[float]], int]] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        cells = [c.strip() for c in line.split(",")]
        if header is None:
            header = cells
            missing = [c for c in CSV_COLUMNS if c not in header]
            if missing:
                raise DataFileError(
                    path, f"line {lineno}: header {line!r} lacks column(s) {', '.join(missing)} (need {','.join(CSV_COLUMNS)})"
                )
            dups = sorted({c for c in header if header.count(c) > 1})
            if dups:
                raise DataFileError(path, f"line {lineno}: duplicate column(s) {', '.join(dups)} in the header")
            col = {c: header.index(c) for c in CSV_COLUMNS}
            continue
        if len(cells) != len(header):
            raise DataFileError(path, f"line {lineno}: {len(cells)} fields, the header has {len(header)}")
        tid = cells[col["toss_id"]]
        if not tid or '"' in tid:
            raise DataFileError(path, f"line {lineno}, column toss_id: empty or quoted id {tid!r}")
        vals: list[float] = []
        for name in ("t", "x", "y", "z"):
            cell = cells[col[name]]
            try:
                v = float(cell)
            except ValueError:
                raise DataFileError(path, f"line {lineno}, column {name}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                raise DataFileError(path, f"line {lineno}, column {name}: {cell!r} is not finite")
            vals.append(v)
        ts, ps, last_line = data.setdefault(tid, ([], [], lineno))
        if ts and vals[0] <= ts[-1]:
            raise DataFileError(
                path,
                f"line {lineno}, column t: time {vals[0]!r} of toss {tid!r} not after {ts[-1]!r} (line {last_line}); "
                "times must strictly increase within a toss",
            )
        ts.append(vals[0])
        ps.append(vals[1:])
        data[tid] = (ts, ps, lineno)
    if header is None:
        raise DataFileError(path, f"no header line (expected {','.join(CSV_COLUMNS)})")
    if not data:
        raise DataFileError(path, "no data rows")
    recs = []
    for tid, (ts, ps, last_line) in data.items():
        if len(ts) < MIN_SAMPLES_PER_TOSS:
            raise DataFileError(
                path, f"toss {tid!r} (last row line {last_line}): {len(ts)} samples, at least {MIN_SAMPLES_PER_TOSS} needed"
            )
        recs.append(TossRecording(toss_id=tid, t=np.array(ts), p=np.array(ps)))
    return TossRecordings(recordings=tuple(recs))


# =====================================================================================
# Synthetic recordings
# =====================================================================================


@dataclass(frozen=True, slots=True)
class TossNoise:
    """Randomness of repeated executions of one toss and of their measurement.

    Defaults: chosen so that 15-20 tosses spread by about +/-1 cm 0.7 s after the lift,
    as the paper reports (its Fig. "toss spread"), with a +/-3 mm tracking accuracy.
    """

    vibration: float = 0.008
    """Std. dev. of the random release-velocity perturbation per axis [m/s] (arm
    vibration; isotropic)."""
    release_jitter: float = 0.001
    """Std. dev. of the release time around the contact-force crossing [s]."""
    wind: float = 0.07
    """Std. dev. of the horizontal air velocity per axis [m/s] (small room air flows;
    constant during a toss; enters the drag as the relative air velocity)."""
    wind_vertical: float = 0.02
    """Std. dev. of the vertical air velocity [m/s]."""
    measurement: float = 0.0015
    """Std. dev. of the tracking error per axis [m]: the paper's +/-3 mm read as 2 sigma."""
    camera_rate: float = 200.0
    """Camera frame rate [Hz]; each recording has a random frame phase."""
    visible_before_release: tuple[float, float] = (0.25, 0.35)
    """Range [s] (uniform) of how long before the release the recording starts: the
    ball riding in the cup is recorded too."""
    clock_offset: tuple[float, float] = (10.0, 1000.0)
    """Range [s] (uniform) of the recording clock's offset from the command clock."""
    t_max: float = 1.5
    """Latest end of a recording on the command clock [s]."""
    end_height: float = -0.30
    """A recording stops when the ball falls below this height [m]. Below the table
    level (the ball is behind the end line, nothing is in the way) so that the
    recordings cover 0.7 s after the lift like the paper's spread figure; a serve must
    strike the ball above the table level (ITTF 2.6.4)."""

    def __post_init__(self) -> None:
        for name in ("vibration", "release_jitter", "wind", "wind_vertical", "measurement"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise InvalidInputError(f"TossNoise.{name} must be finite and >= 0, got {v}")
        if not math.isfinite(self.end_height):
            raise InvalidInputError(f"TossNoise.end_height must be finite, got {self.end_height}")
        for name in ("camera_rate", "t_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise InvalidInputError(f"TossNoise.{name} must be finite and > 0, got {v}")
        for name in ("visible_before_release", "clock_offset"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise InvalidInputError(f"TossNoise.{name} must be a finite range (lo <= hi), got {(lo, hi)}")
        if self.visible_before_release[0] < 0.0:
            raise InvalidInputError("TossNoise.visible_before_release must be >= 0")

    @classmethod
    def none(cls) -> TossNoise:
        """No randomness except the camera sampling (noise-free reference)."""
        return cls(vibration=0.0, release_jitter=0.0, wind=0.0, wind_vertical=0.0, measurement=0.0, clock_offset=(0.0, 0.0))


def _hermite(t_s: FloatArray, p_s: FloatArray, v_s: FloatArray, tq: FloatArray) -> FloatArray:
    """Cubic Hermite interpolation of positions ``p_s`` (M, 3) with velocities ``v_s``
    at sample times ``t_s`` (M,), evaluated at ``tq`` (Q,) inside ``[t_s[0], t_s[-1]]``."""
    i = np.clip(np.searchsorted(t_s, tq, side="right") - 1, 0, t_s.size - 2)
    h = t_s[i + 1] - t_s[i]
    s = ((tq - t_s[i]) / h)[:, None]
    h = h[:, None]
    h00 = 2 * s**3 - 3 * s**2 + 1
    h10 = s**3 - 2 * s**2 + s
    h01 = -2 * s**3 + 3 * s**2
    h11 = s**3 - s**2
    return h00 * p_s[i] + h10 * h * v_s[i] + h01 * p_s[i + 1] + h11 * h * v_s[i + 1]


def _free_flights(
    p0: FloatArray,
    v0: FloatArray,
    t0: FloatArray,
    duration: float,
    flight: object,
    *,
    wind: FloatArray | None = None,
    h: float = 5e-4,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Batch of spinless free flights: RK4 (step ``h`` [s]) on the ball model's
    equations (:meth:`studio.physics.ball.FlightModel.acceleration`: gravity and quadratic drag;
    no Magnus force without spin). The drag acts on the velocity relative to the air
    (``wind``, uniform and constant). No contacts: the toss flies behind the end line.

    Args:
        p0, v0: initial positions and velocities (C, 3); t0: start times (C,) [s].
        duration: flight time [s].
        flight: a :class:`studio.physics.ball.FlightModel`.
        wind: air velocities (C, 3) [m/s] (default still air).

    Returns:
        times (C, M), positions (C, M, 3), velocities (C, M, 3).
    """
    n = int(math.ceil(duration / h)) + 1
    w = np.zeros_like(v0)
    air = np.zeros_like(v0) if wind is None else np.asarray(wind, dtype=float)
    model_acc = flight.acceleration  # type: ignore[attr-defined]

    def acc(p: FloatArray, v: FloatArray, w: FloatArray) -> FloatArray:
        return model_acc(p, v - air, w)

    P = np.empty((p0.shape[0], n, 3))
    V = np.empty_like(P)
    p, v = np.array(p0, dtype=float), np.array(v0, dtype=float)
    for i in range(n):
        P[:, i], V[:, i] = p, v
        k1v = acc(p, v, w)
        k2v = acc(p, v + 0.5 * h * k1v, w)
        k3v = acc(p, v + 0.5 * h * k2v, w)
        k4v = acc(p, v + h * k3v, w)
        p = p + h * (v + h / 6.0 * (k1v + k2v + k3v))
        v = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
    T = t0[:, None] + h * np.arange(n)[None, :]
    return T, P, V


def _flight(
    p0: FloatArray, v0: FloatArray, t0: float, t_end: float, wind: FloatArray, flight: object
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One spinless flight from ``(p0, v0)`` at ``t0`` to ``t_end`` [s] in a uniform,
    constant ``wind`` (3,) [m/s] (see :func:`_free_flights`).

    Returns:
        t (M,), p (M, 3), v (M, 3) sampled every millisecond.
    """
    T, P, V = _free_flights(
        np.asarray(p0, dtype=float)[None, :],
        np.asarray(v0, dtype=float)[None, :],
        np.array([t0]),
        max(t_end - t0, 1e-3),
        flight,
        wind=np.asarray(wind, dtype=float)[None, :],
        h=1e-3,
    )
    return T[0], P[0], V[0]


def nominal_ball_path(
    primitive: TossPrimitive, *, flight: object | None = None, end_height: float = 0.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Noise-free ball path of a toss on the command grid: in the cup until the
    predicted release, then free flight (still air, no spin) until the ball falls
    below ``end_height`` [m] or the primitive ends.

    Returns:
        t (M,), p (M, 3) [m], v (M, 3) [m/s] on ``primitive.t[:M]``.
    """
    from studio.physics import ball

    fl = ball.DEFAULT_FLIGHT if flight is None else flight
    rel = primitive.release
    t = primitive.t
    v_cup = np.gradient(primitive.cup_p, t, axis=0, edge_order=2)
    ft, fp, fv = _flight(rel.position, rel.velocity, rel.time, float(t[-1]), np.zeros(3), fl)
    after = t > rel.time
    tq = t[after]
    tq = tq[tq <= ft[-1]]
    p = np.concatenate([primitive.cup_p[~after], _hermite(ft, fp, fv, tq)])
    v = np.concatenate([v_cup[~after], np.stack([np.interp(tq, ft, fv[:, j]) for j in range(3)], axis=1)])
    below = np.flatnonzero((p[:, 2] < end_height) & (np.arange(len(p)) > np.count_nonzero(~after)))
    m = int(below[0]) if below.size else len(p)
    return t[:m].copy(), p[:m], v[:m]


def simulate_tosses(
    robot: Robot,
    primitive: TossPrimitive,
    n: int,
    rng: np.random.Generator,
    *,
    noise: TossNoise = TossNoise(),
    flight: object | None = None,
    id_prefix: str | None = None,
) -> TossRecordings:
    """Execute a toss ``n`` times in simulation and record the ball like a camera would.

    Per toss: the primitive's commands run through ``robot.dynamics`` (predicted joint
    motion; the same every time), the ball rides in the cup and leaves it at the
    :func:`find_release` instant plus a random jitter, with the cup's velocity plus a
    random arm-vibration perturbation; it then flies (drag relative to a random
    constant air flow, no spin; the equations of :class:`studio.physics.ball.FlightModel`)
    until it falls below
    ``noise.end_height`` or ``noise.t_max``. The camera samples it at
    ``noise.camera_rate`` with a random phase, from a random time before the release,
    adds Gaussian tracking noise and stamps the samples with its own clock (a random
    offset from the command clock).

    Args:
        robot: the robot (its joint dynamics and kinematics give the cup path).
        primitive: the toss primitive to execute.
        n: number of tosses (>= 1).
        rng: random generator (use a seeded one for reproducible data).
        noise: the randomness (:class:`TossNoise`).
        flight: ball flight model (default :data:`studio.physics.ball.DEFAULT_FLIGHT`).
        id_prefix: toss ids are ``f"{id_prefix}_{k:02d}"`` (default: the primitive name).

    Returns:
        :class:`TossRecordings` with the ground truth of every toss.
    """
    from studio.physics import ball

    if not (isinstance(n, int) and n >= 1):
        raise InvalidInputError(f"simulate_tosses: n must be an int >= 1, got {n!r}")
    fl = ball.DEFAULT_FLIGHT if flight is None else flight
    t = primitive.t
    X = robot.dynamics.simulate(primitive.u, primitive.dt, primitive.X[0])
    cup = np.empty((t.size, 3))
    rot = np.empty((t.size, 3, 3))
    for k in range(t.size):
        cup[k] = robot.cup_position(X[k, :, 0])
        rot[k] = robot.fk(X[k, :, 0]).rotation
    cup_v = np.gradient(cup, t, axis=0, edge_order=2)
    rel = find_release(t, cup, rot[:, :, 2], rotation=rot, gravity=fl.gravity, drag_k=fl.drag_constant)
    if rel is None:
        raise InvalidInputError(f"simulate_tosses: the ball never leaves the cup in toss {primitive.name!r}")
    prefix = id_prefix or primitive.name
    frame = 1.0 / noise.camera_rate
    # Random draws, toss by toss (fixed order: reproducible for a seed).
    t_rel = np.empty(n)
    v_dev = np.empty((n, 3))
    wind = np.empty((n, 3))
    t_start = np.empty(n)
    phase = np.empty(n)
    offset = np.empty(n)
    for k in range(n):
        t_rel[k] = np.clip(rel.time + noise.release_jitter * rng.standard_normal(), t[1], t[-2])
        v_dev[k] = noise.vibration * rng.standard_normal(3)
        wind[k] = [noise.wind * rng.standard_normal(), noise.wind * rng.standard_normal(), noise.wind_vertical * rng.standard_normal()]
        t_start[k] = max(0.0, t_rel[k] - rng.uniform(*noise.visible_before_release))
        phase[k] = rng.uniform(0.0, frame)
        offset[k] = rng.uniform(*noise.clock_offset)
    p_rel = _hermite(t, cup, cup_v, t_rel)
    v_rel = np.stack([np.interp(t_rel, t, cup_v[:, j]) for j in range(3)], axis=1) + v_dev
    FT, FP, FV = _free_flights(p_rel, v_rel, t_rel, noise.t_max - float(np.min(t_rel)), fl, wind=wind, h=1e-3)
    recs: list[TossRecording] = []
    truths: list[TossTruth] = []
    for k in range(n):
        tc = t_start[k] + phase[k] + frame * np.arange(int((noise.t_max - t_start[k] - phase[k]) / frame) + 1)
        tc = tc[tc <= noise.t_max]
        pc = np.empty((tc.size, 3))
        inside = tc < t_rel[k]
        pc[inside] = _hermite(t, cup, cup_v, tc[inside])
        pc[~inside] = _hermite(FT[k], FP[k], FV[k], tc[~inside])
        falling = np.flatnonzero((pc[:, 2] < noise.end_height) & ~inside)
        if falling.size:
            tc, pc = tc[: falling[0]], pc[: falling[0]]
        pc = pc + noise.measurement * rng.standard_normal(pc.shape)
        recs.append(TossRecording(toss_id=f"{prefix}_{k:02d}", t=tc + offset[k], p=pc))
        truths.append(
            TossTruth(clock_offset=float(offset[k]), release_time=float(t_rel[k]), release_p=p_rel[k], release_v=v_rel[k], wind=wind[k])
        )
    return TossRecordings(recordings=tuple(recs), truth=tuple(truths))


# =====================================================================================
# Toss model: alignment, mean path, t_lift, spread
# =====================================================================================

SMOOTHING_WINDOW: Final[float] = 0.065
"""Savitzky-Golay window [s] of the per-recording smoothing (13 frames at 200 Hz)."""

SMOOTHING_ORDER: Final[int] = 3
"""Savitzky-Golay polynomial order."""

LIFT_SEARCH: Final[tuple[float, float]] = (-0.03, 0.05)
"""Range [s] around the rough release estimate searched for ``t_lift``."""

LIFT_FIT_WINDOW: Final[tuple[float, float]] = (0.10, 0.25)
"""Data used by the ``t_lift`` fit [s]: from this long before the earliest candidate
to this long after the latest one."""

LOCAL_FIT_HALF_WINDOW: Final[float] = 0.06
"""Half width [s] of the window of a recording's own samples from which its ball state
at a time in free flight is fitted (:meth:`TossModel.recorded_state_at`): 25 frames at
200 Hz. With the +/-1.5 mm tracking noise of :class:`TossNoise` the fitted position
scatters by ~0.5 mm and the velocity by ~9 mm/s per axis (the Savitzky-Golay velocity
just after the lift: 46-78 mm/s); the drag's change over the window biases the
velocity of every toss alike by ~2 mm/s."""

LOCAL_FIT_ORDER: Final[int] = 2
"""Polynomial order of that local fit (free flight: about constant acceleration)."""

LOCAL_FIT_LIFT_MARGIN: Final[float] = 0.015
"""The local fit window starts at least this long after ``t_lift`` [s], so that it
holds free flight only (``t_lift`` scatters by ~2.5 ms, the release by ~1 ms)."""

LOCAL_FIT_MIN_SAMPLES: Final[int] = 8
"""Fewest recorded samples a local fit window must hold, else the toss is refused as
not covering the time."""

BACK_FLIGHT_STEP: Final[float] = 0.025
"""Longest RK4 step [s] of the spinless flight integrated back from a recorded state
(:meth:`TossModel.recorded_start_state`): :func:`studio.physics.ball.simulate`'s forward flight
then meets the recorded state within 1e-6 m (0.01 s: 1e-7 m, 2.5 times the cost)."""


def _local_fit_state(
    t: FloatArray, p: FloatArray, time: float, span: tuple[float, float], *, half_window: float, order: int
) -> tuple[FloatArray, FloatArray]:
    """Ball position [m] and velocity [m/s] (3,) at ``time`` [s] from a least-squares
    polynomial (``order``) fitted per axis to the recorded samples ``t`` (M,) [s],
    ``p`` (M, 3) [m] in ``[time - half_window, time + half_window]``.

    Where that window leaves ``span`` = (lo, hi) [s] (free flight covered by the
    recording) it is shifted inside it (nearest covered window, same width), so near
    the lift or the recording's end the fit is one-sided; ``time`` itself must lie in
    ``span`` (no extrapolation).

    Raises:
        InvalidInputError: ``time`` outside ``span``, ``span`` narrower than the window,
            or fewer than :data:`LOCAL_FIT_MIN_SAMPLES` samples in it.
    """
    lo, hi = span
    if not (lo - 1e-9 <= time <= hi + 1e-9):
        raise InvalidInputError(f"time {time:.4f} s is not covered by the recording's free flight [{lo:.4f}, {hi:.4f}] s")
    if hi - lo < 2.0 * half_window:
        raise InvalidInputError(f"the recording's free flight [{lo:.4f}, {hi:.4f}] s is shorter than the {2 * half_window:.3f} s fit window")
    w_lo = min(max(time - half_window, lo), hi - 2.0 * half_window)
    sel = (t >= w_lo - 1e-9) & (t <= w_lo + 2.0 * half_window + 1e-9)
    if np.count_nonzero(sel) < max(LOCAL_FIT_MIN_SAMPLES, order + 2):
        raise InvalidInputError(
            f"only {np.count_nonzero(sel)} recorded samples in [{w_lo:.4f}, {w_lo + 2 * half_window:.4f}] s "
            f"(need {LOCAL_FIT_MIN_SAMPLES}): the recording does not cover {time:.4f} s"
        )
    coef = np.polynomial.polynomial.polyfit(t[sel] - time, p[sel], order)  # (order + 1, 3)
    return coef[0].copy(), coef[1].copy()


def _spinless_flight(p: FloatArray, v: FloatArray, t0: float, t1: float, flight: object, *, step: float = BACK_FLIGHT_STEP) -> tuple[FloatArray, FloatArray]:
    """Positions [m] and velocities [m/s] (C, 3) at ``t1`` [s] of spinless flights from
    ``p``, ``v`` (C, 3) at ``t0`` [s] in still air: classic RK4 on the flight model's
    scalar derivative (``flight.scalar_derivative()``, a :class:`studio.physics.ball.FlightModel`;
    the same equations as its ``acceleration``, on Python floats: a single state costs
    ~0.2 ms instead of ~3 ms with numpy) with equal steps of at most ``step`` [s];
    ``t1 < t0`` integrates backwards in time."""
    n = max(int(math.ceil(abs(t1 - t0) / step - 1e-9)), 1)
    h = (t1 - t0) / n
    deriv = flight.scalar_derivative()  # type: ignore[attr-defined]
    out = np.empty((len(p), 6))
    for row, (p_i, v_i) in enumerate(zip(np.asarray(p, dtype=float), np.asarray(v, dtype=float), strict=True)):
        y = [*p_i.tolist(), *v_i.tolist(), 0.0, 0.0, 0.0]
        for _ in range(n):
            k1 = deriv(y)
            k2 = deriv([a + 0.5 * h * b for a, b in zip(y, k1)])
            k3 = deriv([a + 0.5 * h * b for a, b in zip(y, k2)])
            k4 = deriv([a + h * b for a, b in zip(y, k3)])
            y = [a + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4) for a, b1, b2, b3, b4 in zip(y, k1, k2, k3, k4)]
        out[row] = y[:6]
    return out[:, :3], out[:, 3:]


def _align_recording(
    rec: TossRecording, z_nom: object, t_cross_nom: float, z_thr: float, t_rel_nom: float
) -> tuple[float, float]:
    """Clock offset (recording minus command clock) [s] and height bias [m] of one
    recording, by least squares of its in-cup heights against the predicted cup height.

    ``z_nom`` is a callable z(t) of the predicted cup height on the command clock;
    ``t_cross_nom`` is when it crosses ``z_thr`` (half-way up the lift).
    """
    from scipy.optimize import minimize_scalar

    z = rec.p[:, 2]
    above = np.flatnonzero(z >= z_thr)
    if above.size == 0 or above[0] == 0:
        raise InvalidInputError(
            f"toss {rec.toss_id!r}: the recording does not show the ball rising in the cup through "
            f"z = {z_thr:.3f} m (it must start before the lift to be aligned)"
        )
    i = int(above[0])
    w = (z_thr - z[i - 1]) / (z[i] - z[i - 1])
    off0 = float(rec.t[i - 1] + w * (rec.t[i] - rec.t[i - 1]) - t_cross_nom)
    tc = rec.t - off0
    sel = tc <= t_rel_nom - 0.01
    if np.count_nonzero(sel) < 8:
        raise InvalidInputError(f"toss {rec.toss_id!r}: too few in-cup samples to align it ({np.count_nonzero(sel)})")
    ts, zs = rec.t[sel], z[sel]

    def cost(off: float) -> float:
        r = zs - z_nom(ts - off)  # type: ignore[operator]
        r = r - r.mean()
        return float(r @ r)

    res = minimize_scalar(cost, bounds=(off0 - 0.01, off0 + 0.01), method="bounded", options={"xatol": 1e-7})
    off = float(res.x)
    bias = float(np.mean(zs - z_nom(ts - off)))  # type: ignore[operator]
    return off, bias


def _smooth_recording(t: FloatArray, p: FloatArray, window: float, order: int) -> tuple[FloatArray, ...]:
    """Savitzky-Golay smoothing of one recording: uniform resampling at its median
    frame period, then position, velocity and acceleration estimates.

    Returns:
        tu (M,), p (M, 3), v (M, 3), a (M, 3).
    """
    from scipy.signal import savgol_filter

    h = float(np.median(np.diff(t)))
    m = int(math.floor((t[-1] - t[0]) / h + 1e-9)) + 1
    tu = t[0] + h * np.arange(m)
    pu = np.stack([np.interp(tu, t, p[:, j]) for j in range(3)], axis=1)
    n_win = max(int(round(window / h)) | 1, order + 2 + (order + 2 + 1) % 2)
    if n_win > m:
        raise InvalidInputError(f"recording too short ({m} frames) for a {window} s smoothing window")
    ps = savgol_filter(pu, n_win, order, deriv=0, axis=0, mode="interp")
    vs = savgol_filter(pu, n_win, order, deriv=1, delta=h, axis=0, mode="interp")
    as_ = savgol_filter(pu, n_win, order, deriv=2, delta=h, axis=0, mode="interp")
    return tu, ps, vs, as_


def estimate_t_lift(
    primitive: TossPrimitive,
    recordings: tuple[TossRecording, ...],
    t_rough: float,
    *,
    flight: object | None = None,
    step: float = 1e-3,
) -> tuple[float, float]:
    """Time at which the ball's acceleration reaches free flight, from aligned recordings.

    While the ball rides in the cup it moves with the cup, so its acceleration is the
    cup's (above free fall: the cup pushes it); once released its acceleration is that
    of free flight (gravity plus drag). For a candidate ``t_c`` every recording (on the
    command clock) is modelled as the predicted cup path before ``t_c`` and the free
    flight started from the cup's state at ``t_c`` after it, plus a per-recording,
    per-axis offset (tracking calibration) and post-release velocity deviation (arm
    vibration), fitted by least squares. ``t_lift`` is the candidate with the smallest
    residual (grid of ``step``, refined by a parabola): the instant from which the
    recorded ball stops following the cup and its acceleration is that of gravity.

    Why not a threshold on the Savitzky-Golay acceleration: with the +/-3 mm tracking
    noise an acceleration estimate good to ~0.5 m/s^2 needs a 60-100 ms window, which
    rounds off the release and delays a threshold crossing by a good part of the
    window (tens of ms), while the acceleration itself is continuous at the release
    (the cup releases the ball when its deceleration reaches g + drag). The fit uses
    the same physics without that bias.

    Accuracy: because the acceleration is continuous at the release, riding a few ms
    longer or shorter changes the path only at third order in the shift; for a
    vertical release (the cup moves only vertically, so x and y carry no information)
    the estimate scatters by ~2.5 ms (std, up to ~5 ms; 20 tosses, default
    :class:`TossNoise`), about 0.1 ms with tracking noise only. The mean path
    ``p_bar(t)`` does not depend on it.

    Args:
        primitive: the toss (its predicted cup path).
        recordings: recordings already on the command clock.
        t_rough: rough release time [s] (within about -30/+50 ms).
        flight: ball flight model (default :data:`studio.physics.ball.DEFAULT_FLIGHT`).
        step: candidate grid step [s].

    Returns:
        (t_lift [s], rms fit residual per coordinate [m]).
    """
    from studio.physics import ball

    fl = ball.DEFAULT_FLIGHT if flight is None else flight
    lo = max(t_rough + LIFT_SEARCH[0], float(primitive.t[1]))
    hi = min(t_rough + LIFT_SEARCH[1], float(primitive.t[-2]))
    w_lo, w_hi = lo - LIFT_FIT_WINDOW[0], hi + LIFT_FIT_WINDOW[1]
    cand = np.arange(lo, hi + step / 2, step)
    t = primitive.t
    cup = primitive.cup_p
    cup_v = np.gradient(cup, t, axis=0, edge_order=2)
    p0 = _hermite(t, cup, cup_v, cand)
    v0 = np.stack([np.interp(cand, t, cup_v[:, j]) for j in range(3)], axis=1)
    FT, FP, FV = _free_flights(p0, v0, cand, w_hi - lo + 0.01, fl)

    ts, ps, ks = [], [], []
    for k, rec in enumerate(recordings):
        sel = (rec.t >= w_lo) & (rec.t <= w_hi)
        ts.append(rec.t[sel])
        ps.append(rec.p[sel])
        ks.append(np.full(np.count_nonzero(sel), k))
    t_all = np.concatenate(ts)
    p_all = np.concatenate(ps)
    k_all = np.concatenate(ks)
    K = len(recordings)
    if t_all.size < 4 * K:
        raise InvalidInputError("estimate_t_lift: too few recorded samples around the release")
    cup_all = _hermite(t, cup, cup_v, t_all)

    n_k = np.bincount(k_all, minlength=K).astype(float)

    def rss(c: int) -> float:
        tc = cand[c]
        after = t_all >= tc
        model = cup_all.copy()
        model[after] = _hermite(FT[c], FP[c], FV[c], t_all[after])
        r = p_all - model
        # Offsets b_k (all samples) and post-release velocity deviations d_k with
        # sum_k d_k = 0 (the arm's vibration has zero mean), same design for x, y, z:
        # columns e_k (recording k's samples) and x e_j - x e_{K-1} (j < K-1), x = t - tc
        # after the release. The normal equations from per-recording sums (the design
        # is block-sparse: 2K-1 columns, thousands of rows), solved by least squares
        # (rank-deficient when some recording has no sample after tc); RSS = |r|^2 - |A c|^2
        # = |r|^2 - c . A^T r for any solution c.
        x = np.where(after, t_all - tc, 0.0)
        s1 = np.bincount(k_all, weights=x, minlength=K)
        s2 = np.bincount(k_all, weights=x * x, minlength=K)
        r0 = np.stack([np.bincount(k_all, weights=r[:, j], minlength=K) for j in range(3)], axis=1)  # (K, 3)
        r1 = np.stack([np.bincount(k_all, weights=x * r[:, j], minlength=K) for j in range(3)], axis=1)
        ata = np.zeros((2 * K - 1, 2 * K - 1))
        ata[np.arange(K), np.arange(K)] = n_k
        j = np.arange(K - 1)
        ata[j, K + j] = ata[K + j, j] = s1[:-1]  # b_j . (x e_j)
        ata[K - 1, K:] = ata[K:, K - 1] = -s1[-1]  # b_{K-1} . (-x e_{K-1})
        ata[K:, K:] = s2[-1]
        ata[K + j, K + j] += s2[:-1]
        atr = np.vstack([r0, r1[:-1] - r1[-1:]])  # (2K-1, 3)
        coef, *_ = np.linalg.lstsq(ata, atr, rcond=None)
        return float(np.sum(r * r) - np.sum(coef * atr))

    vals = np.array([rss(c) for c in range(cand.size)])
    i = int(np.argmin(vals))
    t_best = float(cand[i])
    if 0 < i < cand.size - 1:
        y0, y1, y2 = vals[i - 1], vals[i], vals[i + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            t_best += 0.5 * step * (y0 - y2) / den
    return t_best, math.sqrt(float(vals[i]) / p_all.size)


@dataclass(frozen=True, eq=False)
class TossModel:
    """Statistical model of a toss from recordings (paper: mean path ``p_bar(t)``,
    ``t_lift`` and the spread of the ball around the mean).

    Per-toss states: in free flight (from ``t_lift`` + :data:`LOCAL_FIT_LIFT_MARGIN`
    to the end of a recording) a recorded toss's state at a time comes from its own
    samples around that time (:meth:`recorded_state_at`, a local polynomial fit), not
    from a state just after the lift flown forward: the velocity estimated there carries
    ~50-80 mm/s of noise per axis, which spreads such predictions ~7 times wider at the
    strike than the recordings themselves. Recordings measure positions only: the
    states carry zero spin (the toss releases the ball without spin, ITTF Law 2.6.2).

    All times are on the primitive's command clock. Arrays are read-only.
    """

    side: TossSide
    """Toss side of the primitive."""
    primitive: TossPrimitive
    """The toss primitive the recordings execute."""
    t: FloatArray
    """Time grid (N,) [s] (command clock, the primitive's step), covered by every recording."""
    p: FloatArray
    """Mean ball path ``p_bar`` (N, 3) [m]: mean of the Savitzky-Golay-smoothed,
    time-aligned recordings."""
    v: FloatArray
    """Mean ball velocity (N, 3) [m/s] (derivative of the smoothed paths)."""
    a: FloatArray
    """Mean ball acceleration (N, 3) [m/s^2] (Savitzky-Golay second derivative)."""
    t_lift: float
    """Time the ball's acceleration reaches free flight (see :func:`estimate_t_lift`) [s]."""
    spread: FloatArray
    """Std. dev. over the tosses of their deviation from the mean path (N, 3) [m]."""
    tosses_p: FloatArray
    """Smoothed aligned path of each toss on the grid (K, N, 3) [m]."""
    tosses_v: FloatArray
    """Smoothed aligned velocity of each toss on the grid (K, N, 3) [m/s]."""
    recordings: TossRecordings
    """The recordings with their times moved to the command clock (truth kept)."""
    clock_offsets: FloatArray
    """Estimated recording-clock minus command-clock offset per toss (K,) [s]."""
    z_bias: FloatArray
    """Estimated height offset of each recording against the predicted cup path (K,) [m]
    (diagnostic of the tracking calibration; not removed from the data)."""
    lift_fit_rms: float
    """RMS residual of the ``t_lift`` fit [m] (about the tracking noise when it fits)."""
    _start_cache: dict[tuple[object, ...], FloatArray] = field(default_factory=dict, init=False, repr=False, compare=False)
    """Cache of :meth:`_recorded_start_states` per (t_start, t_target, flight) (internal)."""

    def __post_init__(self) -> None:
        for fname in ("t", "p", "v", "a", "spread", "tosses_p", "tosses_v", "clock_offsets", "z_bias"):
            arr = np.array(getattr(self, fname), dtype=float)
            arr.setflags(write=False)
            object.__setattr__(self, fname, arr)

    @property
    def n_tosses(self) -> int:
        """Number of recorded tosses."""
        return int(self.tosses_p.shape[0])

    @property
    def spread_norm(self) -> FloatArray:
        """Spread magnitude (N,) [m]: ``sqrt(sum of the per-axis variances)``."""
        return np.sqrt(np.sum(self.spread**2, axis=1))

    def _check_t(self, time: float) -> float:
        tt = float(time)
        if not (math.isfinite(tt) and self.t[0] - 1e-9 <= tt <= self.t[-1] + 1e-9):
            raise InvalidInputError(
                f"toss model {self.primitive.name!r}: time {time} s outside the recorded range "
                f"[{self.t[0]:.3f}, {self.t[-1]:.3f}] s"
            )
        return min(max(tt, float(self.t[0])), float(self.t[-1]))

    def spread_at(self, time: float) -> FloatArray:
        """Per-axis spread (3,) [m] at ``time`` [s] (linear interpolation)."""
        tt = self._check_t(time)
        return np.array([np.interp(tt, self.t, self.spread[:, j]) for j in range(3)])

    def mean_state(self, time: float) -> BallState:
        """Mean ball state at ``time`` [s] (command clock): position (cubic Hermite),
        velocity (linear), zero spin (the toss releases the ball without spin)."""
        from studio.physics.ball import BallState

        tt = self._check_t(time)
        p = _hermite(self.t, self.p, self.v, np.array([tt]))[0]
        v = np.array([np.interp(tt, self.t, self.v[:, j]) for j in range(3)])
        return BallState(p=p, v=v, w=np.zeros(3))

    def ball_states_at(self, time: float) -> tuple[BallState, ...]:
        """State of every recorded toss at ``time`` [s] (:meth:`recorded_state_at`), zero spin."""
        return tuple(self.recorded_state_at(time, k) for k in range(self.n_tosses))

    def _check_k(self, k: int) -> int:
        """``k`` as a toss index in ``[0, n_tosses)``, else InvalidInputError."""
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not (0 <= k < self.n_tosses):
            raise InvalidInputError(f"toss index must be an integer in [0, {self.n_tosses}), got {k!r}")
        return int(k)

    @property
    def free_flight_start(self) -> float:
        """Earliest time [s] whose recorded states come from the local fit:
        ``t_lift`` + :data:`LOCAL_FIT_LIFT_MARGIN`."""
        return float(self.t_lift) + LOCAL_FIT_LIFT_MARGIN

    def recorded_state_at(self, time: float, k: int) -> BallState:
        """State of recorded toss ``k`` at ``time`` [s] (command clock), zero spin.

        In free flight (``time >= free_flight_start``): a polynomial of order
        :data:`LOCAL_FIT_ORDER` fitted to the toss's own recorded positions within
        +/- :data:`LOCAL_FIT_HALF_WINDOW` of ``time`` gives the position [m] and its
        derivative the velocity [m/s] (the window is shifted to stay after
        ``free_flight_start`` and before the recording's last sample: one-sided near
        them, no extrapolation). Every time of the model's interval is covered by every
        recording (the interval is their common one). Before that (ball in the cup or
        just leaving it): the Savitzky-Golay-smoothed path, as before.

        Raises:
            InvalidInputError: ``time`` outside the toss model's interval, ``k`` not a
                toss index, or a recording with a gap (too few samples in the window).
        """
        from studio.physics.ball import BallState

        k = self._check_k(k)
        tt = self._check_t(time)
        if tt < self.free_flight_start:
            p = _hermite(self.t, self.tosses_p[k], self.tosses_v[k], np.array([tt]))[0]
            v = np.array([np.interp(tt, self.t, self.tosses_v[k, :, j]) for j in range(3)])
            return BallState(p=p, v=v, w=np.zeros(3))
        rec = self.recordings.recordings[k]
        span = (self.free_flight_start, float(rec.t[-1]))
        try:
            p, v = _local_fit_state(rec.t, rec.p, tt, span, half_window=LOCAL_FIT_HALF_WINDOW, order=LOCAL_FIT_ORDER)
        except InvalidInputError as exc:
            raise InvalidInputError(f"toss model {self.primitive.name!r}, toss {rec.toss_id!r}: {exc}") from exc
        return BallState(p=p, v=v, w=np.zeros(3))

    def recorded_spread_at(self, time: float) -> FloatArray:
        """Per-axis standard deviation (3,) [m] (ddof = 1) of the recorded tosses'
        positions at ``time`` [s] (:meth:`recorded_state_at`): the spread robust
        evaluations fly the ball through at the strike."""
        P = np.array([s.p for s in self.ball_states_at(time)])
        return P.std(axis=0, ddof=1)

    def recorded_start_state(self, k: int, t_start: float, t_target: float, *, flight: object | None = None) -> BallState:
        """Ball state of recorded toss ``k`` at ``t_start`` [s] from which a spinless
        flight in still air under ``flight`` (default :data:`studio.physics.ball.DEFAULT_FLIGHT`)
        passes through the toss's recorded state at ``t_target`` [s] (the strike time
        tau): :meth:`recorded_state_at` at ``t_target`` integrated back to ``t_start``
        (RK4, :data:`BACK_FLIGHT_STEP`). Robust evaluations fly the ball forward from it
        with the racket moving, so up to the strike the ball follows this toss's own
        recording (within ~1 mm at ``t_target``; earlier it departs by the room air flow
        and the fitted velocity's noise times the time before ``t_target``, a few mm).

        ``t_target`` before :attr:`free_flight_start` (or not after ``t_start``): the
        toss's state at ``t_start`` itself (no flight to aim at).

        Raises:
            InvalidInputError: times outside the model's interval, bad ``k``.
        """
        from studio.physics.ball import BallState

        k = self._check_k(k)
        t0, t1 = self._check_t(t_start), self._check_t(t_target)
        if t1 <= t0 or t1 < self.free_flight_start:
            return self.recorded_state_at(t0, k)
        X = self._recorded_start_states(t0, t1, flight)
        return BallState(p=X[k, :3], v=X[k, 3:], w=np.zeros(3))

    def mean_start_state(self, t_start: float, t_target: float, *, flight: object | None = None) -> BallState:
        """Ball state at ``t_start`` [s] from which a spinless flight in still air under
        ``flight`` (default :data:`studio.physics.ball.DEFAULT_FLIGHT`) passes through the mean
        path's state at ``t_target`` [s] (the strike time tau): the mean-toss evaluation
        flies from it, so the ball is exactly where the strike target assumes it at tau
        (:func:`studio.serve.evaluate.strike_target`). ``t_target`` before
        :attr:`free_flight_start` (or not after ``t_start``): :meth:`mean_state` at ``t_start``.

        Raises:
            InvalidInputError: times outside the model's interval.
        """
        from studio.physics import ball

        t0, t1 = self._check_t(t_start), self._check_t(t_target)
        if t1 <= t0 or t1 < self.free_flight_start:
            return self.mean_state(t0)
        target = self.mean_state(t1)
        fl = ball.DEFAULT_FLIGHT if flight is None else flight
        p0, v0 = _spinless_flight(target.p[None, :], target.v[None, :], t1, t0, fl)
        return ball.BallState(p=p0[0], v=v0[0], w=np.zeros(3))

    def _recorded_start_states(self, t_start: float, t_target: float, flight: object | None) -> FloatArray:
        """All tosses' :meth:`recorded_start_state` as (K, 6) ``[p, v]`` [m, m/s], cached
        per (t_start, t_target, flight): a robust evaluation asks for each toss in turn."""
        from studio.physics import ball

        fl = ball.DEFAULT_FLIGHT if flight is None else flight
        try:
            key: tuple[object, ...] | None = (t_start, t_target, fl)
            hash(key)
        except TypeError:
            key = None
        cached = self._start_cache.get(key) if key is not None else None
        if cached is not None:
            return cached
        states = self.ball_states_at(t_target)
        p1 = np.array([s.p for s in states])
        v1 = np.array([s.v for s in states])
        p0, v0 = _spinless_flight(p1, v1, t_target, t_start, fl)
        X = np.concatenate([p0, v0], axis=1)
        X.setflags(write=False)
        if key is not None:
            if len(self._start_cache) >= 256:
                self._start_cache.clear()
            self._start_cache[key] = X
        return X

    def sample(self, time: float, rng: np.random.Generator, *, method: Literal["gaussian", "recorded"] = "gaussian") -> BallState:
        """A random ball state at ``time`` [s], zero spin.

        ``"gaussian"``: mean state plus a deviation drawn from the recordings' joint
        position-velocity covariance at that time (a random combination of the tosses'
        deviations, so the 6-D correlations are kept); ``"recorded"``: one recorded toss
        picked uniformly.
        """
        from studio.physics.ball import BallState

        if method == "recorded":
            return self.recorded_state_at(time, int(rng.integers(self.n_tosses)))
        states = self.ball_states_at(time)
        if method != "gaussian":
            raise InvalidInputError(f"TossModel.sample: method must be 'gaussian' or 'recorded', got {method!r}")
        X = np.array([np.concatenate([s.p, s.v]) for s in states])
        mean = X.mean(axis=0)
        dev = X - mean
        K = X.shape[0]
        draw = mean + (rng.standard_normal(K) @ dev) / math.sqrt(max(K - 1, 1))
        return BallState(p=draw[:3], v=draw[3:], w=np.zeros(3))

    @classmethod
    def from_recordings(
        cls,
        primitive: TossPrimitive,
        recordings: TossRecordings,
        *,
        smoothing_window: float = SMOOTHING_WINDOW,
        smoothing_order: int = SMOOTHING_ORDER,
    ) -> TossModel:
        """Build the toss model from recordings of ``primitive`` (paper's procedure).

        1. Time alignment: each recording's clock offset is estimated by least squares
           of its heights while the ball rides up in the cup against the primitive's
           predicted cup height (:attr:`TossPrimitive.cup_p`), after a coarse match of
           the half-way crossing; this puts every toss on the command clock.
        2. Each aligned recording is smoothed by a Savitzky-Golay filter
           (``smoothing_window`` [s], order ``smoothing_order``), interpolated on the
           primitive's time grid over the interval every recording covers by a cubic
           spline (velocity = its derivative; acceleration = the filter's second
           derivative); the mean over tosses is ``p_bar(t)``.
        3. ``t_lift``: :func:`estimate_t_lift` around the instant the mean acceleration
           drops below ``-g/2`` after the peak upward speed.
        4. Spread: per-axis standard deviation of the tosses' smoothed paths around the
           mean (ddof = 1).

        Raises:
            InvalidInputError: fewer than 3 tosses, a recording that cannot be aligned
                (no in-cup samples) or no common time interval.
        """
        from scipy.interpolate import CubicSpline

        recs = recordings.recordings
        if len(recs) < 3:
            raise InvalidInputError(f"TossModel: need at least 3 recorded tosses, got {len(recs)}")
        rel = primitive.release
        z_cup = CubicSpline(primitive.t, primitive.cup_p[:, 2])
        z0 = float(primitive.cup_p[0, 2])
        z_thr = z0 + 0.5 * (float(rel.position[2]) - z0)
        i_thr = int(np.argmax(primitive.cup_p[:, 2] >= z_thr))
        zc = primitive.cup_p[:, 2]
        w = (z_thr - zc[i_thr - 1]) / (zc[i_thr] - zc[i_thr - 1])
        t_cross = float(primitive.t[i_thr - 1] + w * primitive.dt)

        offsets, biases, aligned = [], [], []
        for rec in recs:
            off, bias = _align_recording(rec, z_cup, t_cross, z_thr, rel.time)
            offsets.append(off)
            biases.append(bias)
            aligned.append(TossRecording(toss_id=rec.toss_id, t=rec.t - off, p=rec.p))
        aligned_set = TossRecordings(recordings=tuple(aligned), truth=recordings.truth)

        smoothed = [_smooth_recording(r.t, r.p, smoothing_window, smoothing_order) for r in aligned]
        t_lo = max(s[0][0] for s in smoothed)
        t_hi = min(s[0][-1] for s in smoothed)
        grid = primitive.t[(primitive.t >= t_lo) & (primitive.t <= t_hi)]
        if grid.size < 10:
            raise InvalidInputError("TossModel: the recordings have no common time interval")
        P = np.empty((len(smoothed), grid.size, 3))
        V = np.empty_like(P)
        Acc = np.empty_like(P)
        for k, (tu, ps, _, as_) in enumerate(smoothed):
            # C^2 spline through the smoothed frames: position and velocity consistent.
            spline = CubicSpline(tu, ps, axis=0)
            P[k] = spline(grid)
            V[k] = spline(grid, 1)
            for j in range(3):
                Acc[k, :, j] = np.interp(grid, tu, as_[:, j])
        p_mean = P.mean(axis=0)
        v_mean = V.mean(axis=0)
        a_mean = Acc.mean(axis=0)
        spread = P.std(axis=0, ddof=1)

        i_peak = int(np.argmax(v_mean[:, 2]))
        below = np.flatnonzero(a_mean[i_peak:, 2] <= -0.5 * C.GRAVITY)
        if below.size == 0:
            raise InvalidInputError("TossModel: the mean path never decelerates like a released ball")
        t_rough = float(grid[i_peak + int(below[0])])
        t_lift, rms = estimate_t_lift(primitive, tuple(aligned), t_rough)
        return cls(
            side=primitive.side,
            primitive=primitive,
            t=grid,
            p=p_mean,
            v=v_mean,
            a=a_mean,
            t_lift=t_lift,
            spread=spread,
            tosses_p=P,
            tosses_v=V,
            recordings=aligned_set,
            clock_offsets=np.array(offsets),
            z_bias=np.array(biases),
            lift_fit_rms=rms,
        )


# =====================================================================================
# Shipped defaults and their generator
# =====================================================================================

DEFAULT_TOSS_DIR: Final[Path] = DATA_DIR / "tosses"
"""Folder of the shipped toss recordings ``right.csv`` and ``left.csv``."""

DEFAULT_N_TOSSES: Final[int] = 20
"""Number of synthetic tosses per side in the shipped recordings."""

DEFAULT_SEED: Final[int] = 20251215
"""Seed of the shipped synthetic recordings (side index appended)."""


def default_toss(robot: Robot, side: TossSide) -> TossPrimitive:
    """The default toss primitive of a side: :func:`make_toss` with its defaults
    (deterministic: the same robot gives the same commands)."""
    return make_toss(robot, side)


def default_recordings_path(side: TossSide) -> Path:
    """Path of the shipped recordings of ``side``."""
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"toss side must be one of {TOSS_SIDES}, got {side!r}")
    return DEFAULT_TOSS_DIR / f"{side}.csv"


@functools.lru_cache(maxsize=2)
def _default_model_cached(side: TossSide) -> TossModel:
    from studio.robot.model import load_robot

    robot = load_robot()
    return TossModel.from_recordings(default_toss(robot, side), load_recordings_csv(default_recordings_path(side)))


def load_default_toss_model(side: TossSide, robot: Robot | None = None) -> TossModel:
    """Toss model of ``side`` from the shipped recordings (``studio/data/tosses``).

    The primitive is rebuilt with :func:`default_toss` on ``robot`` (default: the
    shipped robot, and the model is cached per side) and the recordings are loaded
    from ``<side>.csv``.

    Raises:
        InvalidInputError: unknown side; DataFileError: a bad recordings file.
    """
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"toss side must be one of {TOSS_SIDES}, got {side!r}")
    if robot is None:
        return _default_model_cached(side)
    return TossModel.from_recordings(default_toss(robot, side), load_recordings_csv(default_recordings_path(side)))


def generate_default_recordings(
    out_dir: str | Path = DEFAULT_TOSS_DIR, *, n: int = DEFAULT_N_TOSSES, seed: int = DEFAULT_SEED
) -> list[Path]:
    """Write synthetic ``right.csv`` and ``left.csv`` (deterministic for a seed).

    Each side: :func:`default_toss` on the shipped robot, :func:`simulate_tosses` with
    the default :class:`TossNoise` and ``np.random.default_rng([seed, side_index])``,
    toss ids ``<side>_<k>``, saved with 4 decimals (0.1 ms, 0.1 mm): ~165 KiB per side.
    """
    from studio.robot.model import load_robot

    robot = load_robot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for idx, side in enumerate(TOSS_SIDES):
        prim = default_toss(robot, side)
        recs = simulate_tosses(robot, prim, n, np.random.default_rng([seed, idx]), noise=TossNoise(), id_prefix=side)
        path = out / f"{side}.csv"
        save_recordings_csv(
            path,
            recs,
            decimals=4,
            comment=(
                f"Synthetic recordings of the default {side} toss (python -m studio.toss.model --generate, "
                f"seed {seed}, {n} tosses, default TossNoise).\n"
                "Columns: toss_id, t [s] (camera clock, random offset per toss), x, y, z [m] ball centre, "
                "world frame (origin table centre, +X to the receiver, +Z up)."
            ),
        )
        written.append(path)
    return written


def toss_report(side: TossSide = "right", csv_path: str | Path | None = None, *, robot: Robot | None = None) -> str:
    """Human-readable analysis of toss recordings (``serve-studio toss``).

    Builds the :class:`TossModel` of the default ``side`` primitive from ``csv_path``
    (default: the shipped recordings) and reports the predicted release, ``t_lift``,
    the rise of the mean path and the spread after the lift.

    Raises:
        InvalidInputError / DataFileError: bad side or recordings file.
    """
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"toss side must be one of {TOSS_SIDES}, got {side!r}")
    if robot is None and csv_path is None:
        model = load_default_toss_model(side)
    else:
        from studio.robot.model import load_robot

        rb = load_robot() if robot is None else robot
        path = default_recordings_path(side) if csv_path is None else Path(csv_path)
        model = TossModel.from_recordings(default_toss(rb, side), load_recordings_csv(path))
    rel = model.primitive.release
    apex = float(np.max(model.p[:, 2]))
    lines = [
        f"{model.primitive.name}: {model.n_tosses} tosses, model grid {model.t[0]:.3f}-{model.t[-1]:.3f} s (command clock)",
        f"  predicted release {rel.time:.4f} s at {np.round(rel.position, 3)} m, "
        f"v = {np.round(rel.velocity, 3)} m/s, spin {rel.spin:.2g} rad/s",
        f"  t_lift {model.t_lift:.4f} s (fit rms {model.lift_fit_rms * 1e3:.2f} mm, "
        f"{(model.t_lift - rel.time) * 1e3:+.1f} ms from the prediction)",
        f"  mean path apex {apex:.3f} m: rise {apex - float(rel.position[2]):.3f} m above the release "
        f"(ITTF 2.6.2: >= {C.TOSS_MIN_RISE} m)",
        f"  clock offsets {np.min(model.clock_offsets):.3f}..{np.max(model.clock_offsets):.3f} s, "
        f"height bias {np.min(model.z_bias) * 1e3:+.1f}..{np.max(model.z_bias) * 1e3:+.1f} mm",
    ]
    for dt_after in (0.3, 0.5, 0.7):
        tq = model.t_lift + dt_after
        if tq <= model.t[-1]:
            sp = model.spread_at(tq) * 1e3
            lines.append(
                f"  spread {dt_after:.1f} s after the lift: x {sp[0]:.1f}, y {sp[1]:.1f}, z {sp[2]:.1f} mm "
                f"(|.| {float(np.linalg.norm(sp)):.1f} mm), ball at z = {model.mean_state(tq).p[2]:.3f} m"
            )
            if tq >= model.free_flight_start:
                rs = model.recorded_spread_at(tq) * 1e3
                lines.append(f"    recorded states there (each toss's own samples +/- {LOCAL_FIT_HALF_WINDOW * 1e3:.0f} ms): |spread| {float(np.linalg.norm(rs)):.1f} mm")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m studio.toss.model [--generate] [--out DIR] [--n N] [--seed S]``: write the
    default synthetic recordings (``--generate``) and print a summary of the models."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m studio.toss.model", description=main.__doc__)
    ap.add_argument("--generate", action="store_true", help="write right.csv and left.csv")
    ap.add_argument("--out", default=str(DEFAULT_TOSS_DIR), help="output folder (default: the shipped data)")
    ap.add_argument("--n", type=int, default=DEFAULT_N_TOSSES, help="tosses per side")
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED, help="random seed")
    args = ap.parse_args(argv)
    from studio.robot.model import load_robot

    if args.generate:
        for path in generate_default_recordings(args.out, n=args.n, seed=args.seed):
            print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")
    robot = load_robot()
    for side in TOSS_SIDES:
        print(toss_report(side, Path(args.out) / f"{side}.csv", robot=robot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
