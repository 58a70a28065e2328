"""Ball physics: flight, table/net/racket impacts and an event-driven simulator.

One analytic ball model serves the fast predictor and the MuJoCo rollout (``DESIGN.md``,
"Ball physics"): the parameters live here, with their sources.

Frames and units: world frame of ``DESIGN.md`` (origin at the centre of the playing
surface, +X towards the receiver, +Z up), SI units: positions [m], velocities [m/s],
spins (angular velocities) [rad/s]. The racket frame is that of :mod:`studio.constants`
(origin at the blade centre on its mid-plane, z = face-A normal, y towards the blade
tip, x = y cross z).

Sign conventions (checked by the tests):

- Magnus force along ``w x v``: a ball travelling +X with topspin ``w_y > 0`` is pushed
  down (-Z); with ``w_z > 0`` (counter-clockwise seen from above) it curves to +Y, i.e.
  to its left.
- :func:`spin_components` uses the paper's velocity-aligned frame: ``e_x = v/|v|``,
  ``e_y = e_z x e_x`` horizontal, ``e_z = e_x x e_y`` pointing up. For a ball
  travelling +X, ``e_y = +Y`` so ``w . e_y = w_y > 0`` is topspin, ``w . e_z = w_z``
  is sidespin and ``w . e_x`` is the cork (gyro) spin.

Contents:

- :class:`BallState`, :class:`FlightModel` (gravity, quadratic drag, saturating Magnus
  lift, spin decay);
- :class:`TableBounceModel` (friction/restitution impulse model with sliding and rolling
  regimes), :class:`NetModel` (inelastic net, rigid posts), :class:`RacketModel`
  (rubber impact model calibrated on measured bounces, see :mod:`studio.physics.ball_calibration`);
- :class:`RacketState`, :class:`RacketMotion`, :class:`SampledRacketMotion` (the moving
  racket);
- :func:`simulate` -> :class:`Trajectory` with :class:`Event` records (table, net,
  floor, racket), every event located in time by root finding on the dense output of a
  fixed-step RK4 integrator.
"""

from __future__ import annotations

import bisect
import functools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from scipy.optimize import brentq, minimize_scalar
from scipy.spatial.transform import Rotation

from studio import constants as C
from studio.errors import DataFileError, InvalidInputError
from studio.paths import DATA_DIR
from studio.physics.court import DEFAULT_COURT, Court
from studio.storage.jsonfile import not_utf8

FloatArray = npt.NDArray[np.float64]

EventKind = Literal["table", "net", "floor", "racket", "obstacle"]

RACKET_DATA_DIR = DATA_DIR / "racket_bounces"
"""Shipped racket-bounce measurements and the calibrated racket models (JSON)."""

RACKET_MODELS_JSON = RACKET_DATA_DIR / "racket_models.json"
"""Calibrated :class:`RacketModel` parameters with their fit figures, written by
``serve-studio calibrate --write``."""

DEFAULT_RACKET = "racket_01"
"""Racket of the serve robot: an offensive blade with offensive inverted rubber."""


# =====================================================================================
# Validation helpers
# =====================================================================================


def _vec3(value: npt.ArrayLike, what: str) -> FloatArray:
    """A finite (3,) float array copy of ``value`` or InvalidInputError naming ``what``."""
    try:
        arr = np.array(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{what}: expected a 3-vector of numbers, got {value!r}") from exc
    if arr.shape != (3,):
        raise InvalidInputError(f"{what}: expected a 3-vector, got shape {np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{what}: must be finite, got {arr.tolist()}")
    return arr


def _rows3(value: npt.ArrayLike, what: str) -> tuple[FloatArray, bool]:
    """(N, 3) finite float array and whether the input was a single (3,) vector."""
    arr = np.asarray(value, dtype=float)
    single = arr.ndim == 1
    arr = np.atleast_2d(arr)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"{what}: expected shape (3,) or (N, 3), got {np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{what}: must be finite")
    return arr, single


def _finite_param(obj: object, name: str, lo: float | None = None, hi: float | None = None) -> None:
    """Check a float field of a parameter dataclass; InvalidInputError naming it."""
    val = getattr(obj, name)
    cls = type(obj).__name__
    if not isinstance(val, (int, float)) or not math.isfinite(val):
        raise InvalidInputError(f"{cls}.{name} must be a finite number, got {val!r}")
    if lo is not None and val < lo:
        raise InvalidInputError(f"{cls}.{name} must be >= {lo}, got {val!r}")
    if hi is not None and val > hi:
        raise InvalidInputError(f"{cls}.{name} must be <= {hi}, got {val!r}")


# =====================================================================================
# Ball state and flight
# =====================================================================================


