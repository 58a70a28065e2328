"""Ball in the cup: the holding cone of the racket's ball cup and its check along a motion.

The ball (radius R) rests on the inner top edges of the ``wall_count`` (n) wall blocks of
the cup, at distance ``rim_radius`` (r < R) from the cup axis (``robots/serve_robot.toml``,
``[cup]``: R = 20 mm, r = 14 mm, n = 8; :class:`studio.robot.description.RacketSpec`).
While the ball rides with the cup, the cup must give it the *specific force*
``f = a_cup - g`` (acceleration of the ball's centre minus gravity, per unit mass). A
frictionless edge contact pushes only along its normal, from the edge to the ball's
centre, tilted from the cup axis by ``alpha = asin(r / R)`` (44.4 deg). So the ball stays
seated exactly while ``f`` lies in the convex cone of the n edge normals: a regular
n-sided pyramid around the cup axis, widest towards an edge (``tan alpha``), narrowest
between two edges (``tan alpha cos(pi / n)``). In the cup frame (z = the racket's face-A
normal, the cup's axis)::

    f_n = f . z > 0   and   |f_t| <= c_geom f_n,   c_geom = tan(asin(r / R)) cos(pi / n)

(0.905 for the shipped cup: the ball rolls over the rim once the cup accelerates
sideways at ~0.9 times its normal load). Friction between ball and rim only widens the
cone; it is left out (conservative). Air drag on the ball, moving with the cup through
still air, is in ``f`` (``+ k |v| v``, as in :func:`studio.toss.release.find_release`): < 0.1
m/s^2 in the preparation, ~1 m/s^2 pressing the rising ball into the cup near the
toss's release.
The check allows ``c = c_geom / CUP_SAFETY_FACTOR``. ``tests/test_cup_hold.py`` measures
the cone in a native MuJoCo model of the cup (ball tilted off at the predicted angles) and
replays exported serves in it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt
import pinocchio as pin

from studio import constants as C
from studio.errors import InvalidInputError
from studio.robot.description import BALL_CUP_FRAME, RacketSpec
from studio.robot.model import Robot

FloatArray = npt.NDArray[np.float64]

CUP_SAFETY_FACTOR: Final[float] = 1.5
"""Safety factor on the frictionless rim cone [-] (a choice): room for what the predicted
joint states do not hold: tracking errors of the real drives (the joint model's wn, zeta
are stand-in values), vibration of the racket mount, a ball not exactly centred."""


@dataclass(frozen=True, slots=True)
class CupGrip:
    """Allowed specific force of the ball cup: ``|f_t| <= limit * f_n``, ``f_n > 0``."""

    geometric: float
    """Frictionless rim cone c_geom = tan(asin(r / R)) cos(pi / n) [-] (module docstring)."""
    safety_factor: float = CUP_SAFETY_FACTOR
    """Divides ``geometric`` [-]."""

    def __post_init__(self) -> None:
        for name in ("geometric", "safety_factor"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInputError(f"CupGrip.{name} must be finite and > 0, got {v!r}")

    @property
    def limit(self) -> float:
        """Allowed ratio c = |f_t| / f_n [-]."""
        return self.geometric / self.safety_factor

    @classmethod
    def from_racket(cls, racket: RacketSpec, *, safety_factor: float = CUP_SAFETY_FACTOR) -> CupGrip:
        """The grip of the cup described by ``racket`` (rim radius, ball radius, wall count)."""
        alpha = math.asin(racket.cup_rim_radius / racket.ball_radius)
        return cls(math.tan(alpha) * math.cos(math.pi / racket.cup_wall_count), safety_factor)

    @classmethod
    def of(cls, robot: Robot) -> CupGrip:
        """The grip of ``robot``'s cup with the default safety factor."""
        return cls.from_racket(robot.spec.racket)


def joint_accelerations(robot: Robot, u: npt.ArrayLike, q: npt.ArrayLike, qd: npt.ArrayLike) -> FloatArray:
    """Predicted joint accelerations (N, 8) [m/s^2 | rad/s^2] at the samples from the joint
    model q'' = wn^2 (u - q) - 2 zeta wn q' (the command u[k] acting from t_k on)."""
    dyn = robot.dynamics
    return dyn.wn**2 * (np.asarray(u, float) - np.asarray(q, float)) - 2.0 * dyn.zeta * dyn.wn * np.asarray(qd, float)


def smooth_accelerations(robot: Robot, u: npt.ArrayLike, q: npt.ArrayLike, qd: npt.ArrayLike) -> FloatArray:
    """Joint accelerations (N, 8) at the samples t_k without the zero-order hold's ripple:
    the joint model driven by the smooth command at t_k, (u[k-1] + u[k]) / 2 (u[k] is the
    planned command at t_k + dt/2; u[0] for the first sample).

    Under the hold the acceleration jumps by wn^2 (u[k] - u[k-1]) at every sample (up to
    ~1 m/s^2 at the cup in the preparation, ~5 m/s^2 in the toss) and swings back within
    the millisecond; such a zero-mean swing moves the ball by ~jump dt^2 / 12 < 1
    micrometre, so the ball feels the mean, which is this value (it equals the second
    difference of the predicted positions to O(dt^2))."""
    U = np.asarray(u, float)
    mid = 0.5 * (np.vstack([U[:1], U[:-1]]) + U)
    return joint_accelerations(robot, mid, q, qd)


