"""MuJoCo rollout of a serve: the robot follows its predicted joint motion, the ball flies.

One MuJoCo model (:func:`studio.sim.scene.build_scene`) holds the robot (``robots/serve_robot.xml``),
the ITTF table top and legs, net, posts, floor plane and the ball (free joint, 40 mm
sphere, 2.7 g, thin-shell inertia). :func:`rollout` plays joint commands ``u`` (1 kHz)
on it and returns the ball's path and every ball contact.

How the pieces work together (world frame of ``DESIGN.md``, SI units):

- **Robot.** The robot is position controlled and ~10^4 times heavier than the ball, so
  it is driven kinematically: the commands go through the joint model
  (:meth:`studio.robot.model.JointDynamics.simulate`) and the predicted joint positions are
  written into ``qpos`` (``mj_kinematics``) at each sample; between samples they are
  cubic-Hermite interpolated from the predicted positions and velocities.
- **Ball flight.** Between contacts the ball's state [p, v, w] is integrated with the
  flight equations of :mod:`studio.physics.ball` (gravity + drag + saturating Magnus + spin
  decay, from the given :class:`~studio.physics.ball.FlightModel`) by the same fixed-step RK4
  with cubic-Hermite dense output as the fast predictor :func:`studio.physics.ball.simulate`,
  so free flights of both agree to round-off. MuJoCo does not step the ball (no
  ``mj_step``): its soft contact can therefore never act on it, which is what the
  calibrated impulse maps require; gravity is the model's ``opt.gravity`` (checked
  against the flight model's).
- **Contacts.** MuJoCo finds them (:class:`studio.sim.contact_search.ContactSearch`). Broadphase per RK4 step: the ball's box against the
  court geoms' boxes, and against bounding spheres of the robot's collision geoms posed
  with ``mj_kinematics`` at every command sample. Near a candidate, the narrowphase
  ``mujoco.mj_geomDistance`` (signed distance) is evaluated on a grid of ``substep``
  spacing (0.25 ms by default), skipping grid points by conservative advancement (no
  contact can happen before distance / closing-speed bound); the first touch is then
  located by Brent's method on the distance to ``time_tolerance`` (1 ns). The contact
  normal points from the nearest point of the geom to the ball centre.
- **Rebounds.** The impulse maps of :mod:`studio.physics.ball` decide them
  (:class:`studio.sim.impact.Impacts`): table top (edges
  with their own normal) and floor: :class:`~studio.physics.ball.TableBounceModel`; the blade
  faces: :class:`~studio.physics.ball.RacketModel` relative to the racket's velocity at the
  contact point (MuJoCo point Jacobian), face A or B from the side touched; net and
  posts: :class:`~studio.physics.ball.NetModel`; any other robot geom (links, handle, cup,
  blade rim): a "robot" (rim: "racket") contact with a simple restitution relative to
  the geom's velocity (:class:`~studio.sim.options.RolloutOptions`). A geom just touched counts again only
  after the ball has been ``rearm_distance`` away from it, or if the ball sinks
  ``sink_depth`` into it (pushed again: a double hit), so one contact is counted once.
  A contact whose normal rebound speed is below ``rest_speed`` ends the rollout
  ("rest": resting and rolling contact are not modelled).
- **Toss.** With ``ball="cup"`` the ball rides in the cup (at the ``ball_cup`` site of
  the predicted motion) until :func:`studio.toss.release.find_release` says the contact force
  vanishes; then it flies from the release state. Cup geoms touching the ball at that
  instant count only once the ball has left them (see above).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError, RobotModelError, checked_array
from studio.physics.ball import (
    DEFAULT_FLIGHT,
    DEFAULT_NET,
    DEFAULT_TABLE,
    BallState,
    FlightModel,
    NetModel,
    RacketModel,
    TableBounceModel,
    hermite,
    rk4_step,
)
from studio.robot.model import JointDynamics
from studio.sim.contact import Contact
from studio.sim.contact_search import ContactSearch
from studio.sim.impact import Impacts
from studio.sim.options import DEFAULT_OPTIONS, RolloutOptions
from studio.sim.robot_track import RobotTrack, hermite_rows
from studio.sim.scene import Scene
from studio.toss.release import Release, find_release

FloatArray = npt.NDArray[np.float64]

EndReason = Literal["t_end", "floor", "rest", "max_contacts", "in_cup"]
"""Why a rollout ended (``"in_cup"``: the ball never left the cup)."""

Piece = tuple[float, float, list[float], list[float], list[float], list[float]]
"""A flight interval ``(ta, tb, y(ta), y'(ta), y(tb), y'(tb))`` of the 9-state [p, v, w]."""


@dataclass(frozen=True, slots=True)
class RolloutResult:
    """Ball path, robot motion and contacts of a rollout, sampled on the command grid.

    Sample ``k`` is the scene at ``t[k]``; at a sample that coincides with a contact the
    ball state is the one after the impact. Arrays are read-only.
    """

    t: FloatArray
    """Sample times (M,) [s]: the command grid up to the end of the rollout."""
    p: FloatArray
    """Ball centre (M, 3) [m] (in the cup until the release, if tossed)."""
    v: FloatArray
    """Ball velocity (M, 3) [m/s]."""
    w: FloatArray
    """Ball spin (M, 3) [rad/s]."""
    q: FloatArray
    """Predicted robot joint positions (M, 8) [m | rad], robot joint order."""
    contacts: tuple[Contact, ...]
    """Ball contacts in time order."""
    release: Release | None
    """The :class:`studio.toss.release.Release` when the ball started in the cup and left it, else
    None."""
    t_final: float
    """Time the rollout ended [s] (``t_end``, or the instant of the stopping contact)."""
    end_reason: EndReason
    """Why the rollout ended (``"in_cup"``: the ball never left the cup)."""

    @property
    def release_t(self) -> float | None:
        """Release time from the cup [s], or None."""
        return None if self.release is None else float(self.release.time)

    def contacts_of(self, kind: str) -> tuple[Contact, ...]:
        """The contacts of one kind, in time order."""
        return tuple(c for c in self.contacts if c.kind == kind)

    def first(self, kind: str) -> Contact | None:
        """The first contact of ``kind``, or None."""
        return next((c for c in self.contacts if c.kind == kind), None)

    @property
    def table_bounces(self) -> tuple[Contact, ...]:
        """Table contacts in time order."""
        return self.contacts_of("table")

    @property
    def racket_contacts(self) -> tuple[Contact, ...]:
        """Racket (blade) contacts in time order."""
        return self.contacts_of("racket")

    def state_at(self, k: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Ball ``(p, v, w)`` at sample ``k``."""
        return self.p[k], self.v[k], self.w[k]