@dataclass(frozen=True, slots=True)
class BallState:
    """Ball centre position, velocity and spin, world frame (SI units)."""

    p: FloatArray
    """Position of the ball centre [m], (3,)."""
    v: FloatArray
    """Velocity [m/s], (3,)."""
    w: FloatArray
    """Angular velocity (spin) [rad/s], (3,)."""

    def __post_init__(self) -> None:
        for name in ("p", "v", "w"):
            arr = _vec3(getattr(self, name), f"BallState.{name}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def as_vector(self) -> FloatArray:
        """State as one (9,) vector ``[p, v, w]``."""
        return np.concatenate([self.p, self.v, self.w])


@dataclass(frozen=True, slots=True)
class FlightModel:
    """Ball flight in still air: gravity, quadratic drag, Magnus lift and spin decay.

    Equations (world frame, ``K = rho A / (2 m)`` [1/m], ``A = pi r^2``)::

        a  = -g e_z - K C_D |v| v + K C_L(S) |v|^2 (w x v) / |w_perp x v|
        dw/dt = -spin_decay * |v| * w

    with ``w_perp`` the spin component perpendicular to ``v`` (spin about the flight
    direction, "cork", makes no lift) and ``S = r |w_perp| / |v|`` the spin ratio.
    The lift coefficient saturates::

        C_L(S) = S / (lift_a + lift_b S)

    so that ``C_L ~ S / lift_a`` for small S (the linear Magnus law) and
    ``C_L -> 1 / lift_b`` for large S. Written out the Magnus acceleration is
    ``K r |v| (w x v) / (lift_a |v| + lift_b r |w_perp|)``: smooth, no division by zero.

    Parameters: fitted on real match flights (:mod:`studio.physics.flight_calibration`): the
    Ace public match data, SonyResearch/ace_public ``data/match_data.csv`` (Nature 652,
    2026), players Elite A, Elite B, Elite C and Pro 1 (210 rallies, 1,105 flights with
    a measured landing: 210 serves racket -> first bounce, 210 serves first -> second
    bounce, 685 rally shots -> bounce). Each flight is flown from its measured
    post-event state to the table and the landing point and time are compared with the
    measured bounce; drag and lift law by robust least squares (soft-L1, 1 ms of landing
    time ~ 5 mm), jointly with the data's velocity lag (the measured post-event velocities
    behave as the velocity 18.7 ms after the event, see
    :data:`studio.physics.flight_calibration.VELOCITY_LAG`). Leave-one-player-out CV gives the same
    parameters within C_D 0.556-0.563, lift_a 0.16-0.28, lift_b 3.24-3.49; held-out
    landing errors (median, pooled over the 4 folds): serves racket -> first bounce
    23 mm (previous model 53 mm), first -> second bounce 31 mm (122), rally shots 57 mm
    (152; p90 164 vs 407 mm); landed flights predicted into the net 23 of 1,105 (223),
    a Monte Carlo of the data's own state noise alone gives ~14. The record is
    ``studio/data/flight_model.json``.

    - ``C_D = 0.559``: above the 0.40-0.50 of a smooth non-spinning sphere at
      Re ~ 1e4-5e4 (Achenbach, J. Fluid Mech. 54 (1972) 565); the fit may absorb
      effects the model leaves out (drag growing with spin, the data's velocity
      estimates). Rally flights fix it: 0.556-0.563 in every cross-validation fold.
    - Lift law (form kept, parameters fitted): ``lift_a = 0.235, lift_b = 3.336``:
      C_L = 0.18 at S = 0.1, 0.23 at S = 0.25, 0.26 at S = 0.5, 0.28 at S = 1, saturating
      at 1/lift_b = 0.30 (the previous 1/(2 + 1/S) reached 0.33 at S = 1 and 0.5 at large
      S, too much down-force on heavy topspin drives, which it sent into the net). Within
      the 0.15-0.35 measured on spinning balls at S = 0.1-1 (Nathan, Am. J. Phys. 76
      (2008) 119; Sawicki, Hubbard & Stronge, Am. J. Phys. 71 (2003) 1152). An
      exponential saturation and a law with a maximum fitted no better.
    - ``spin_decay = 0.0107`` [1/m]: spin decays as ``exp(-spin_decay * distance)``.
      The landings do not determine it (the fit cost changes < 0.1 % between 0 and
      0.12 /m); measured from the data's vertical spin ``w_z``, which the table bounce
      keeps: median loss of |w_z| per metre over the flights ending at a bounce
      (:func:`studio.physics.flight_calibration.spin_decay_from_bounces`; an upper bound if the
      table takes some ``w_z``). Close to the previous order-of-magnitude estimate 0.008
      (air torque ``C_m rho w^2 r^5 / 2``, ``C_m ~ 0.05``, on the shell's inertia; the
      velocity-proportional form follows Nathan, "The effect of spin-down on the flight
      of a baseball", 2008).
    """

    gravity: float = C.GRAVITY
    """Gravitational acceleration [m/s^2] (along -Z)."""
    air_density: float = C.AIR_DENSITY
    """Air density [kg/m^3]."""
    drag_coefficient: float = 0.559
    """Drag coefficient C_D [-] (fitted on the Ace match flights, see the class docstring)."""
    lift_a: float = 0.235
    """Small-spin-ratio parameter of C_L(S) = S / (lift_a + lift_b S) [-]: slope 1/lift_a
    (fitted on the Ace match flights)."""
    lift_b: float = 3.336
    """Saturation parameter of C_L(S) = S / (lift_a + lift_b S) [-]: C_L -> 1/lift_b
    (fitted on the Ace match flights)."""
    spin_decay: float = 0.0107
    """Spin decay per metre of flight [1/m]: dw/dt = -spin_decay |v| w (measured from the
    vertical spin of the Ace match flights, see the class docstring)."""
    radius: float = C.BALL_RADIUS
    """Ball radius [m] (ITTF Law 2.3.1)."""
    mass: float = C.BALL_MASS
    """Ball mass [kg] (ITTF Law 2.3.2)."""

    def __post_init__(self) -> None:
        for name in ("gravity", "air_density", "drag_coefficient", "spin_decay"):
            _finite_param(self, name, lo=0.0)
        _finite_param(self, "lift_a", lo=1e-6)
        _finite_param(self, "lift_b", lo=0.0)
        _finite_param(self, "radius", lo=1e-6)
        _finite_param(self, "mass", lo=1e-9)

    @property
    def k_air(self) -> float:
        """``K = rho A / (2 m)`` [1/m], A the ball cross-section."""
        return self.air_density * math.pi * self.radius**2 / (2.0 * self.mass)

    @property
    def drag_constant(self) -> float:
        """Quadratic drag constant ``k = rho C_D A / (2 m)`` [1/m]: ``a_drag = -k |v| v``."""
        return self.k_air * self.drag_coefficient

    def lift_coefficient(self, spin_ratio: npt.ArrayLike) -> FloatArray:
        """C_L(S) = S / (lift_a + lift_b S) [-] for spin ratios S = r |w_perp| / |v| >= 0."""
        s = np.asarray(spin_ratio, dtype=float)
        return s / (self.lift_a + self.lift_b * s)

    def without_air(self) -> FlightModel:
        """The same model in vacuum (no drag, no lift, no spin decay)."""
        return FlightModel(
            gravity=self.gravity,
            air_density=0.0,
            drag_coefficient=self.drag_coefficient,
            lift_a=self.lift_a,
            lift_b=self.lift_b,
            spin_decay=0.0,
            radius=self.radius,
            mass=self.mass,
        )

    def acceleration(self, p: npt.ArrayLike, v: npt.ArrayLike, w: npt.ArrayLike) -> FloatArray:
        """Ball acceleration [m/s^2], world frame.

        Args:
            p: positions (3,) or (N, 3) [m] (unused: uniform field, kept for the ODE form).
            v: velocities (3,) or (N, 3) [m/s].
            w: spins (3,) or (N, 3) [rad/s].

        Returns:
            Accelerations with the shape of ``v``.
        """
        del p
        v = np.asarray(v, dtype=float)
        w = np.asarray(w, dtype=float)
        k = self.k_air
        speed = np.linalg.norm(v, axis=-1, keepdims=True)
        wv = np.sum(w * v, axis=-1, keepdims=True)
        w2 = np.sum(w * w, axis=-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            wpar2 = np.where(speed > 0.0, wv * wv / np.maximum(speed * speed, 1e-300), 0.0)
        wperp = np.sqrt(np.maximum(w2 - wpar2, 0.0))
        denom = self.lift_a * speed + self.lift_b * self.radius * wperp
        lift = np.where(denom > 0.0, k * self.radius * speed / np.where(denom > 0.0, denom, 1.0), 0.0)
        a = -k * self.drag_coefficient * speed * v + lift * np.cross(w, v)
        a[..., 2] -= self.gravity
        return a

    def spin_derivative(self, v: npt.ArrayLike, w: npt.ArrayLike) -> FloatArray:
        """dw/dt [rad/s^2] = -spin_decay |v| w, shapes as :meth:`acceleration`."""
        v = np.asarray(v, dtype=float)
        w = np.asarray(w, dtype=float)
        return -self.spin_decay * np.linalg.norm(v, axis=-1, keepdims=True) * w

    def energy(self, p: npt.ArrayLike, v: npt.ArrayLike, w: npt.ArrayLike) -> FloatArray:
        """Mechanical energy [J]: translational + rotational kinetic + potential (z = 0 ref).

        Shapes: (3,) -> scalar array, (N, 3) -> (N,).
        """
        p = np.asarray(p, dtype=float)
        v = np.asarray(v, dtype=float)
        w = np.asarray(w, dtype=float)
        inertia = 2.0 / 3.0 * self.mass * self.radius**2
        return (
            0.5 * self.mass * np.sum(v * v, axis=-1)
            + 0.5 * inertia * np.sum(w * w, axis=-1)
            + self.mass * self.gravity * p[..., 2]
        )

    def scalar_derivative(self) -> Callable[[Sequence[float]], list[float]]:
        """Fast derivative of the 9-state ``[p, v, w]`` on Python floats (same equations
        as :meth:`acceleration` / :meth:`spin_derivative`; the tests compare them)."""
        k = self.k_air
        kd = k * self.drag_coefficient
        kr = k * self.radius
        la = self.lift_a
        lbr = self.lift_b * self.radius
        g = self.gravity
        sd = self.spin_decay
        sqrt = math.sqrt

        def deriv(y: Sequence[float]) -> list[float]:
            vx, vy, vz, wx, wy, wz = y[3], y[4], y[5], y[6], y[7], y[8]
            s2 = vx * vx + vy * vy + vz * vz
            sp = sqrt(s2)
            wv = wx * vx + wy * vy + wz * vz
            w2 = wx * wx + wy * wy + wz * wz
            wp2 = w2 - wv * wv / s2 if s2 > 0.0 else w2
            denom = la * sp + lbr * sqrt(wp2 if wp2 > 0.0 else 0.0)
            lift = kr * sp / denom if denom > 0.0 else 0.0
            drag = -kd * sp
            dec = -sd * sp
            return [
                vx,
                vy,
                vz,
                drag * vx + lift * (wy * vz - wz * vy),
                drag * vy + lift * (wz * vx - wx * vz),
                drag * vz + lift * (wx * vy - wy * vx) - g,
                dec * wx,
                dec * wy,
                dec * wz,
            ]

        return deriv


def spin_components(v: npt.ArrayLike, w: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Spin in the paper's velocity-aligned frame: ``(topback, side, cork)`` [rad/s].

    ``e_x = v/|v|``, ``e_y = e_z x e_x`` normalized (horizontal, perpendicular to e_x),
    ``e_z = e_x x e_y`` (up). ``topback = w . e_y`` (topspin > 0: for a ball travelling
    +X, ``e_y = +Y`` and topspin is ``w_y > 0``), ``side = w . e_z`` (> 0:
    counter-clockwise seen from above, the ball curves to its left), ``cork = w . e_x``.
    For a (near) vertical or zero velocity ``e_x`` falls back to +X / ``e_y`` to +Y
    (as :func:`studio.serve.reward.velocity_frame`).

    Args:
        v: velocities (3,) or (N, 3) [m/s].
        w: spins, same shape [rad/s].

    Returns:
        Three arrays of shape () or (N,).
    """
    v = np.asarray(v, dtype=float)
    w = np.asarray(w, dtype=float)
    speed = np.linalg.norm(v, axis=-1, keepdims=True)
    ex = np.where(speed > 1e-9, v / np.where(speed > 1e-9, speed, 1.0), np.array([1.0, 0.0, 0.0]))
    ey = np.cross(np.array([0.0, 0.0, 1.0]), ex)
    n = np.linalg.norm(ey, axis=-1, keepdims=True)
    ey = np.where(n > 1e-9, ey / np.where(n > 1e-9, n, 1.0), np.array([0.0, 1.0, 0.0]))
    ez = np.cross(ex, ey)
    return np.sum(w * ey, axis=-1), np.sum(w * ez, axis=-1), np.sum(w * ex, axis=-1)


# =====================================================================================
# Impact models
# =====================================================================================

_ALPHA_SHELL = C.BALL_MASS * C.BALL_RADIUS**2 / C.BALL_INERTIA
"""m r^2 / I = 3/2 for a thin shell."""


def _tangential_impulse_update(
    v: FloatArray, w: FloatArray, jt: FloatArray, lever: float, mass: float, inertia: float
) -> tuple[FloatArray, FloatArray]:
    """Apply a tangential impulse ``jt`` (N, 2) [N s] at the contact point ``-lever e_z``.

    Local frame: z = contact normal pointing from the surface to the ball. Returns the
    new (v, w) (N, 3); the normal velocity component is left to the caller.
    """
    v2 = v.copy()
    w2 = w.copy()
    v2[:, 0] += jt[:, 0] / mass
    v2[:, 1] += jt[:, 1] / mass
    # torque of J at r_c = -lever e_z: r_c x J = (lever J_y, -lever J_x, 0)
    w2[:, 0] += lever * jt[:, 1] / inertia
    w2[:, 1] -= lever * jt[:, 0] / inertia
    return v2, w2


def _contact_slip(v: FloatArray, w: FloatArray, lever: float) -> FloatArray:
    """Tangential velocity (N, 2) [m/s] of the ball's contact point ``-lever e_z``."""
    return np.stack([v[:, 0] - lever * w[:, 1], v[:, 1] + lever * w[:, 0]], axis=1)


@dataclass(frozen=True, slots=True)
class TableBounceModel:
    """Ball-table impact: restitution plus Coulomb friction with sliding and rolling regimes.

    The model of Nakashima et al., "Modeling of rebound phenomenon of a rigid ball with
    friction and elastic effects" (American Control Conference 2010) for a thin-shell
    ball (``I = 2/3 m r^2``, ``alpha = m r^2 / I = 3/2``), local frame z = surface normal::

        v_z'  = -e v_z
        u     = (v_x - r w_y, v_y + r w_x)                contact-point slip
        sliding if |u| > (1 + alpha) mu (1 + e) |v_z|:   J_t = -mu m (1 + e) |v_z| u/|u|
        rolling otherwise:                                J_t = -m u / (1 + alpha)
        v_t' = v_t + J_t / m,  w' = w + r (-e_z) x J_t / I,  w_z' = w_z

    The contact point never reverses its slip, so no bounce gains energy.

    ``restitution`` is tuned so that the ITTF Law 2.1.3 drop test (ball dropped from
    30 cm onto the surface, air drag of the default :class:`FlightModel` included)
    bounces to 23.0 cm (:func:`studio.physics.ball_calibration.tune_table_restitution`).

    ``friction = 0.23`` is fitted on 1,091 real bounces of the Ace public match data
    (SonyResearch/ace_public ``data/match_data.csv``, players Elite A, Elite B, Elite C,
    Pro 1; :func:`studio.physics.flight_calibration.fit_table_friction`): the model applied to
    the pre-bounce state predicted by the flight model from the previous event, compared
    with the measured post-bounce horizontal velocity and spin (robust least squares).
    Previously 0.25, mid-range of the 0.2-0.3 reported for table-tennis tables (Nakashima
    et al. 2010 identified ~0.25). Spin gained towards rolling on the sliding bounces
    (67 % of them), per m/s of incoming vertical speed: data 33.8, model 32.8 rad/s (the
    previous flight and table models on the raw data: 35.0 and 35.6). Median post-bounce errors 0.31 m/s and 20 rad/s (RMS 0.93 m/s,
    79 rad/s: a few gross outliers). Not modelled: the data's post-bounce vertical speed
    is 1.0 times the predicted incoming one (median, with the velocity-lag correction of
    :data:`studio.physics.flight_calibration.VELOCITY_LAG`; 0.94 without), above the drop-test
    restitution; the restitution is kept on the ITTF drop test.
    """

    restitution: float = 0.9125
    """Normal coefficient of restitution e [-]: drop test 30 cm -> 23.0 cm with the
    default :class:`FlightModel` (tuned, see the class docstring)."""
    friction: float = 0.23
    """Coulomb friction coefficient mu [-] between ball and table (fitted on the Ace
    match bounces, see the class docstring)."""
    radius: float = C.BALL_RADIUS
    """Ball radius [m]."""
    mass: float = C.BALL_MASS
    """Ball mass [kg]."""

    def __post_init__(self) -> None:
        _finite_param(self, "restitution", lo=0.0, hi=1.0)
        _finite_param(self, "friction", lo=0.0)
        _finite_param(self, "radius", lo=1e-6)
        _finite_param(self, "mass", lo=1e-9)

    def bounce(self, v_in: npt.ArrayLike, w_in: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Velocity and spin after a bounce on a surface with normal +Z (at rest).

        Args:
            v_in: incoming velocities (3,) or (N, 3) [m/s] (v_z < 0: approaching).
            w_in: incoming spins, same shape [rad/s].

        Returns:
            ``(v_out, w_out)`` with the input shape.
        """
        v, single = _rows3(v_in, "TableBounceModel.bounce v_in")
        w, _ = _rows3(w_in, "TableBounceModel.bounce w_in")
        if v.shape != w.shape:
            raise InvalidInputError(f"TableBounceModel.bounce: v_in {v.shape} and w_in {w.shape} differ in shape")
        r, m, e, mu = self.radius, self.mass, self.restitution, self.friction
        inertia = 2.0 / 3.0 * m * r * r
        alpha = m * r * r / inertia
        vn = np.minimum(v[:, 2], 0.0)  # only an approaching ball is pushed
        u = _contact_slip(v, w, r)
        un = np.linalg.norm(u, axis=1)
        jn = m * (1.0 + e) * (-vn)  # normal impulse [N s]
        j_roll = -m * u / (1.0 + alpha)
        with np.errstate(invalid="ignore", divide="ignore"):
            j_slide = -mu * jn[:, None] * u / np.where(un > 0.0, un, 1.0)[:, None]
        sliding = np.linalg.norm(j_roll, axis=1) > mu * jn
        jt = np.where(sliding[:, None], j_slide, j_roll)
        v_out, w_out = _tangential_impulse_update(v, w, jt, r, m, inertia)
        v_out[:, 2] = v[:, 2] + jn / m
        if single:
            return v_out[0], w_out[0]
        return v_out, w_out


@dataclass(frozen=True, slots=True)
class NetModel:
    """Ball impacts on the net (soft mesh) and on the net posts (rigid).

    The net absorbs most of the ball's energy (a slack mesh): the normal velocity
    component is reversed with a small restitution, the tangential one and the spin are
    damped. Posts are rigid plastic/metal clamps: a plain restitution on the normal
    component, tangential velocity and spin kept. Both are assumptions (the laws fix no
    such numbers); a serve touching the net assembly is illegal or a let anyway, so
    only the qualitative outcome matters (the ball drops near the net).
    """

    net_restitution: float = 0.1
    """Normal restitution of the net mesh [-] (assumption: the ball nearly stops)."""
    net_tangential_retention: float = 0.5
    """Fraction of the tangential velocity kept at a net impact [-] (assumption)."""
    net_spin_retention: float = 0.5
    """Fraction of the spin kept at a net impact [-] (assumption)."""
    post_restitution: float = 0.5
    """Normal restitution of the net posts [-] (assumption: hard clamp)."""

    def __post_init__(self) -> None:
        for name in ("net_restitution", "net_tangential_retention", "net_spin_retention", "post_restitution"):
            _finite_param(self, name, lo=0.0, hi=1.0)

    def bounce(
        self, v_in: FloatArray, w_in: FloatArray, normal: FloatArray, part: Literal["net", "post"]
    ) -> tuple[FloatArray, FloatArray]:
        """Velocity and spin (3,) after hitting the net or a post with outward ``normal`` (3,)."""
        n = np.asarray(normal, dtype=float)
        vn = float(v_in @ n)
        if vn >= 0.0:
            return v_in.copy(), w_in.copy()
        vt = v_in - vn * n
        if part == "net":
            v_out = self.net_tangential_retention * vt - self.net_restitution * vn * n
            return v_out, self.net_spin_retention * w_in
        return vt - self.post_restitution * vn * n, w_in.copy()


@dataclass(frozen=True, slots=True)
class RacketModel:
    """Ball-rubber impact in the racket frame (z = face normal towards the ball), relative to the racket.

    A rigid-ball impulse model with an elastic rubber (the "k_p" tangential compliance
    model of Gossard et al., see ``studio/data/racket_bounces/README.md``), extended for
    the brushing contacts of serves (``studio/data/robot_serve_contacts/README.md``): a
    compliance that falls with the slip speed, a smooth friction saturation, restitution
    that depends on the impact, a return of part of the tangential energy lost into the
    normal rebound, an effective lever arm and torsional friction. With ``v_n = -v_z > 0``
    the approach speed, ``l = lever_ratio * r``, ``m* = 1 / (1/m + l^2/I)``,
    ``I = 2/3 m r^2``, all velocities and spins relative to the racket::

        u    = (v_x - l w_y, v_y + l w_x)                  slip of the contact point
        k    = clip(k0 + k1 v_n + k2 tanh(|u| / u_k), -1, 1)
        e_b  = clip(e0 - e1 v_n, 0, 1)
        J_e  = -m* (1 + k) u                               elastic-rubber impulse
        J_t  = J_e  J_max tanh(|J_e| / J_max) / |J_e|,  J_max = mu m (1 + e_b) v_n
        e    = clip(e_b - e2 |J_t| / (m v_n), 0, 1)       slip work lowers the rebound
        v_t' = v_t + J_t/m,   w_xy' = w_xy + l (-e_z x J_t)_xy / I
        v_z' = min(sqrt((e v_n)^2 + 2 eta dE_t / m), v_n)    dE_t: in-plane kinetic energy lost
        w_z' = w_z - sign(w_z) min(|w_z|, tau r m (1 + e) v_n / I)   torsional friction

    ``k`` is the fraction of the contact point's slip that the elastic rubber reverses (0:
    the ball leaves rolling, 1: elastic reversal). ``J_max tanh(|J_e| / J_max)`` is a
    smooth Coulomb limit: the impulse follows the elastic one while it is small and
    saturates at ``J_max``. ``eta`` returns that fraction of the in-plane energy lost into
    the normal rebound, never beyond an elastic normal reversal (``v_z' <= v_n``): a
    tangentially sheared rubber springs back partly along the normal. The fit leaves it
    nearly idle (``eta`` ~ 0.02 on racket_01): referenced to the racket centre's velocity
    the serve contacts seemed to rebound above ``e_b v_n`` at large slip, but most of that
    was the racket's rotation (``omega x d``), which :meth:`bounce_moving` now takes into
    account. The cap keeps the term bounded where the data end (a loose brush at
    ``v_n`` -> 0 does not launch the ball off the face).

    Physically sound by construction (tested on random impacts): isotropic in the face
    plane; the contact point's slip becomes ``(1 - s (1 + k)) u`` with
    ``0 <= s (1 + k) <= 2`` (``s = tanh(x)/x <= 1``), so the in-plane energy cannot grow
    (``dE_t >= 0``); the normal energy is ``e^2`` of the incoming one plus
    ``eta <= 1`` of ``dE_t``; torsional friction only slows ``w_z``. No impact gains
    energy relative to the racket.

    Moving racket (:meth:`bounce_moving`): the ball's velocity relative to the
    racket-fixed point at its centre and its spin relative to the racket's angular
    velocity enter the map (the contact point's slip is then exact); the
    racket's velocity and angular velocity are added back to the result (the scoring
    rule of the robot serve contacts' README).

    Parameters: :meth:`default` loads the joint fit on racket_01 (Gossard's competition
    racket at rest) and the Ace robot's serve contacts from
    ``studio/data/racket_bounces/racket_models.json``, with its cross-validated errors;
    :func:`studio.physics.ball_calibration.calibrate_racket` refits.

    Extrapolation below the data (normal speeds under ~2.5 m/s): restitution and
    compliance are linear in ``v_n`` and bounded by their clips; the friction limit is
    proportional to the normal impulse, so a brushing contact with a small normal speed
    still gives at most ``mu (1 + e_b) v_n`` of tangential velocity change (with the
    fitted ``mu ~ 3`` about ``6 v_n``): spin keeps growing with the racket's tangential
    speed up to that bound, then saturates. Whether real rubber grips more (adhesion) at
    very low load is not in the data.
    """

    restitution_0: float = 0.92
    """e0: normal restitution extrapolated to zero approach speed [-]."""
    restitution_slope: float = 0.022
    """e1: decrease of the restitution per m/s of normal approach speed [s/m]."""
    restitution_slip: float = 0.0
    """e2: decrease of the restitution per unit of tangential velocity change relative to
    the approach speed, |J_t| / (m v_n) [-]."""
    compliance_0: float = 0.63
    """k0: tangential compliance (fraction of the contact-point slip reversed) [-]."""
    compliance_slope: float = 0.0
    """k1: change of the compliance per m/s of normal approach speed [s/m]."""
    compliance_slip: float = 0.0
    """k2: change of the compliance with the slip speed, times tanh(|u| / u_k) [-]."""
    compliance_slip_speed: float = 10.0
    """u_k: slip speed scale of the compliance's slip term [m/s]."""
    friction: float = 3.0
    """mu: smooth Coulomb limit of the tangential impulse relative to the normal one [-]."""
    lever_ratio: float = 1.0
    """l / r: effective lever arm of the contact force relative to the ball radius [-]
    (< 1 when the ball sinks into the sponge)."""
    torsion: float = 1.0
    """tau: torsional friction arm relative to r [-]: |dw_z| <= tau r J_n / I."""
    normal_return: float = 0.0
    """eta: fraction of the in-plane kinetic energy lost at the contact that returns into
    the normal rebound [-], in [0, 1]."""
    name: str = "uncalibrated"
    """Identifier of the racket the parameters belong to."""
    cv_rms_velocity: float | None = None
    """k-fold cross-validated RMS of the outgoing velocity error norm [m/s] (fit record,
    racket-at-rest rows)."""
    cv_rms_spin: float | None = None
    """k-fold cross-validated RMS of the outgoing spin error norm [rad/s] (fit record,
    racket-at-rest rows)."""
    radius: float = C.BALL_RADIUS
    """Ball radius [m]."""
    mass: float = C.BALL_MASS
    """Ball mass [kg]."""

    def __post_init__(self) -> None:
        _finite_param(self, "restitution_0", lo=0.0, hi=1.5)
        _finite_param(self, "restitution_slope", lo=-1.0, hi=1.0)
        _finite_param(self, "restitution_slip", lo=0.0, hi=1.0)
        _finite_param(self, "compliance_0", lo=-1.0, hi=1.0)
        _finite_param(self, "compliance_slope", lo=-1.0, hi=1.0)
        _finite_param(self, "compliance_slip", lo=-2.0, hi=2.0)
        _finite_param(self, "compliance_slip_speed", lo=1e-3, hi=1e3)
        _finite_param(self, "friction", lo=1e-6)
        _finite_param(self, "lever_ratio", lo=0.1, hi=1.0)
        _finite_param(self, "torsion", lo=0.0)
        _finite_param(self, "normal_return", lo=0.0, hi=1.0)
        _finite_param(self, "radius", lo=1e-6)
        _finite_param(self, "mass", lo=1e-9)

    # -- construction -----------------------------------------------------------------

    PARAMETERS = (
        "restitution_0",
        "restitution_slope",
        "restitution_slip",
        "compliance_0",
        "compliance_slope",
        "compliance_slip",
        "compliance_slip_speed",
        "friction",
        "lever_ratio",
        "torsion",
        "normal_return",
    )
    """Names of the fitted parameters, in the order of :meth:`from_vector`."""

    def as_vector(self) -> FloatArray:
        """The fitted parameters as a vector (order :attr:`PARAMETERS`)."""
        return np.array([getattr(self, n) for n in self.PARAMETERS], dtype=float)

    @classmethod
    def from_vector(cls, x: npt.ArrayLike, **kwargs: object) -> RacketModel:
        """Model from a parameter vector (order :attr:`PARAMETERS`) plus keyword fields."""
        x = np.asarray(x, dtype=float)
        return cls(**{n: float(val) for n, val in zip(cls.PARAMETERS, x, strict=True)}, **kwargs)  # type: ignore[arg-type]

    @classmethod
    def default(cls) -> RacketModel:
        """Parameters calibrated on racket_01 (competition racket), see :meth:`for_racket`."""
        return cls.for_racket(DEFAULT_RACKET)

    @classmethod
    def for_racket(cls, name: str) -> RacketModel:
        """Calibrated parameters of a measured racket (``racket_01``, ``racket_03``).

        Raises:
            DataFileError: the JSON file is missing, malformed or lacks the racket.
        """
        models = _load_racket_models(RACKET_MODELS_JSON)
        if name not in models:
            raise DataFileError(RACKET_MODELS_JSON, f"no racket model {name!r} (have {sorted(models)})")
        return models[name]

    # -- impact -----------------------------------------------------------------------

    def bounce(self, v_in: npt.ArrayLike, w_in: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Velocity and spin after the impact, racket frame, relative to the racket.

        Args:
            v_in: incoming ball velocities (3,) or (N, 3) [m/s], v_z < 0 (approaching the face).
            w_in: incoming spins, same shape [rad/s].

        Returns:
            ``(v_out, w_out)`` with the input shape. Rows with v_z >= 0 (not
            approaching) are returned unchanged.
        """
        v, single = _rows3(v_in, "RacketModel.bounce v_in")
        w, _ = _rows3(w_in, "RacketModel.bounce w_in")
        if v.shape != w.shape:
            raise InvalidInputError(f"RacketModel.bounce: v_in {v.shape} and w_in {w.shape} differ in shape")
        m, r = self.mass, self.radius
        inertia = 2.0 / 3.0 * m * r * r
        lever = self.lever_ratio * r
        vn = np.maximum(-v[:, 2], 0.0)
        hit = vn > 0.0
        jt, e_b = self._tangential_impulse(v, w, vn, lever)
        jnorm = np.linalg.norm(jt, axis=1)
        e = np.clip(e_b - self.restitution_slip * (jnorm / m) / np.where(hit, vn, 1.0), 0.0, 1.0)
        v_out, w_out = _tangential_impulse_update(v, w, jt, lever, m, inertia)
        lost = 0.5 * (np.sum(v[:, :2] ** 2, axis=1) - np.sum(v_out[:, :2] ** 2, axis=1))
        lost += 0.5 * inertia / m * (np.sum(w[:, :2] ** 2, axis=1) - np.sum(w_out[:, :2] ** 2, axis=1))
        vz_out = np.minimum(np.sqrt((e * vn) ** 2 + 2.0 * self.normal_return * np.maximum(lost, 0.0)), vn)
        v_out[:, 2] = np.where(hit, vz_out, v[:, 2])
        dwz_max = self.torsion * r * m * (1.0 + e) * vn / inertia
        wz = w[:, 2]
        w_out[:, 2] = wz - np.sign(wz) * np.minimum(np.abs(wz), dwz_max)
        if single:
            return v_out[0], w_out[0]
        return v_out, w_out

    def _tangential_impulse(
        self, v: FloatArray, w: FloatArray, vn: FloatArray, lever: float
    ) -> tuple[FloatArray, FloatArray]:
        """Tangential impulse (N, 2) [N s] (zero where ``vn == 0``) and the base restitution e_b (N,)."""
        m, r = self.mass, self.radius
        m_eff = 1.0 / (1.0 / m + lever * lever / (2.0 / 3.0 * m * r * r))
        u = _contact_slip(v, w, lever)
        un = np.linalg.norm(u, axis=1)
        k = self.compliance_0 + self.compliance_slope * vn
        k = np.clip(k + self.compliance_slip * np.tanh(un / self.compliance_slip_speed), -1.0, 1.0)
        e_b = np.clip(self.restitution_0 - self.restitution_slope * vn, 0.0, 1.0)
        j_el = m_eff * (1.0 + k) * un  # |J_e|
        j_max = self.friction * m * (1.0 + e_b) * vn
        ok = (j_el > 0.0) & (j_max > 0.0)
        x = np.where(ok, j_el / np.where(ok, j_max, 1.0), 0.0)
        scale = np.where(ok, np.tanh(x) / np.where(ok, x, 1.0), 0.0)  # smooth Coulomb: |J| = J_max tanh(x)
        return -(m_eff * (1.0 + k) * scale)[:, None] * u, e_b

    def bounce_moving(
        self,
        v_ball: npt.ArrayLike,
        w_ball: npt.ArrayLike,
        racket_R: npt.ArrayLike,
        v_contact: npt.ArrayLike,
        face_sign: float = 1.0,
        omega: npt.ArrayLike | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Impact with a moving racket, world frame.

        The ball velocity relative to the racket-fixed point at its centre and its spin
        relative to the racket's angular velocity are expressed in the face frame
        (z = outward normal of the struck face: ``face_sign * R[:, 2]``; for face B the
        frame is the racket frame turned by pi about its x axis), bounced with
        :meth:`bounce`, and mapped back with the racket's velocity and angular velocity
        added.

        Args:
            v_ball: ball velocity (3,) [m/s], world frame.
            w_ball: ball spin (3,) [rad/s], world frame.
            racket_R: racket orientation (3, 3): columns = racket axes in the world.
            v_contact: velocity [m/s] (3,) of the racket-fixed point at the ball's centre,
                ``v_racket + omega x (p_ball - p_racket)``: with the spin taken relative to
                ``omega`` the contact point's slip is then exact (the rubber point under the
                ball moves at ``v_contact - omega x (r n)``).
            face_sign: +1 for face A (racket +z side), -1 for face B.
            omega: racket angular velocity (3,) [rad/s], world frame (None: at rest).

        Returns:
            ``(v_out, w_out)``, each (3,), world frame.
        """
        v = _vec3(v_ball, "RacketModel.bounce_moving v_ball")
        w = _vec3(w_ball, "RacketModel.bounce_moving w_ball")
        vc = _vec3(v_contact, "RacketModel.bounce_moving v_contact")
        wr = np.zeros(3) if omega is None else _vec3(omega, "RacketModel.bounce_moving omega")
        R = np.asarray(racket_R, dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise InvalidInputError(
                f"RacketModel.bounce_moving: racket_R must be a finite (3, 3) matrix, got {R.shape}"
            )
        s = 1.0 if face_sign >= 0.0 else -1.0
        F = R * np.array([1.0, s, s])  # columns x, s*y, s*z: a proper rotation
        v2, w2 = self.bounce(F.T @ (v - vc), F.T @ (w - wr))
        return F @ v2 + vc, F @ w2 + wr

    def to_dict(self) -> dict[str, object]:
        """JSON-ready dict of all fields."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _load_racket_models(path: Path) -> dict[str, RacketModel]:
    """Parse the racket-model JSON (schema 2) into models; DataFileError naming the field."""
    return dict(_load_racket_models_cached(str(path)))


@functools.lru_cache(maxsize=4)
def _load_racket_models_cached(path: str) -> tuple[tuple[str, RacketModel], ...]:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise not_utf8(path, exc) from None
    except OSError as exc:
        raise DataFileError(path, f"cannot read racket models: {exc}") from exc
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataFileError(path, f"invalid JSON at line {exc.lineno}: {exc.msg}") from exc
    if not isinstance(doc, dict) or doc.get("schema") != 2 or not isinstance(doc.get("models"), dict):
        raise DataFileError(path, "expected an object with 'schema': 2 and 'models': {name: {...}}")
    allowed = {f.name for f in fields(RacketModel)}
    out: list[tuple[str, RacketModel]] = []
    for name, entry in doc["models"].items():
        if not isinstance(entry, dict) or not isinstance(entry.get("parameters"), dict):
            raise DataFileError(path, f"models.{name}: expected an object with 'parameters'")
        params = entry["parameters"]
        for key in RacketModel.PARAMETERS:
            if key not in params:
                raise DataFileError(path, f"models.{name}.parameters: missing {key!r}")
        unknown = set(params) - allowed
        if unknown:
            raise DataFileError(path, f"models.{name}.parameters: unknown fields {sorted(unknown)}")
        cv = entry.get("cross_validation")
        cv = cv.get("racket_bounces") if isinstance(cv, dict) else None
        cv = cv if isinstance(cv, dict) else {}
        try:
            model = RacketModel(
                **params,
                name=name,
                cv_rms_velocity=cv.get("rms_velocity"),
                cv_rms_spin=cv.get("rms_spin"),
            )
        except (TypeError, InvalidInputError) as exc:
            raise DataFileError(path, f"models.{name}.parameters: {exc}") from exc
        out.append((name, model))
    return tuple(out)


def _local_frame(n: FloatArray) -> FloatArray:
    """Rotation (3, 3) whose third column is the unit vector ``n``."""
    n = n / np.linalg.norm(n)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, n)
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    return np.stack([x, y, n], axis=1)


def _bounce_on_normal(
    model: TableBounceModel, v: FloatArray, w: FloatArray, n: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Table-model bounce on a static surface with unit normal ``n`` (3,), world frame."""
    if abs(n[2] - 1.0) < 1e-12:
        return model.bounce(v, w)
    F = _local_frame(n)
    v2, w2 = model.bounce(F.T @ v, F.T @ w)
    return F @ v2, F @ w2


# =====================================================================================
# The moving racket
# =====================================================================================


@dataclass(frozen=True, slots=True)
class RacketState:
    """Pose and velocity of the racket frame at one instant, world frame."""

    p: FloatArray
    """Origin of the racket frame (blade centre, mid-plane) [m], (3,)."""
    R: FloatArray
    """Orientation (3, 3): columns are the racket x, y, z axes in the world."""
    v: FloatArray
    """Linear velocity of the racket origin [m/s], (3,)."""
    omega: FloatArray
    """Angular velocity [rad/s], (3,), world frame."""

    def point_velocity(self, point: npt.ArrayLike) -> FloatArray:
        """Velocity [m/s] of the racket-fixed point at world position ``point`` (3,)."""
        return self.v + np.cross(self.omega, np.asarray(point, dtype=float) - self.p)


@runtime_checkable
class RacketMotion(Protocol):
    """A racket moving along a known trajectory during ``[t_start, t_end]``."""

    @property
    def t_start(self) -> float:
        """First instant [s] the racket pose is known."""
        ...

    @property
    def t_end(self) -> float:
        """Last instant [s] the racket pose is known."""
        ...

    def state(self, t: float) -> RacketState:
        """Racket pose and velocity at time ``t`` in ``[t_start, t_end]``."""
        ...


def _rodrigues(rv: FloatArray) -> FloatArray:
    """Rotation matrix (3, 3) of a rotation vector (3,)."""
    th = math.sqrt(float(rv @ rv))
    if th < 1e-12:
        K = np.array([[0.0, -rv[2], rv[1]], [rv[2], 0.0, -rv[0]], [-rv[1], rv[0], 0.0]])
        return np.eye(3) + K
    k = rv / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


def _relative_rotvecs(R: FloatArray) -> FloatArray:
    """Rotation vectors (N-1, 3) of R_i^T R_{i+1} for rotations R (N, 3, 3): the log map
    from the skew part (atan2 of its norm and the trace), scipy's for angles near pi
    where the skew part loses the axis."""
    M = np.einsum("nji,njk->nik", R[:-1], R[1:])
    w = 0.5 * np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], axis=1)
    sn = np.linalg.norm(w, axis=1)
    cs = 0.5 * (M[:, 0, 0] + M[:, 1, 1] + M[:, 2, 2] - 1.0)
    ang = np.arctan2(sn, cs)
    scale = np.where(sn > 1e-12, ang / np.maximum(sn, 1e-300), 1.0)
    out = w * scale[:, None]
    near_pi = cs < -0.9
    if np.any(near_pi):
        out[near_pi] = Rotation.from_matrix(M[near_pi]).as_rotvec()
    return out


class SampledRacketMotion:
    """Racket motion interpolated from samples (e.g. the planner's predicted flange path).

    Positions: cubic spline (``CubicSpline``, or ``CubicHermiteSpline`` when
    velocities are given); velocity = its derivative. Orientations: slerp between
    consecutive samples (constant angular velocity in each interval); ``omega`` from the
    slerp unless given (then interpolated linearly).

    Args:
        t: sample times (N,) [s], strictly increasing, N >= 2.
        p: racket origin positions (N, 3) [m], world frame.
        R: orientations (N, 3, 3), columns = racket axes in the world (proper rotations).
        v: optional origin velocities (N, 3) [m/s].
        omega: optional angular velocities (N, 3) [rad/s], world frame.
    """

    def __init__(
        self,
        t: npt.ArrayLike,
        p: npt.ArrayLike,
        R: npt.ArrayLike,
        *,
        v: npt.ArrayLike | None = None,
        omega: npt.ArrayLike | None = None,
    ) -> None:
        t = np.asarray(t, dtype=float)
        p = np.asarray(p, dtype=float)
        R = np.asarray(R, dtype=float)
        n = t.shape[0] if t.ndim == 1 else -1
        if n < 2:
            raise InvalidInputError(f"SampledRacketMotion: t must be (N,) with N >= 2, got shape {t.shape}")
        if p.shape != (n, 3):
            raise InvalidInputError(f"SampledRacketMotion: p must be ({n}, 3), got {p.shape}")
        if R.shape != (n, 3, 3):
            raise InvalidInputError(f"SampledRacketMotion: R must be ({n}, 3, 3), got {R.shape}")
        for name, arr in (("t", t), ("p", p), ("R", R)):
            if not np.all(np.isfinite(arr)):
                raise InvalidInputError(f"SampledRacketMotion: {name} must be finite")
        if np.any(np.diff(t) <= 0.0):
            raise InvalidInputError("SampledRacketMotion: t must be strictly increasing")
        ortho = np.max(np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)))
        if ortho > 1e-6 or np.any(np.linalg.det(R) < 0.0):
            raise InvalidInputError(
                f"SampledRacketMotion: R must hold proper rotation matrices (max |R^T R - I| = {ortho:.2e})"
            )
        self._t = t
        self._tl = t.tolist()
        if v is not None:
            v = np.asarray(v, dtype=float)
            if v.shape != (n, 3) or not np.all(np.isfinite(v)):
                raise InvalidInputError(f"SampledRacketMotion: v must be finite ({n}, 3), got {v.shape}")
            spline = CubicHermiteSpline(t, p, v, axis=0)
        else:
            spline = CubicSpline(t, p, axis=0)
        self._c = np.ascontiguousarray(np.moveaxis(spline.c, 1, 0))  # (N-1, 4, 3)
        self._R = R.copy()  # not the caller's array: rows are converted lazily
        self._R.setflags(write=False)
        rel = _relative_rotvecs(R)  # body-frame increments (N-1, 3)
        self._rv = rel
        self._omega_slerp = np.einsum("nij,nj->ni", self._R[:-1], rel) / np.diff(t)[:, None]
        if omega is not None:
            omega = np.asarray(omega, dtype=float)
            if omega.shape != (n, 3) or not np.all(np.isfinite(omega)):
                raise InvalidInputError(f"SampledRacketMotion: omega must be finite ({n}, 3), got {omega.shape}")
        self._omega = omega
        self._rows: dict[int, tuple[Any, Any, Any]] = {}  # interval -> python floats (hot path), filled on demand
        # Rigorous bound on the origin speed: per interval |p'| <= 3|c0| h^2 + 2|c1| h + |c2| per axis.
        hs = np.diff(t)[:, None]
        c = self._c
        vb = 3.0 * np.abs(c[:, 0]) * hs**2 + 2.0 * np.abs(c[:, 1]) * hs + np.abs(c[:, 2])
        self._vmax = float(np.max(np.linalg.norm(vb, axis=1)))
        self._p = p

    def _far(
        self, lo: tuple[float, float, float], hi: tuple[float, float, float], ta: float, tb: float, dist: float
    ) -> bool:
        """True if the origin stays farther than ``dist`` [m] from the box [lo, hi] over
        [ta, tb] (conservative: nearest sample plus the speed bound; hot path of :func:`simulate`)."""
        tl = self._tl
        tm = 0.5 * (ta + tb)
        i = min(max(bisect.bisect_right(tl, tm) - 1, 0), len(tl) - 1)
        if i + 1 < len(tl) and tl[i + 1] - tm < tm - tl[i]:
            i += 1
        ox, oy, oz = self._p[i].tolist()
        ti = tl[i]
        rad = self._vmax * max(abs(ta - ti), abs(tb - ti))
        dx = max(lo[0] - ox, 0.0, ox - hi[0])
        dy = max(lo[1] - oy, 0.0, oy - hi[1])
        dz = max(lo[2] - oz, 0.0, oz - hi[2])
        return math.sqrt(dx * dx + dy * dy + dz * dz) - rad > dist

    def _row(self, i: int) -> tuple[Any, Any, Any]:
        """Spline coefficients (4, 3), slerp increment (3,) and R_i (3, 3) of interval i as
        nested lists (converted on first use: a flight touches few intervals)."""
        row = self._rows.get(i)
        if row is None:
            row = self._rows[i] = (self._c[i].tolist(), self._rv[i].tolist(), self._R[i].tolist())
        return row

    def _fast_plane(self, t: float) -> tuple[float, float, float, float, float, float]:
        """Origin and face-A normal at ``t`` as six floats (hot path of :func:`simulate`)."""
        tl = self._tl
        i = min(max(bisect.bisect_right(tl, t) - 1, 0), len(tl) - 2)
        dt = t - tl[i]
        cl, rvl, Ri = self._row(i)
        c0, c1, c2, c3 = cl
        # unrolled (a list comprehension costs a frame per call on this hot path)
        ox = ((c0[0] * dt + c1[0]) * dt + c2[0]) * dt + c3[0]
        oy = ((c0[1] * dt + c1[1]) * dt + c2[1]) * dt + c3[1]
        oz = ((c0[2] * dt + c1[2]) * dt + c2[2]) * dt + c3[2]
        # e_z rotated by the slerp increment (Rodrigues on one vector), then by R_i
        frac = dt / (tl[i + 1] - tl[i])
        kx, ky, kz = rvl
        kx, ky, kz = frac * kx, frac * ky, frac * kz
        th = math.sqrt(kx * kx + ky * ky + kz * kz)
        if th > 1e-12:
            s, cm = math.sin(th) / th, (1.0 - math.cos(th)) / (th * th)
        else:
            s, cm = 1.0, 0.5
        # R(k) e_z = e_z + s (k x e_z) + cm (k x (k x e_z))
        ux = s * ky + cm * kx * kz
        uy = -s * kx + cm * ky * kz
        uz = 1.0 - cm * (kx * kx + ky * ky)
        r0, r1, r2 = Ri
        return (
            ox,
            oy,
            oz,
            r0[0] * ux + r0[1] * uy + r0[2] * uz,
            r1[0] * ux + r1[1] * uy + r1[2] * uz,
            r2[0] * ux + r2[1] * uy + r2[2] * uz,
        )

    @property
    def t_start(self) -> float:
        """First sample time [s]."""
        return float(self._t[0])

    @property
    def t_end(self) -> float:
        """Last sample time [s]."""
        return float(self._t[-1])

    def state(self, t: float) -> RacketState:
        """Interpolated racket state at ``t`` [s] (within ``[t_start, t_end]``)."""
        if not (self._tl[0] - 1e-12 <= t <= self._tl[-1] + 1e-12):
            raise InvalidInputError(f"SampledRacketMotion.state: t = {t} outside [{self._tl[0]}, {self._tl[-1]}]")
        i = min(max(bisect.bisect_right(self._tl, t) - 1, 0), len(self._tl) - 2)
        t0 = self._tl[i]
        dt = t - t0
        c = self._c[i]
        p = ((c[0] * dt + c[1]) * dt + c[2]) * dt + c[3]
        v = (3.0 * c[0] * dt + 2.0 * c[1]) * dt + c[2]
        frac = dt / (self._tl[i + 1] - t0)
        R = self._R[i] @ _rodrigues(frac * self._rv[i])
        if self._omega is None:
            omega = self._omega_slerp[i].copy()
        else:
            omega = (1.0 - frac) * self._omega[i] + frac * self._omega[i + 1]
        return RacketState(p=p, R=R, v=v, omega=omega)


# =====================================================================================
# Simulation
# =====================================================================================


@dataclass(frozen=True, slots=True)
class Event:
    """A ball contact found by :func:`simulate` (world frame, SI units)."""

    kind: EventKind
    """``"table"``, ``"net"`` (net or post, see ``part``), ``"floor"``, ``"racket"``, or
    ``"obstacle"`` (an extra court box of another kind than table/net/post)."""
    t: float
    """Contact instant [s]."""
    p: FloatArray
    """Ball centre at contact [m], (3,)."""
    v_before: FloatArray
    """Velocity just before the impact [m/s], (3,)."""
    v_after: FloatArray
    """Velocity just after the impact [m/s], (3,)."""
    w_before: FloatArray
    """Spin just before [rad/s], (3,)."""
    w_after: FloatArray
    """Spin just after [rad/s], (3,)."""
    part: str
    """Which part was hit: table ``"top"`` (playing surface), ``"edge"`` (its rim, contact
    normal pointing upwards: still the playing surface, ITTF 2.1.2) or ``"side"`` (the
    vertical side of the top, normal not upwards: *not* the playing surface); net
    ``"net"`` or ``"post"``; racket ``"face_a"`` or ``"face_b"``; ``"floor"``; or the
    name of an extra court box (kind ``"obstacle"``)."""
    normal: FloatArray
    """Unit contact normal (3,), pointing from the hit object towards the ball."""
    side: Literal["server", "receiver"] | None = None
    """Table half (x < 0: server) for table and floor events, else None."""


@dataclass(frozen=True, slots=True)
class Trajectory:
    """Ball path from :func:`simulate`, sampled every ``dt_out`` plus the event instants.

    At an event instant the sample holds the state just *after* the impact (the state
    just before is in the :class:`Event`).
    """

    t: FloatArray
    """Sample times (N,) [s], increasing."""
    p: FloatArray
    """Ball centre positions (N, 3) [m]."""
    v: FloatArray
    """Velocities (N, 3) [m/s]."""
    w: FloatArray
    """Spins (N, 3) [rad/s]."""
    events: tuple[Event, ...]
    """Contacts in time order."""
    end_reason: Literal["t_max", "floor", "max_table_bounces", "rest", "max_events"]
    """Why the simulation stopped."""

    def events_of(self, kind: EventKind) -> tuple[Event, ...]:
        """The events of one kind, in time order."""
        return tuple(e for e in self.events if e.kind == kind)

    @property
    def table_bounces(self) -> tuple[Event, ...]:
        """Table events in time order."""
        return self.events_of("table")

    @property
    def final_state(self) -> BallState:
        """Ball state at the last sample."""
        return BallState(self.p[-1], self.v[-1], self.w[-1])


DEFAULT_FLIGHT = FlightModel()
"""Default flight model."""

DEFAULT_TABLE = TableBounceModel()
"""Default table bounce model (drop test tuned)."""

DEFAULT_NET = NetModel()
"""Default net/post impact model."""

_MAX_EVENTS = 64
"""Safety limit on the number of impacts in one simulation."""

_REST_SPEED = 0.02
"""Normal speed [m/s] below which a table/floor bounce ends the simulation ("rest")."""


def hermite(
    theta: float, h: float, ya: Sequence[float], fa: Sequence[float], yb: Sequence[float], fb: Sequence[float], n: int
) -> list[float]:
    """Cubic Hermite interpolation of the first ``n`` state components at ``theta`` in [0, 1]."""
    t2 = theta * theta
    t3 = t2 * theta
    h00 = 2.0 * t3 - 3.0 * t2 + 1.0
    h10 = (t3 - 2.0 * t2 + theta) * h
    h01 = -2.0 * t3 + 3.0 * t2
    h11 = (t3 - t2) * h
    if n == 3:  # positions: the hot path of event location, unrolled
        return [
            h00 * ya[0] + h10 * fa[0] + h01 * yb[0] + h11 * fb[0],
            h00 * ya[1] + h10 * fa[1] + h01 * yb[1] + h11 * fb[1],
            h00 * ya[2] + h10 * fa[2] + h01 * yb[2] + h11 * fb[2],
        ]
    return [h00 * ya[i] + h10 * fa[i] + h01 * yb[i] + h11 * fb[i] for i in range(n)]


@dataclass(slots=True)
class _Obstacle:
    """A court box prepared for the event search."""

    name: str
    kind: str
    c: tuple[float, float, float]
    h: tuple[float, float, float]


def _box_distance(p: Sequence[float], ob: _Obstacle) -> float:
    """Signed distance [m] from point ``p`` to a box (negative inside)."""
    qx = abs(p[0] - ob.c[0]) - ob.h[0]
    qy = abs(p[1] - ob.c[1]) - ob.h[1]
    qz = abs(p[2] - ob.c[2]) - ob.h[2]
    ox, oy, oz = max(qx, 0.0), max(qy, 0.0), max(qz, 0.0)
    return math.sqrt(ox * ox + oy * oy + oz * oz) + min(max(qx, qy, qz), 0.0)


def _box_normal(p: FloatArray, ob: _Obstacle) -> FloatArray:
    """Outward unit normal of the box at the point of it closest to ``p`` (outside)."""
    c = np.array(ob.c)
    h = np.array(ob.h)
    closest = np.clip(p, c - h, c + h)
    d = p - closest
    nd = float(np.linalg.norm(d))
    if nd > 1e-12:
        return d / nd
    q = (np.abs(p - c) - h) / np.maximum(h, 1e-12)
    i = int(np.argmax(q))
    n = np.zeros(3)
    n[i] = 1.0 if p[i] >= c[i] else -1.0
    return n


def _first_crossing(g: Callable[[float], float], n_sub: int, refine: float) -> float | None:
    """First theta in (0, 1] where ``g`` goes from > 0 to <= 0, by sampling + Brent.

    ``n_sub`` equal sub-intervals are sampled; if no sample is <= 0 but the smallest is
    below ``refine`` (a possible grazing contact between samples), the minimum is
    searched with a bounded scalar minimization. Returns None if there is no crossing.
    """
    thetas = [i / n_sub for i in range(n_sub + 1)]
    gs = [g(th) for th in thetas]
    armed = gs[0] > 0.0
    for i in range(1, n_sub + 1):
        if armed and gs[i] <= 0.0:
            a, b = thetas[i - 1], thetas[i]
            if gs[i] == 0.0:
                return b
            return brentq(g, a, b, xtol=1e-14, maxiter=200)
        if gs[i] > 0.0:
            armed = True
    if not armed:
        return None
    # an interior local minimum of the samples that is close to 0: look between samples
    i_min = min(range(1, n_sub), key=lambda i: gs[i])
    if gs[i_min] >= refine or gs[i_min] > gs[i_min - 1] or gs[i_min] > gs[i_min + 1]:
        return None
    lo = thetas[i_min - 1]
    hi = thetas[i_min + 1]
    res = minimize_scalar(g, bounds=(lo, hi), method="bounded", options={"xatol": 1e-10})
    th_min = float(res.x)
    if res.fun > 0.0 or th_min <= 0.0:
        return None
    # the crossing lies between the last positive sample before th_min and th_min
    a = max((th for th in thetas if th < th_min and g(th) > 0.0), default=0.0)
    if g(a) <= 0.0:
        return None
    return brentq(g, a, th_min, xtol=1e-14, maxiter=200)


def rk4_step(
    deriv: Callable[[Sequence[float]], list[float]], y: list[float], f: list[float], h: float
) -> tuple[list[float], list[float]]:
    """One classic RK4 step of the 9-state ball ODE on plain floats (fast for scalars).

    Args:
        deriv: the flight equations (:meth:`FlightModel.scalar_derivative`).
        y: state [p, v, w] (9,) at the step start; f: deriv(y).
        h: step [s].

    Returns:
        (y1, f1): the state after the step and its derivative (for Hermite dense output).
    """
    k2 = deriv([y[i] + 0.5 * h * f[i] for i in range(9)])
    k3 = deriv([y[i] + 0.5 * h * k2[i] for i in range(9)])
    k4 = deriv([y[i] + h * k3[i] for i in range(9)])
    h6 = h / 6.0
    y1 = [y[i] + h6 * (f[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]) for i in range(9)]
    return y1, deriv(y1)


_EndReason = Literal["t_max", "floor", "max_table_bounces", "rest", "max_events"]
"""Why :func:`simulate` ended."""


def simulate(
    state: BallState,
    t_max: float,
    *,
    flight: FlightModel = DEFAULT_FLIGHT,
    table: TableBounceModel = DEFAULT_TABLE,
    racket_model: RacketModel | None = None,
    net: NetModel = DEFAULT_NET,
    court: Court = DEFAULT_COURT,
    racket: RacketMotion | None = None,
    t0: float = 0.0,
    dt_out: float = 1e-3,
    max_table_bounces: int | None = None,
    stop_on_floor: bool = True,
    max_step: float = 0.01,
) -> Trajectory:
    """Simulate the ball from ``state`` at time ``t0`` for at most ``t_max`` seconds.

    Flight is integrated with classic RK4 at a fixed step ``max_step`` (shortened only
    to land on ``t0 + t_max``); each step carries a cubic Hermite dense output. Events
    are searched on that dense output (:class:`_EventSearch`) and located by Brent's
    method, so event times do not depend on the step size. At an event the impact map
    of the object is applied (:func:`_impact`) and integration restarts from the event
    instant.

    Args:
        state: initial ball state (world frame).
        t_max: maximal simulated duration [s] after ``t0`` (> 0).
        flight: flight model.
        table: table bounce model (also used for the floor).
        racket_model: racket impact model (default :meth:`RacketModel.default`).
        net: net/post impact model.
        court: court geometry (table, net, posts, extras; floor at ``court.floor_z``).
        racket: optional moving racket, active during ``[racket.t_start, racket.t_end]``.
        t0: time of ``state`` [s].
        dt_out: output sampling period [s].
        max_table_bounces: stop right after this many table bounces (None: no limit).
        stop_on_floor: stop at the first floor contact (the event is recorded).
        max_step: integration step [s] (RK4; 0.01 keeps the position error < 1e-7 m).

    Returns:
        The :class:`Trajectory` (samples at ``t0 + k dt_out``, the event instants and
        the final instant).

    Raises:
        InvalidInputError: non-finite or non-positive durations/steps, bad arguments.
    """
    _check_simulate_args(state, t_max, t0, dt_out, max_step, max_table_bounces, racket)
    if racket is not None and racket_model is None:
        racket_model = RacketModel.default()
    rules = _EventRules(table, net, racket_model, court, stop_on_floor, max_table_bounces)
    search = _EventSearch(flight.radius, court, racket)
    pieces_t, pieces_y, events, t_final, end_reason = _integrate(
        flight, search, rules, state, float(t0), float(t_max), max_step
    )
    return _assemble(pieces_t, pieces_y, events, float(t0), t_final, dt_out, end_reason)


def _integrate(
    flight: FlightModel,
    search: _EventSearch,
    rules: _EventRules,
    state: BallState,
    t0: float,
    t_max: float,
    max_step: float,
) -> tuple[
    list[tuple[float, float]],
    list[tuple[list[float], list[float], list[float], list[float]]],
    list[Event],
    float,
    _EndReason,
]:
    """The flight from ``state`` at ``t0`` for at most ``t_max`` [s]: RK4 steps of
    ``max_step`` with cubic Hermite dense output, each cut at its first event, where
    ``rules`` apply the impact map and decide whether to stop. Returns the pieces' time
    spans and dense outputs ``(y_a, f_a, y_b, f_b)``, the events, the final time [s] and
    why it ended."""
    deriv = flight.scalar_derivative()
    t = t0
    t_stop = t + t_max
    y = [*state.p.tolist(), *state.v.tolist(), *state.w.tolist()]
    f = deriv(y)
    pieces_t: list[tuple[float, float]] = []
    pieces_y: list[tuple[list[float], list[float], list[float], list[float]]] = []
    events: list[Event] = []
    n_table = 0
    end_reason: _EndReason = "t_max"
    while t < t_stop - 1e-12:
        h = min(max_step, t_stop - t)
        if t_stop - (t + h) < 1e-9:
            h = t_stop - t
        y1, f1 = rk4_step(deriv, y, f, h)
        ya, fa = y, f
        found = search.first_event(t, h, ya, fa, y1, f1)
        if found is None:
            pieces_t.append((t, t + h))
            pieces_y.append((ya, fa, y1, f1))
            t, y, f = t + h, y1, f1
            continue
        best_theta, best = found
        te = t + best_theta * h
        ye = hermite(best_theta, h, ya, fa, y1, f1, 9)
        fe = deriv(ye)
        pieces_t.append((t, te))
        pieces_y.append((ya, fa, ye, fe))
        event = rules.impact(best, te, ye)
        events.append(event)
        t = te
        y = [*ye[0:3], *event.v_after.tolist(), *event.w_after.tolist()]
        f = deriv(y)
        if event.kind == "table":
            n_table += 1
        reason = rules.stop_reason(event, n_table, len(events))
        if reason is not None:
            end_reason = reason
            break
    # closing zero-length piece: the final (post-event) state
    pieces_t.append((t, t))
    pieces_y.append((y, f, y, f))
    return pieces_t, pieces_y, events, t, end_reason


def _check_simulate_args(
    state: object,
    t_max: float,
    t0: float,
    dt_out: float,
    max_step: float,
    max_table_bounces: int | None,
    racket: object,
) -> None:
    """InvalidInputError for a bad argument of :func:`simulate`."""
    if not isinstance(state, BallState):
        raise InvalidInputError(f"simulate: state must be a BallState, got {type(state).__name__}")
    for label, val in (("t_max", t_max), ("dt_out", dt_out), ("max_step", max_step)):
        if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0.0):
            raise InvalidInputError(f"simulate: {label} must be a positive finite number [s], got {val!r}")
    if not (isinstance(t0, (int, float)) and math.isfinite(t0)):
        raise InvalidInputError(f"simulate: t0 must be finite, got {t0!r}")
    if max_table_bounces is not None and max_table_bounces < 1:
        raise InvalidInputError(f"simulate: max_table_bounces must be >= 1 or None, got {max_table_bounces!r}")
    if racket is not None and not isinstance(racket, RacketMotion):
        raise InvalidInputError("simulate: racket must provide t_start, t_end and state(t) (RacketMotion)")


class _EventSearch:
    """The first event of a flight step on its dense output: the event functions (sphere
    vs court boxes: table top incl. its edges, net, posts, extras; floor plane; the moving
    racket's blade, either face) are sampled on sub-intervals shorter than r/4 of ball
    travel, and every sign change is located by Brent's method (grazing contacts between
    samples by a bounded minimization, :func:`_first_crossing`).

    Racket contact: with ``n`` the racket z axis and ``d = n . (p_ball - p_racket)``,
    contact when ``|d| - (r + RACKET_HALF_THICKNESS)`` reaches 0 (from the side the ball
    is on at the start of the step) while the ball centre projects inside the blade
    ellipse (RACKET_BLADE_WIDTH along racket x, RACKET_BLADE_LENGTH along y). Hits on
    the blade rim and on the handle are not modelled.
    """

    def __init__(self, r: float, court: Court, racket: RacketMotion | None) -> None:
        self.r = r
        """Ball radius [m]."""
        self.floor_z = court.floor_z
        self.obstacles = [_Obstacle(b.name, b.kind, b.center, b.half_size) for b in court.boxes()]
        self.slab = r + C.RACKET_HALF_THICKNESS
        self.ra2 = (0.5 * C.RACKET_BLADE_WIDTH) ** 2
        self.rb2 = (0.5 * C.RACKET_BLADE_LENGTH) ** 2
        self.racket_reach = 0.5 * max(C.RACKET_BLADE_WIDTH, C.RACKET_BLADE_LENGTH) + self.slab
        self.margin = r + 0.005
        self.racket = racket
        self._racket_cache: dict[float, RacketState] = {}
        self.racket_plane: Callable[[float], tuple[float, float, float, float, float, float]] = (
            getattr(racket, "_fast_plane", None) or self._plane_from_state
        )
        # The ball box farther than the racket's reach from every origin the racket can have
        # over the step: no contact possible, skip the racket planes (the same events result).
        self.racket_far = getattr(racket, "_far", None)

    def racket_state(self, tt: float) -> RacketState:
        """The racket's state at ``tt`` [s] (cached: the search asks for the same times)."""
        rs = self._racket_cache.get(tt)
        if rs is None:
            assert self.racket is not None
            rs = self.racket.state(tt)
            if len(self._racket_cache) > 64:
                self._racket_cache.clear()
            self._racket_cache[tt] = rs
        return rs

    def _plane_from_state(self, tt: float) -> tuple[float, float, float, float, float, float]:
        rs = self.racket_state(tt)
        return (*rs.p.tolist(), *rs.R[:, 2].tolist())  # type: ignore[return-value]

    def first_event(
        self, t: float, h: float, ya: list[float], fa: list[float], y1: list[float], f1: list[float]
    ) -> tuple[float, tuple[str, object]] | None:
        """The first event in the step ``[t, t + h]`` (dense output ``ya, fa, y1, f1``):
        (theta in (0, 1], ("floor", None) | ("box", obstacle) | ("racket", (side, state)))."""
        r, margin = self.r, self.margin

        def pos(
            theta: float,
            _ya: list[float] = ya,
            _fa: list[float] = fa,
            _y1: list[float] = y1,
            _f1: list[float] = f1,
            _h: float = h,
        ) -> list[float]:
            return hermite(theta, _h, _ya, _fa, _y1, _f1, 3)

        x0, y0, z0 = ya[0], ya[1], ya[2]
        xe, ye_, ze = y1[0], y1[1], y1[2]
        travel = math.sqrt((xe - x0) ** 2 + (ye_ - y0) ** 2 + (ze - z0) ** 2)
        n_sub = max(2, math.ceil(travel / (0.25 * r)))
        lo = (min(x0, xe) - margin, min(y0, ye_) - margin, min(z0, ze) - margin)
        hi = (max(x0, xe) + margin, max(y0, ye_) + margin, max(z0, ze) + margin)

        best_theta = 2.0
        best: tuple[str, object] | None = None
        # --- floor -------------------------------------------------------------------
        if lo[2] - r <= self.floor_z:
            th = _first_crossing(lambda th: pos(th)[2] - r - self.floor_z, n_sub, 1e-3)
            if th is not None and th < best_theta:
                best_theta, best = th, ("floor", None)
        # --- court boxes ---------------------------------------------------------------
        for ob in self.obstacles:
            if (
                lo[0] > ob.c[0] + ob.h[0]
                or hi[0] < ob.c[0] - ob.h[0]
                or lo[1] > ob.c[1] + ob.h[1]
                or hi[1] < ob.c[1] - ob.h[1]
                or lo[2] > ob.c[2] + ob.h[2]
                or hi[2] < ob.c[2] - ob.h[2]
            ):
                continue

            def box_gap(th: float, _ob: _Obstacle = ob) -> float:
                return _box_distance(pos(th), _ob) - r

            th = _first_crossing(box_gap, n_sub, 2e-3)
            if th is not None and th < best_theta:
                best_theta, best = th, ("box", ob)
        # --- racket --------------------------------------------------------------------
        if self.racket is not None:
            hit = self._racket_event(t, h, pos, lo, hi)
            if hit is not None and hit[0] < best_theta:
                best_theta, best = hit
        return None if best is None else (best_theta, best)

    def _racket_event(
        self,
        t: float,
        h: float,
        pos: Callable[[float], list[float]],
        lo: tuple[float, float, float],
        hi: tuple[float, float, float],
    ) -> tuple[float, tuple[str, object]] | None:
        """The racket contact in the step (ball box ``lo``..``hi``, positions ``pos``) while
        the racket is active: (theta of the step, ("racket", (side, racket state))), or None."""
        racket = self.racket
        assert racket is not None
        r, slab, racket_plane = self.r, self.slab, self.racket_plane
        ta_r = max(t, racket.t_start)
        tb_r = min(t + h, racket.t_end)
        if not ta_r < tb_r or (
            self.racket_far is not None and self.racket_far(lo, hi, ta_r, tb_r, self.racket_reach + 0.01)
        ):
            return None
        pl_a = racket_plane(ta_r)
        pl_b = racket_plane(tb_r)
        pa = pos((ta_r - t) / h)
        pb = pos((tb_r - t) / h)
        rel_travel = math.dist(pa, pb) + math.dist(pl_a[:3], pl_b[:3])
        dist_a = math.dist(pa, pl_a[:3])
        dist_b = math.dist(pb, pl_b[:3])
        if not min(dist_a, dist_b) < self.racket_reach + rel_travel + 0.01:
            return None
        d_a = sum(pl_a[3 + j] * (pa[j] - pl_a[j]) for j in range(3))
        s = 1.0 if d_a >= 0.0 else -1.0

        def g_racket(th: float, _s: float = s, _ta: float = ta_r, _tb: float = tb_r) -> float:
            tt = _ta + th * (_tb - _ta)
            ox, oy, oz, nx, ny, nz = racket_plane(tt)
            px, py, pz = pos((tt - t) / h)
            return _s * (nx * (px - ox) + ny * (py - oy) + nz * (pz - oz)) - slab

        n_rk = max(4, math.ceil(rel_travel / (0.25 * r)))
        th = _first_crossing(g_racket, n_rk, 2e-3)
        if th is None:
            return None
        tt = ta_r + th * (tb_r - ta_r)
        rs = self.racket_state(tt)
        local = rs.R.T @ (np.array(pos((tt - t) / h)) - rs.p)
        inside = local[0] ** 2 / self.ra2 + local[1] ** 2 / self.rb2 <= 1.0
        if not inside:
            return None
        return (tt - t) / h, ("racket", (s, rs))


@dataclass(frozen=True, eq=False)
class _EventRules:
    """What happens at an event of :func:`simulate`: the impact maps (table, with the
    contact normal, so edge hits bounce off the edge: :class:`TableBounceModel`;
    net/posts: :class:`NetModel`; floor: the table model; racket:
    ``racket_model.bounce_moving``) and when the simulation stops."""

    table: TableBounceModel
    """Table (and floor) bounce model."""
    net: NetModel
    """Net/post impact model."""
    racket_model: RacketModel | None
    """Racket impact model (needed with a racket)."""
    court: Court
    """Court geometry (table halves)."""
    stop_on_floor: bool
    """Stop at the first floor contact."""
    max_table_bounces: int | None
    """Stop right after this many table bounces (None: no limit)."""

    def impact(self, best: tuple[str, object], te: float, ye: list[float]) -> Event:
        """The :class:`Event` of the ball in state ``ye`` (9,) at ``te`` [s] hitting
        ``best`` (see :meth:`_EventSearch.first_event`)."""
        p_e = np.array(ye[0:3])
        v_b = np.array(ye[3:6])
        w_b = np.array(ye[6:9])
        what, info = best
        side: Literal["server", "receiver"] | None = None
        if what == "floor":
            kind: EventKind = "floor"
            part = "floor"
            normal = np.array([0.0, 0.0, 1.0])
            v_a, w_a = self.table.bounce(v_b, w_b)
            side = self.court.side(float(p_e[0]))
        elif what == "box":
            assert isinstance(info, _Obstacle)
            normal = _box_normal(p_e, info)
            if info.kind == "table":
                kind = "table"
                part = "top" if normal[2] > 1.0 - 1e-9 else ("edge" if normal[2] > 0.0 else "side")
                v_a, w_a = _bounce_on_normal(self.table, v_b, w_b, normal)
                side = self.court.side(float(p_e[0]))
            elif info.kind in ("net", "post"):
                kind = "net"
                part = "net" if info.kind == "net" else "post"
                v_a, w_a = self.net.bounce(v_b, w_b, normal, "net" if info.kind == "net" else "post")
            else:
                kind = "obstacle"
                part = info.name
                v_a, w_a = self.net.bounce(v_b, w_b, normal, "post")
        else:
            racket_model = self.racket_model
            assert racket_model is not None and isinstance(info, tuple)
            s, rs = info
            kind = "racket"
            part = "face_a" if s > 0.0 else "face_b"
            normal = s * rs.R[:, 2]
            # racket velocity at the ball centre with the spin relative to omega: the slip at the
            # contact point is then exact (the serve contacts' convention, RacketModel.bounce_moving)
            v_a, w_a = racket_model.bounce_moving(v_b, w_b, rs.R, rs.point_velocity(p_e), s, omega=rs.omega)
        return Event(
            kind=kind,
            t=te,
            p=p_e,
            v_before=v_b,
            v_after=v_a,
            w_before=w_b,
            w_after=w_a,
            part=part,
            normal=normal,
            side=side,
        )

    def stop_reason(self, event: Event, n_table: int, n_events: int) -> _EndReason | None:
        """Why :func:`simulate` ends at ``event`` (after ``n_table`` table bounces and
        ``n_events`` events), or None if it goes on."""
        kind, normal = event.kind, event.normal
        if kind == "floor" and self.stop_on_floor:
            return "floor"
        if kind == "table" and self.max_table_bounces is not None and n_table >= self.max_table_bounces:
            return "max_table_bounces"
        if kind in ("table", "floor") and normal[2] > 0.99 and float(event.v_after @ normal) < _REST_SPEED:
            return "rest"
        if n_events >= _MAX_EVENTS:
            return "max_events"
        return None


def _assemble(
    pieces_t: list[tuple[float, float]],
    pieces_y: list[tuple[list[float], list[float], list[float], list[float]]],
    events: list[Event],
    t0: float,
    t_final: float,
    dt_out: float,
    end_reason: _EndReason,
) -> Trajectory:
    """Sample the piecewise Hermite dense output on the output grid + event instants."""
    ta = np.array([a for a, _ in pieces_t])
    tb = np.array([b for _, b in pieces_t])
    arr = np.array(pieces_y)  # (M, 4, 9)
    n_grid = int(math.floor((t_final - t0) / dt_out + 1e-9)) + 1
    grid = t0 + dt_out * np.arange(n_grid)
    tq = np.unique(np.concatenate([grid, [e.t for e in events], [t_final]]))
    # drop grid points closer than 1e-9 s to an event/final instant (keep the exact ones)
    exact = np.array([e.t for e in events] + [t_final])
    near = np.min(np.abs(tq[:, None] - exact[None, :]), axis=1) < 1e-9
    is_exact = np.isin(tq, exact)
    tq = tq[~near | is_exact]
    idx = np.clip(np.searchsorted(ta, tq, side="right") - 1, 0, len(ta) - 1)
    h = tb[idx] - ta[idx]
    th = np.where(h > 0.0, (tq - ta[idx]) / np.where(h > 0.0, h, 1.0), 0.0)
    th = np.clip(th, 0.0, 1.0)[:, None]
    t2 = th * th
    t3 = t2 * th
    hh = h[:, None]
    ya, fa, yb, fb = arr[idx, 0], arr[idx, 1], arr[idx, 2], arr[idx, 3]
    yq = (2 * t3 - 3 * t2 + 1) * ya + (t3 - 2 * t2 + th) * hh * fa + (-2 * t3 + 3 * t2) * yb + (t3 - t2) * hh * fb
    for a in (tq, yq):
        a.setflags(write=False)
    return Trajectory(t=tq, p=yq[:, 0:3], v=yq[:, 3:6], w=yq[:, 6:9], events=tuple(events), end_reason=end_reason)