def _default_drag() -> float:
    from studio.physics.ball import DEFAULT_FLIGHT

    return float(DEFAULT_FLIGHT.drag_constant)


def cup_specific_force(
    robot: Robot,
    q: npt.ArrayLike,
    qd: npt.ArrayLike,
    qdd: npt.ArrayLike,
    *,
    gravity: float = C.GRAVITY,
    drag_k: float = 0.0,
) -> FloatArray:
    """Specific force the cup gives the ball, f = a - g + k |v| v (N, 3) [m/s^2], of the
    ball's centre in the cup (frame ``ball_cup``), in the cup frame (z = cup axis = face-A
    normal), at joint states (N, 8) each: pinocchio's classical acceleration a and velocity
    v of the frame (centripetal terms included), the ball's drag constant ``drag_k`` [1/m]."""
    Q, V, A = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (q, qd, qdd))
    if not (Q.shape == V.shape == A.shape and Q.shape[1:] == (robot.nq,)):
        raise InvalidInputError(
            f"cup_specific_force: q, qd, qdd must all be (N, {robot.nq}), got {Q.shape}, {V.shape}, {A.shape}"
        )
    model, data, fid = robot.model, robot.data, robot.frame_id(BALL_CUP_FRAME)
    g = np.array([0.0, 0.0, -gravity])
    out = np.empty((Q.shape[0], 3))
    for k in range(Q.shape[0]):
        pin.forwardKinematics(model, data, Q[k], V[k], A[k])
        pin.updateFramePlacement(model, data, fid)
        a = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL).linear
        v = pin.getFrameVelocity(model, data, fid, pin.LOCAL).linear
        out[k] = a - data.oMf[fid].rotation.T @ g + drag_k * np.linalg.norm(v) * v
    return out


@dataclass(frozen=True)
class CupHoldCheck:
    """The cup's specific force along a motion against its :class:`CupGrip`."""

    limit: float
    """Allowed ratio c [-]."""
    worst_ratio: float
    """Largest |f_t| / f_n over the checked samples [-] (inf where f_n <= 0)."""
    at: float
    """Time of the worst ratio [s] (the clock of the checked motion)."""
    min_normal: float
    """Smallest normal load f_n over the checked samples [m/s^2]."""
    t_start: float
    """First checked sample [s]."""
    t_end: float
    """Checked up to (excluding) this time [s] (e.g. the ball's release from the cup)."""

    @property
    def passed(self) -> bool:
        """True when every checked sample lies inside the cone."""
        return self.min_normal > 0.0 and self.worst_ratio <= self.limit

    @property
    def detail(self) -> str:
        """One line for reports."""
        return (
            f"worst f_t/f_n = {self.worst_ratio:.3f} (limit {self.limit:.3f}) at t = {self.at:.3f} s, "
            f"min normal load {self.min_normal:.2f} m/s^2, checked {self.t_start:.3f}-{self.t_end:.3f} s at 1 kHz"
        )

    def to_json(self) -> dict[str, Any]:
        """JSON-ready fields (``worst_ratio`` None where the normal load vanished: inf)."""
        ratio = self.worst_ratio if math.isfinite(self.worst_ratio) else None
        return {
            "passed": self.passed,
            "limit": self.limit,
            "worst_ratio": ratio,
            "at": self.at,
            "min_normal": self.min_normal,
            "t_start": self.t_start,
            "t_end": self.t_end,
        }


def check_cup_hold(
    robot: Robot,
    t: npt.ArrayLike,
    u: npt.ArrayLike,
    q: npt.ArrayLike,
    qd: npt.ArrayLike,
    *,
    t_end: float | None = None,
    grip: CupGrip | None = None,
    drag_k: float | None = None,
) -> CupHoldCheck:
    """Check the ball-in-cup cone at every sample with t_k < ``t_end`` (default: all) of a
    motion: times t (N,) [s], commands u (zero-order hold), predicted joint states q, qd
    (N, 8) each; accelerations without the hold's 1 kHz ripple (:func:`smooth_accelerations`);
    ``drag_k`` [1/m] (default: the flight model's).

    Raises:
        InvalidInputError: no sample to check, or mismatched shapes.
    """
    T = np.asarray(t, dtype=float)
    stop = T.size if t_end is None else int(np.searchsorted(T, t_end, side="left"))
    if stop == 0:
        raise InvalidInputError(f"check_cup_hold: no sample before t_end = {t_end}")
    Q, QD = np.asarray(q, float)[:stop], np.asarray(qd, float)[:stop]
    k_drag = _default_drag() if drag_k is None else drag_k
    f = cup_specific_force(robot, Q, QD, smooth_accelerations(robot, np.asarray(u, float)[:stop], Q, QD), drag_k=k_drag)
    fn, ft = f[:, 2], np.hypot(f[:, 0], f[:, 1])
    ratio = np.where(fn > 0.0, ft / np.where(fn > 0.0, fn, 1.0), np.inf)
    k = int(np.argmax(ratio))
    grip = grip if grip is not None else CupGrip.of(robot)
    end = float(T[stop - 1] + (T[1] - T[0] if T.size > 1 else 0.0)) if t_end is None else float(t_end)
    return CupHoldCheck(grip.limit, float(ratio[k]), float(T[k]), float(fn.min()), float(T[0]), end)