def rollout(
    scene: Scene,
    *,
    t: npt.ArrayLike,
    u: npt.ArrayLike | None = None,
    X0: npt.ArrayLike | None = None,
    X: npt.ArrayLike | None = None,
    ball: BallState | Literal["cup"],
    t_end: float | None = None,
    dynamics: JointDynamics | None = None,
    flight: FlightModel = DEFAULT_FLIGHT,
    table: TableBounceModel = DEFAULT_TABLE,
    racket_model: RacketModel | None = None,
    net: NetModel = DEFAULT_NET,
    options: RolloutOptions = DEFAULT_OPTIONS,
) -> RolloutResult:
    """Roll out joint commands on the MuJoCo scene: robot motion, ball flight and contacts.

    The robot follows the joint motion predicted from the commands by the joint model
    (``dynamics.simulate(u, dt, X0)``), or the given predicted states ``X``. The ball
    either starts from ``ball`` (a :class:`~studio.physics.ball.BallState` at ``t[0]``) or, with
    ``ball="cup"``, rides in the ball cup until :func:`studio.toss.release.find_release` (on the
    predicted cup motion) releases it. See the module docstring for flight, contact
    search and impact maps.

    Args:
        scene: from :func:`studio.sim.scene.build_scene`.
        t: command times (N,) [s], uniformly spaced (1 kHz in the studio), N >= 3.
        u: joint position commands (N, 8) [m | rad], ``u[k]`` held over
            ``[t[k], t[k+1])``; after ``t[-1]`` the last command is held.
        X0: joint state at ``t[0]``, (8, 2) = [q, q'] (default: at rest at ``u[0]``).
        X: predicted joint states (>= N, 8, 2) instead of ``u``/``X0`` (e.g. a toss
            primitive's ``X``, or the planner's prediction: saves the joint-model
            simulation); must then cover ``t_end``.
        ball: initial ball state at ``t[0]`` or ``"cup"``.
        t_end: end of the rollout [s] (default ``t[-1]``); may exceed ``t[-1]`` with ``u``.
        dynamics: joint model (default: that of :func:`studio.robot.model.load_robot`).
        flight: ball flight model (gravity along -Z must equal the scene's).
        table: table (and floor) bounce model.
        racket_model: rubber model of the blade faces (default
            :meth:`RacketModel.default`, the calibrated racket, loaded at the first
            blade contact).
        net: net and post impact model.
        options: numerical settings and the robot-contact restitution.

    Returns:
        The :class:`RolloutResult` on the command grid up to the end of the rollout.

    Raises:
        InvalidInputError: a bad argument (shape, non-finite value, non-uniform ``t``,
            ``t_end`` out of range), naming it.
        RobotModelError: the scene's robot joints differ from the joint model's.
    """
    _check_types(scene, options)
    tt = _checked_times(t)
    _check_ball(ball)
    t0, dt = float(tt[0]), float(tt[1] - tt[0])
    t_stop = _checked_end(t_end, tt)
    n_total = max(tt.size, int(math.ceil((t_stop - t0) / dt - 1e-9)) + 1)
    Xa = _predicted_states(scene, tt, n_total, t_stop, u=u, X0=X0, X=X, dynamics=dynamics)
    Q = np.ascontiguousarray(Xa[:, :, 0])
    QD = np.ascontiguousarray(Xa[:, :, 1])
    grid = t0 + dt * np.arange(n_total, dtype=np.float64)
    _check_flight(scene, flight)

    m = scene.model
    d = mujoco.MjData(m)
    track = RobotTrack(scene, d, t0, dt, Q, QD)
    mujoco.mj_kinematics(m, d)
    search = ContactSearch(scene, d, track, grid, t0, dt, options)
    impacts = Impacts(scene, d, track, table=table, net=net, racket_model=racket_model, options=options)

    start = _start(ball, track, grid, flight, t_stop)
    if start is None:  # the ball stays in the cup
        return _in_cup_result(grid, track, Q, t_stop)
    release, cup_until, t_start, y = start
    # geoms touching the ball at the start (e.g. the cup at release) count only once left
    search.disarm_touching(t_start, y[0:3])
    pieces, contacts, t_final, end_reason = _fly(search, impacts, flight, t_start, y, t_stop, options)
    return _assemble(grid, track, Q, pieces, contacts, release, cup_until, t_final, end_reason)


