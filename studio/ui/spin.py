"""Spin made visible: the ball's orientation from its spin, its marking, spin-axis arrows.

Pure functions (no viser): the scene adapter draws what they return.

- :func:`integrate_orientation` turns the sampled spin ``w(t)`` of a ball path
  (:class:`studio.physics.ball.Trajectory`: ``t`` [s], ``w`` [rad/s], world frame) into the
  ball's orientation at every sample, so a marking on the ball turns at the simulated spin;
- :func:`orientation_at` resamples it at playback times;
- :func:`seam_points` is the marking (a tennis-ball seam on the unit sphere, non-planar, so
  a turn about any axis shows) and :data:`LOGO_DIRECTION` a dot on one of its lobes;
- :func:`spin_arrows` gives an arrow along the spin axis (right-hand rule) at the racket
  contact and after each table bounce, labelled with the velocity-aligned components of
  :func:`studio.physics.ball.spin_components` (topspin > 0, backspin < 0, sidespin > 0:
  counter-clockwise seen from above, the ball curving to its left).

Quaternions are (w, x, y, z), scalar first, as viser takes them; they rotate ball-frame
vectors into the world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from studio.physics.ball import spin_components

if TYPE_CHECKING:
    from studio.physics.ball import Trajectory

FloatArray = npt.NDArray[np.float64]
Rgb = tuple[int, int, int]

SPIN_ARROW_COLOR: Rgb = (150, 50, 210)
"""Colour of the spin-axis arrows (purple: neither a path nor a racket colour)."""

ARROW_LENGTH_PER_SPIN = 0.12 / 150.0
"""Spin-axis arrow length per spin [m per rad/s]: 12 cm at 150 rad/s (~24 rev/s)."""

ARROW_LENGTH_RANGE = (0.04, 0.30)
"""Shortest and longest spin-axis arrow drawn [m] (a weak spin stays visible, a heavy one
does not cross the table)."""

LOGO_DIRECTION = (math.sqrt(0.5), -math.sqrt(0.5), 0.0)
"""Where the logo dot sits on the ball, ball frame (unit vector): the middle of one lobe
of :func:`seam_points`, 45 degrees from the seam."""


def quat_multiply(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Hamilton product ``a * b`` of (w, x, y, z) quaternions, (4,) or (N, 4) each."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_from_rotvec(r: npt.ArrayLike) -> FloatArray:
    """Quaternions (w, x, y, z) of rotation vectors ``r`` (3,) or (N, 3) [rad]."""
    r = np.asarray(r, dtype=float)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 for small a (series), no division by zero
    k = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), k * r], axis=-1)


def rotate(q: npt.ArrayLike, v: npt.ArrayLike) -> FloatArray:
    """Rotate vectors ``v`` (..., 3) by the unit quaternion ``q`` (4,)."""
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    w, u = q[0], q[1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def integrate_orientation(
    t: npt.ArrayLike, w: npt.ArrayLike, q0: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
) -> FloatArray:
    """The ball's orientation at each sample of a spin history.

    Between samples k and k+1 the ball turns at the mean of their spins (world-frame
    angular velocity, so each step multiplies from the left):
    ``q[k+1] = exp((w[k] + w[k+1]) / 2 * (t[k+1] - t[k])) * q[k]``. Repeated times (a
    bounce sampled before and after) add no turn.

    Args:
        t: sample times (N,) [s], non-decreasing.
        w: spins (N, 3) [rad/s], world frame.
        q0: orientation at ``t[0]`` (w, x, y, z).

    Returns:
        Unit quaternions (N, 4), (w, x, y, z).
    """
    t = np.asarray(t, dtype=float)
    w = np.asarray(w, dtype=float)
    if t.ndim != 1 or w.shape != (len(t), 3):
        raise ValueError(f"integrate_orientation: t (N,) and w (N, 3) expected, got {t.shape} and {w.shape}")
    out = np.empty((len(t), 4))
    if len(t) == 0:
        return out
    steps = quat_from_rotvec(0.5 * (w[:-1] + w[1:]) * np.diff(t)[:, None]).tolist()
    qw, qx, qy, qz = (float(x) for x in q0)
    out[0] = (qw, qx, qy, qz)
    for k, (sw, sx, sy, sz) in enumerate(steps, start=1):  # plain floats: cheap per step (docs/measured.md)
        qw, qx, qy, qz = (
            sw * qw - sx * qx - sy * qy - sz * qz,
            sw * qx + sx * qw + sy * qz - sz * qy,
            sw * qy - sx * qz + sy * qw + sz * qx,
            sw * qz + sx * qy - sy * qx + sz * qw,
        )
        if k % 256 == 0:  # keep it unit length against rounding drift
            n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            qw, qx, qy, qz = qw / n, qx / n, qy / n, qz / n
        out[k] = (qw, qx, qy, qz)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def orientation_at(times: npt.ArrayLike, t: npt.ArrayLike, w: npt.ArrayLike, q: npt.ArrayLike) -> FloatArray:
    """Orientation (M, 4) at ``times`` (M,) [s] from samples ``t`` (N,), spins ``w`` (N, 3)
    [rad/s] and orientations ``q`` (N, 4): the sample at or before each time, turned on at
    its spin for the remaining time. Times before ``t[0]`` get ``q[0]``, after ``t[-1]`` ``q[-1]``."""
    times = np.asarray(times, dtype=float)
    t = np.asarray(t, dtype=float)
    idx = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)
    dt = np.clip(times - t[idx], 0.0, None)
    dt[times > t[-1]] = 0.0
    out = quat_multiply(
        quat_from_rotvec(np.asarray(w, dtype=float)[idx] * dt[:, None]), np.asarray(q, dtype=float)[idx]
    )
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def seam_points(n: int = 96, lobe: float = 0.3) -> FloatArray:
    """A closed tennis-ball seam on the unit sphere, (n + 1, 3) (first point repeated).

    ``(a cos s + b cos 3s, a sin s - b sin 3s, 2 sqrt(ab) sin 2s)`` with ``a = 1 - lobe``,
    ``b = lobe`` lies on the unit sphere for every s (``x^2 + y^2 + z^2 = (a + b)^2``)."""
    a, b = 1.0 - lobe, lobe
    s = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.stack(
        [a * np.cos(s) + b * np.cos(3 * s), a * np.sin(s) - b * np.sin(3 * s), 2.0 * np.sqrt(a * b) * np.sin(2 * s)],
        axis=1,
    )


@dataclass(frozen=True, slots=True)
class SpinArrow:
    """An arrow along a spin axis (right-hand rule), drawn at a contact."""

    name: str
    """Node name suffix (unique within a frame)."""
    origin: tuple[float, float, float]
    """Arrow start: the ball centre at the contact [m], world frame."""
    vector: tuple[float, float, float]
    """Arrow from start to tip [m]: along the spin, :data:`ARROW_LENGTH_PER_SPIN` per rad/s
    (clipped to :data:`ARROW_LENGTH_RANGE`)."""
    spin: float
    """Spin magnitude |w| [rad/s]."""
    topspin: float
    """Top (> 0) / back (< 0) spin component [rad/s]."""
    sidespin: float
    """Side spin component [rad/s] (> 0: the ball curves to its left)."""
    where: str
    """Which contact: ``after the racket``, ``after bounce 1``, ..."""
    label: str
    """Text shown at the tip."""


def spin_label(topspin: float, sidespin: float) -> str:
    """``"topspin 118, side -76 rad/s"`` (backspin named as such)."""
    kind = "topspin" if topspin >= 0 else "backspin"
    return f"{kind} {abs(topspin):.0f}, side {sidespin:+.0f} rad/s"


def spin_arrow(name: str, where: str, p: npt.ArrayLike, v: npt.ArrayLike, w: npt.ArrayLike) -> SpinArrow:
    """The arrow of spin ``w`` [rad/s] at ball position ``p`` [m] moving at ``v`` [m/s];
    ``where`` names the contact (``after the racket``, ``after bounce 1``, ...)."""
    w = np.asarray(w, dtype=float)
    magnitude = float(np.linalg.norm(w))
    tb, ss, _ = (float(x) for x in spin_components(v, w))
    length = float(np.clip(ARROW_LENGTH_PER_SPIN * magnitude, *ARROW_LENGTH_RANGE))
    axis = w / magnitude if magnitude > 1e-9 else np.zeros(3)
    return SpinArrow(
        name=name,
        origin=tuple(float(x) for x in np.asarray(p, dtype=float)),  # type: ignore[arg-type]
        vector=tuple(float(x) for x in length * axis),  # type: ignore[arg-type]
        spin=magnitude,
        topspin=tb,
        sidespin=ss,
        where=where,
        label=spin_label(tb, ss),
    )


def spin_arrows(ball: Trajectory) -> tuple[SpinArrow, ...]:
    """Spin-axis arrows just after the first racket contact and after each table bounce
    that follows it (the states of the path's :class:`studio.physics.ball.Event` s)."""
    arrows: list[SpinArrow] = []
    struck = False
    bounce = 0
    for k, e in enumerate(ball.events):
        if e.kind == "racket" and not struck:
            struck = True
            arrows.append(spin_arrow(f"spin_{k}", "after the racket", e.p, e.v_after, e.w_after))
        elif e.kind == "table" and struck:
            bounce += 1
            arrows.append(spin_arrow(f"spin_{k}", f"after bounce {bounce}", e.p, e.v_after, e.w_after))
    return tuple(arrows)
