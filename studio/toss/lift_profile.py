"""Vertical motion of the ball cup during a toss: the lift profile and the rest-to-rest
moves that clear the ball's path.

:class:`LiftProfile` is a chain of constant accelerations joined by quintic smootherstep
transitions (:class:`LiftShape` its free parameters; :meth:`LiftProfile.design` solves
the rest for a release speed); :func:`smoothstep9_move` a degree-9 smoothstep move. SI
units, times from the start of the toss.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import InvalidInputError

FloatArray = npt.NDArray[np.float64]


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


SMOOTHSTEP9: Final = np.polynomial.Polynomial([0, 0, 0, 0, 0, 126, -420, 540, -315, 70])
"""Degree-9 smoothstep ``s(tau)``: s(0) = 0, s(1) = 1, derivatives 1-4 zero at both ends."""


def smoothstep9_move(t: FloatArray, start: float, duration: float, distance: float) -> FloatArray:
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
    poly = SMOOTHSTEP9
    for m in range(6):
        vals = poly(tau) * distance / duration**m
        out[m] = vals if m == 0 else np.where(inside, vals, 0.0)
        poly = poly.deriv()
    return out


@dataclass(frozen=True, slots=True)
class LiftShape:
    """The free parameters of a :class:`LiftProfile`: its rest, ramps and lift
    acceleration (:meth:`LiftProfile.design` solves the lift hold and the stop
    deceleration for a release speed). Defaults: those of the shipped tosses."""

    lift_acceleration: float = 18.0
    """Upward cup acceleration of the lift [m/s^2]."""
    ramp_up: float = 0.20
    """Duration of the 0 -> lift acceleration ramp [s]."""
    ramp_release: float = 0.16
    """Duration of the lift -> stop ramp [s], in which the ball is released."""
    ramp_stop: float = 0.20
    """Duration of the final ramp back to zero acceleration [s]."""
    hold_start: float = 0.05
    """Rest before the lift [s]."""


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
    ``-(g + k v^2)``, see :func:`studio.toss.release.find_release`)
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
    def design(cls, release_speed: float, shape: LiftShape, *, gravity: float = C.GRAVITY) -> LiftProfile:
        """The profile of ``shape`` whose cup crosses ``a = -g`` at ``release_speed`` [m/s]
        and stops with no deceleration hold: ``lift_hold`` and ``stop_deceleration`` are
        solved.

        Raises:
            InvalidInputError: no such profile (the ramps alone are too fast, or the
                stop deceleration would not exceed ``1.05 g``).
        """
        lift_acceleration, ramp_up = shape.lift_acceleration, shape.ramp_up
        ramp_release, ramp_stop, hold_start = shape.ramp_release, shape.ramp_stop, shape.hold_start

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