@functools.lru_cache(maxsize=1)
def _default_dynamics() -> JointDynamics:
    from studio.robot.model import load_robot

    return load_robot().dynamics


def _as_array(value: npt.ArrayLike, name: str, shape: tuple[int, ...]) -> FloatArray:
    """Validated float array (shape, finite) or InvalidInputError naming ``rollout: name``."""
    return checked_array(value, shape, f"rollout: {name}", read_only=False)  # type: ignore[no-any-return]


def _check_types(scene: object, options: object) -> None:
    """InvalidInputError unless ``scene`` is a Scene and ``options`` RolloutOptions."""
    if not isinstance(scene, Scene):
        raise InvalidInputError(f"rollout: scene must be a Scene (build_scene()), got {type(scene).__name__}")
    if not isinstance(options, RolloutOptions):
        raise InvalidInputError(f"rollout: options must be RolloutOptions, got {type(options).__name__}")


def _checked_times(t: npt.ArrayLike) -> FloatArray:
    """The command times (N,) [s]: N >= 3, finite, strictly increasing, uniform step."""
    try:
        tt = np.array(t, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"rollout: t must be an array of times, got {type(t).__name__}") from exc
    if tt.ndim != 1 or tt.size < 3:
        raise InvalidInputError(f"rollout: t must have shape (N,) with N >= 3, got {tt.shape}")
    if not np.all(np.isfinite(tt)):
        raise InvalidInputError("rollout: t must be finite")
    dt = float(tt[1] - tt[0])
    steps = np.diff(tt)
    if not dt > 0.0 or float(np.max(np.abs(steps - dt))) > 1e-9 + 1e-6 * dt:
        raise InvalidInputError("rollout: t must be strictly increasing with a uniform step")
    return tt


