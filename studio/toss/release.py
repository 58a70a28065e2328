"""Release model: when and how the ball leaves the ball cup along a racket motion.

The ball (a point of mass ``m`` at the cup's ball centre) rides in the cup while the cup
pushes on it, i.e. while the normal contact force is non-negative::

    N / m = (a_cup + g e_z + k |v_cup| v_cup) . n_cup >= 0

where ``a_cup`` and ``v_cup`` are the acceleration and velocity of the cup's ball
centre, ``n_cup`` the unit cup/racket normal (face A, the cup's side) and ``k`` the
ball's quadratic drag constant (still air): the drag on a rising ball presses it into
the cup, so it leaves when the cup decelerates at ``g + k v^2`` (about 10.5 m/s^2 at
2.7 m/s), where the free ball's own deceleration takes over without a jump (no
ball-in-cup overlap right after the release). The ball leaves at the first instant this
normal force vanishes (becomes negative): the crossing is located by linear
interpolation of the margin between the two samples that bracket it; the release
position is Hermite-interpolated from positions and velocities, the velocity linearly.
After that the ball is in free flight (gravity, drag) from the returned state, with the
racket's angular velocity as spin (no rolling in the cup).

Assumption: the rim does not push the ball sideways at the release, i.e. the cup's
acceleration perpendicular to ``n_cup`` is ~0 there
(:attr:`Release.sideways_acceleration`). Only the normal force is modelled: the ball
rests on the rim's inner edges (rim radius < ball radius), which could hold it sideways
while it is pressed in, but once the normal force vanishes a sideways accelerating cup
keeps pushing the ball with its rim and its wall soon hits it (the MuJoCo rollout sees
that as a robot contact), so the free flight from the returned state would be wrong.
Check ``sideways_acceleration`` of the result for motions not made by
:func:`studio.toss.design.make_toss` (which keeps it below
:data:`studio.toss.checks.MAX_RELEASE_SIDEWAYS_ACCELERATION`).

Robustness: the normal is renormalised per sample; a margin that is exactly 0 at a
sample is still contact (``>= 0``); a ball that is not supported from the first sample
on is released at ``t[0]``; the first crossing counts (a ball once free does not come
back into the cup in this model).

World frame, SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import InvalidInputError
from studio.toss.flight import drag_constant

FloatArray = npt.NDArray[np.float64]


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
        ~0 (see the module docstring); :func:`studio.toss.design.make_toss` keeps it below
        :data:`studio.toss.checks.MAX_RELEASE_SIDEWAYS_ACCELERATION`."""
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
    """Find when the ball leaves the ball cup along a (predicted) racket motion: the first
    instant the normal contact force vanishes (release model, assumption and robustness
    in the module docstring).

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
    tt, p, n = _checked_samples(t, cup_p, cup_normal)
    v = np.gradient(p, tt, axis=0, edge_order=2) if cup_v is None else _checked_rows(cup_v, "cup_v", tt.size)
    a = np.gradient(v, tt, axis=0, edge_order=2) if cup_a is None else _checked_rows(cup_a, "cup_a", tt.size)
    k_drag = drag_constant() if drag_k is None else float(drag_k)
    if not (math.isfinite(k_drag) and k_drag >= 0.0):
        raise InvalidInputError(f"find_release: drag_k must be finite and >= 0, got {drag_k}")
    margin = contact_margin(a, n, gravity=gravity, velocity=v, drag_k=k_drag)
    negative = np.flatnonzero(margin < 0.0)
    if negative.size == 0:
        return None
    omega = _angular_velocities(tt, n, rotation)
    k = int(negative[0])
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
    return _release_between(k - 1, k, tt, margin, p, v, a, n, omega)


def _checked_samples(
    t: npt.ArrayLike, cup_p: npt.ArrayLike, cup_normal: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Times (N,), cup positions (N, 3) and unit normals (N, 3) of :func:`find_release`,
    validated (InvalidInputError otherwise)."""
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
    return tt, p, n / norms[:, None]


def _checked_rows(value: npt.ArrayLike, name: str, N: int) -> FloatArray:
    """``value`` as an (N, 3) float array, else InvalidInputError naming ``name``."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != (N, 3):
        raise InvalidInputError(f"find_release: {name} must be ({N}, 3), got {arr.shape}")
    return arr


def _angular_velocities(tt: FloatArray, n: FloatArray, rotation: npt.ArrayLike | None) -> FloatArray:
    """Racket angular velocity (N, 3) [rad/s]: from the rotations (``omega^ = dR/dt R^T``),
    else the normal's turning rate ``n x dn/dt``."""
    N = tt.size
    if rotation is not None:
        R = np.asarray(rotation, dtype=float)
        if R.shape != (N, 3, 3):
            raise InvalidInputError(f"find_release: rotation must be ({N}, 3, 3), got {R.shape}")
        Rd = np.gradient(R, tt, axis=0, edge_order=2)
        W = Rd @ np.transpose(R, (0, 2, 1))
        W = 0.5 * (W - np.transpose(W, (0, 2, 1)))
        return np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1)
    nd = np.gradient(n, tt, axis=0, edge_order=2)
    return np.cross(n, nd)


def _release_between(
    i: int,
    k: int,
    tt: FloatArray,
    margin: FloatArray,
    p: FloatArray,
    v: FloatArray,
    a: FloatArray,
    n: FloatArray,
    omega: FloatArray,
) -> Release:
    """The release between samples ``i`` (contact) and ``k = i + 1`` (none): crossing of
    the margin by linear interpolation, cubic Hermite position, linear
    velocity/acceleration/normal/omega."""
    m0, m1 = float(margin[i]), float(margin[k])
    s = m0 / (m0 - m1)  # in [0, 1): m0 >= 0 > m1
    h = float(tt[k] - tt[i])
    t_rel = float(tt[i] + s * h)
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
