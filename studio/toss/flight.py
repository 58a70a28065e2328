"""Spinless flights of the tossed ball: drag constant, vertical rise, RK4 flights and the
cubic Hermite interpolation of their samples.

The toss releases the ball without spin and flies it behind the end line, so these
flights have no Magnus force and no contacts. The equations are those of
:class:`studio.physics.ball.FlightModel` (gravity and quadratic drag on the velocity
relative to the air). World frame, SI units.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from studio import constants as C

FloatArray = npt.NDArray[np.float64]


def drag_constant() -> float:
    """Quadratic drag constant ``k = rho C_D A / (2 m)`` [1/m] of the ball flight model."""
    from studio.physics import ball

    return float(ball.FlightModel().drag_constant)


def vertical_rise(vz: float, *, drag_k: float, gravity: float = C.GRAVITY) -> float:
    """Apex height above the start of a ball thrown straight up at ``vz`` [m/s] under
    gravity and quadratic drag ``a = -g - k v|v|``: ``ln(1 + k vz^2/g) / (2 k)`` [m].
    ``drag_k = rho C_D A / (2 m)`` [1/m]; ``drag_k = 0`` gives ``vz^2 / (2 g)``."""
    if vz <= 0.0:
        return 0.0
    if drag_k <= 0.0:
        return vz * vz / (2.0 * gravity)
    return math.log1p(drag_k * vz * vz / gravity) / (2.0 * drag_k)


def speed_for_rise(rise: float, *, drag_k: float, gravity: float = C.GRAVITY) -> float:
    """Inverse of :func:`vertical_rise`: launch speed [m/s] for an apex ``rise`` [m]."""
    if drag_k <= 0.0:
        return math.sqrt(2.0 * gravity * rise)
    return math.sqrt(gravity * math.expm1(2.0 * drag_k * rise) / drag_k)


def hermite_interpolate(t_s: FloatArray, p_s: FloatArray, v_s: FloatArray, tq: FloatArray) -> FloatArray:
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


def free_flights(
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


def single_flight(
    p0: FloatArray, v0: FloatArray, t0: float, t_end: float, wind: FloatArray, flight: object
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One spinless flight from ``(p0, v0)`` at ``t0`` to ``t_end`` [s] in a uniform,
    constant ``wind`` (3,) [m/s] (see :func:`free_flights`).

    Returns:
        t (M,), p (M, 3), v (M, 3) sampled every millisecond.
    """
    T, P, V = free_flights(
        np.asarray(p0, dtype=float)[None, :],
        np.asarray(v0, dtype=float)[None, :],
        np.array([t0]),
        max(t_end - t0, 1e-3),
        flight,
        wind=np.asarray(wind, dtype=float)[None, :],
        h=1e-3,
    )
    return T[0], P[0], V[0]


def spinless_flight(
    p: FloatArray, v: FloatArray, t0: float, t1: float, flight: object, *, step: float
) -> tuple[FloatArray, FloatArray]:
    """Positions [m] and velocities [m/s] (C, 3) at ``t1`` [s] of spinless flights from
    ``p``, ``v`` (C, 3) at ``t0`` [s] in still air: classic RK4 on the flight model's
    scalar derivative (``flight.scalar_derivative()``, a :class:`studio.physics.ball.FlightModel`;
    the same equations as its ``acceleration``, on Python floats: far cheaper than numpy
    for a single state, ``docs/measured.md``) with equal steps of at most ``step`` [s];
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