def _check_ball(ball: object) -> None:
    """InvalidInputError unless ``ball`` is a BallState or ``"cup"``."""
    if isinstance(ball, str):
        if ball != "cup":
            raise InvalidInputError(f"rollout: ball must be a BallState or 'cup', got {ball!r}")
    elif not isinstance(ball, BallState):
        raise InvalidInputError(f"rollout: ball must be a BallState or 'cup', got {type(ball).__name__}")


def _checked_end(t_end: float | None, tt: FloatArray) -> float:
    """End of the rollout [s] (default ``t[-1]``), finite and after ``t[0]``."""
    t0 = float(tt[0])
    if t_end is not None and not isinstance(t_end, (int, float, np.floating, np.integer)):
        raise InvalidInputError(f"rollout: t_end must be a number [s] or None, got {type(t_end).__name__}")
    t_stop = float(tt[-1]) if t_end is None else float(t_end)
    if not (math.isfinite(t_stop) and t_stop > t0):
        raise InvalidInputError(f"rollout: t_end must be finite and > t[0] = {t0}, got {t_end!r}")
    return t_stop


def _predicted_states(
    scene: Scene,
    tt: FloatArray,
    n_total: int,
    t_stop: float,
    *,
    u: npt.ArrayLike | None,
    X0: npt.ArrayLike | None,
    X: npt.ArrayLike | None,
    dynamics: JointDynamics | None,
) -> FloatArray:
    """Predicted joint states (n_total, 8, 2) on the command grid: the given ``X``, or
    the joint model's response to the commands ``u`` (the last one held) from ``X0``."""
    N = tt.size
    nq = scene.robot_qpos.size
    if X is not None and (u is not None or X0 is not None):
        raise InvalidInputError("rollout: give either u (and X0) or the predicted states X, not both")
    if X is not None:
        Xa = np.array(X, dtype=float)
        if Xa.ndim != 3 or Xa.shape[1:] != (nq, 2) or Xa.shape[0] < N:
            raise InvalidInputError(f"rollout: X must have shape (>= {N}, {nq}, 2), got {Xa.shape}")
        if Xa.shape[0] < n_total:
            raise InvalidInputError(
                f"rollout: X covers {Xa.shape[0]} samples, t_end = {t_stop} needs {n_total} (pass u to extend)"
            )
        return _as_array(Xa[:n_total], "X", (n_total, nq, 2))
    if u is None:
        raise InvalidInputError("rollout: give the joint commands u (or the predicted states X)")
    U = _as_array(u, "u", (N, nq))
    dyn = dynamics if dynamics is not None else _default_dynamics()
    if tuple(dyn.names) != scene.joint_names:
        raise RobotModelError(
            f"rollout: joint model joints {tuple(dyn.names)} differ from the scene's {scene.joint_names}"
        )
    X0a = np.stack([U[0], np.zeros(nq)], axis=1) if X0 is None else _as_array(X0, "X0", (nq, 2))
    if n_total > N:
        U = np.concatenate([U, np.repeat(U[-1:], n_total - N, axis=0)])
    return dyn.simulate(U, float(tt[1] - tt[0]), X0a)


def _check_flight(scene: Scene, flight: FlightModel) -> None:
    """The flight model's gravity and ball radius must be the scene's."""
    if abs(flight.gravity - float(-scene.model.opt.gravity[2])) > 1e-9:
        raise InvalidInputError(
            f"rollout: flight.gravity = {flight.gravity} differs from the scene's {-scene.model.opt.gravity[2]}"
        )
    r = float(scene.model.geom_size[scene.ball_geom, 0])
    if abs(flight.radius - r) > 1e-12:
        raise InvalidInputError(f"rollout: flight.radius = {flight.radius} differs from the scene's ball radius {r}")


def _start(
    ball: BallState | Literal["cup"], track: RobotTrack, grid: FloatArray, flight: FlightModel, t_stop: float
) -> tuple[Release | None, int, float, list[float]] | None:
    """Start of the flight: (release from the cup or None, last grid index with the ball
    in the cup (-1: none), start time [s], ball state (9,) [p, v, w]); None if the ball
    stays in the cup until ``t_stop`` [s]. With ``ball="cup"`` the ball rides in the cup
    until :func:`~studio.toss.release.find_release` on the predicted cup motion."""
    if not isinstance(ball, str):
        return None, -1, float(grid[0]), [*ball.p.tolist(), *ball.v.tolist(), *ball.w.tolist()]
    track.ensure(grid.size - 1)
    release = find_release(
        grid, track.cup, track.R[:, :, 2], rotation=track.R, gravity=flight.gravity, drag_k=flight.drag_constant
    )
    if release is None or release.time >= t_stop:
        return None
    t_start = float(release.time)
    y = [*release.position.tolist(), *release.velocity.tolist(), *release.angular_velocity.tolist()]
    return release, int(np.searchsorted(grid, t_start, side="left")) - 1, t_start, y


def _fly(
    search: ContactSearch,
    impacts: Impacts,
    flight: FlightModel,
    t_start: float,
    y: list[float],
    t_stop: float,
    opts: RolloutOptions,
) -> tuple[list[Piece], list[Contact], float, EndReason]:
    """The ball's flight with contacts from state ``y`` (9,) at ``t_start`` to ``t_stop``
    [s]: fixed-step RK4 (``max_step``) with cubic Hermite dense output; at a contact the
    step is cut, the rebound applied and the flight restarted from the contact instant.
    Returns the flight pieces, the contacts, the final time [s] and why the flight ended."""
    deriv = flight.scalar_derivative()  # the flight equations of studio.physics.ball, on floats
    f = deriv(y)
    t_cur = t_start
    pieces: list[Piece] = []
    contacts: list[Contact] = []
    end_reason: EndReason = "t_end"
    while t_cur < t_stop - 1e-12:
        h = min(opts.max_step, t_stop - t_cur)
        if t_stop - (t_cur + h) < 1e-9:
            h = t_stop - t_cur
        y1, f1 = rk4_step(deriv, y, f, h)
        hit = search.first_contact((t_cur, h, y, f, y1, f1))
        if hit is None:
            pieces.append((t_cur, t_cur + h, y, f, y1, f1))
            t_cur, y, f = t_cur + h, y1, f1
            continue

        tc, g = hit
        ye = hermite((tc - t_cur) / h, h, y, f, y1, f1, 9)
        fe = deriv(ye)
        pieces.append((t_cur, tc, y, f, ye, fe))
        contact = impacts.contact(g, tc, ye)
        contacts.append(contact)
        search.disarm(g)
        t_cur = tc
        y = [*ye[0:3], *contact.v_after.tolist(), *contact.w_after.tolist()]
        f = deriv(y)
        end = _stop_reason(contact, len(contacts), opts)
        if end is not None:
            end_reason = end
            break
    pieces.append((t_cur, t_cur, y, f, y, f))
    return pieces, contacts, t_cur, end_reason


def _stop_reason(contact: Contact, n_contacts: int, opts: RolloutOptions) -> EndReason | None:
    """Why the rollout ends at ``contact`` (the ``n_contacts``-th), or None if it goes on."""
    if contact.kind == "floor" and opts.stop_on_floor:
        return "floor"
    if float((contact.v_after - contact.surface_velocity) @ contact.normal) < opts.rest_speed:
        return "rest"  # no rebound worth the name: resting/rolling contact
    if n_contacts >= opts.max_contacts:
        return "max_contacts"
    return None


def _cup_states(grid: FloatArray, track: RobotTrack, n: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Ball in the cup on the first ``n`` samples: cup centre, its velocity (second-order
    differences, as :func:`studio.toss.release.find_release`) and the racket's angular velocity."""
    m = track.done
    p = track.cup[:m]
    v = np.gradient(p, grid[:m], axis=0, edge_order=2) if m >= 3 else np.zeros_like(p)
    R = track.R[:m]
    if m >= 3:
        Rd = np.gradient(R, grid[:m], axis=0, edge_order=2)
        W = Rd @ np.transpose(R, (0, 2, 1))
        w = 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], axis=1)
    else:
        w = np.zeros_like(p)
    return p[:n].copy(), v[:n].copy(), w[:n].copy()


def _frozen(*arrays: FloatArray) -> None:
    for a in arrays:
        a.setflags(write=False)


def _in_cup_result(grid: FloatArray, track: RobotTrack, Q: FloatArray, t_stop: float) -> RolloutResult:
    M = int(np.searchsorted(grid, t_stop + 1e-9, side="right"))
    p, v, w = _cup_states(grid, track, M)
    tq, q = grid[:M].copy(), Q[:M].copy()
    _frozen(tq, p, v, w, q)
    return RolloutResult(
        t=tq, p=p, v=v, w=w, q=q, contacts=(), release=None, t_final=float(t_stop), end_reason="in_cup"
    )


def _assemble(
    grid: FloatArray,
    track: RobotTrack,
    Q: FloatArray,
    pieces: list[Piece],
    contacts: list[Contact],
    release: Release | None,
    cup_until: int,
    t_final: float,
    end_reason: EndReason,
) -> RolloutResult:
    """Sample the piecewise-Hermite flight (and the cup phase) on the command grid."""
    M = int(np.searchsorted(grid, t_final + 1e-9, side="right"))
    tq = grid[:M].copy()
    P = np.empty((M, 3))
    V = np.empty((M, 3))
    W = np.empty((M, 3))
    n_cup = cup_until + 1
    if n_cup > 0:
        P[:n_cup], V[:n_cup], W[:n_cup] = _cup_states(grid, track, n_cup)
    ta = np.array([pc[0] for pc in pieces])
    tb = np.array([pc[1] for pc in pieces])
    arr = np.array([[pc[2], pc[3], pc[4], pc[5]] for pc in pieces])  # (K, 4, 9)
    tf = tq[n_cup:]
    if tf.size:
        idx = np.clip(np.searchsorted(ta, tf, side="right") - 1, 0, len(ta) - 1)
        h = tb[idx] - ta[idx]
        th = np.clip(np.where(h > 0.0, (tf - ta[idx]) / np.where(h > 0.0, h, 1.0), 0.0), 0.0, 1.0)
        yq = hermite_rows(th, h, arr[idx, 0], arr[idx, 1], arr[idx, 2], arr[idx, 3])
        P[n_cup:], V[n_cup:], W[n_cup:] = yq[:, 0:3], yq[:, 3:6], yq[:, 6:9]
    q = Q[:M].copy()
    _frozen(tq, P, V, W, q)
    return RolloutResult(
        t=tq,
        p=P,
        v=V,
        w=W,
        q=q,
        contacts=tuple(contacts),
        release=release,
        t_final=float(t_final),
        end_reason=end_reason,
    )
