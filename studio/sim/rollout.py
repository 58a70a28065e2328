"""MuJoCo rollout of a serve: the robot follows its predicted joint motion, the ball flies.

One MuJoCo model (:func:`build_scene`) holds the robot (``robots/serve_robot.xml``),
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
- **Contacts.** MuJoCo finds them. Broadphase per RK4 step: the ball's box against the
  court geoms' boxes, and against bounding spheres of the robot's collision geoms posed
  with ``mj_kinematics`` at every command sample. Near a candidate, the narrowphase
  ``mujoco.mj_geomDistance`` (signed distance) is evaluated on a grid of ``substep``
  spacing (0.25 ms by default), skipping grid points by conservative advancement (no
  contact can happen before distance / closing-speed bound); the first touch is then
  located by Brent's method on the distance to ``time_tolerance`` (1 ns). The contact
  normal points from the nearest point of the geom to the ball centre.
- **Rebounds.** The impulse maps of :mod:`studio.physics.ball` decide them: table top (edges
  with their own normal) and floor: :class:`~studio.physics.ball.TableBounceModel`; the blade
  faces: :class:`~studio.physics.ball.RacketModel` relative to the racket's velocity at the
  contact point (MuJoCo point Jacobian), face A or B from the side touched; net and
  posts: :class:`~studio.physics.ball.NetModel`; any other robot geom (links, handle, cup,
  blade rim): a "robot" (rim: "racket") contact with a simple restitution relative to
  the geom's velocity (:class:`RolloutOptions`). A geom just touched counts again only
  after the ball has been ``rearm_distance`` away from it, or if the ball sinks
  ``sink_depth`` into it (pushed again: a double hit), so one contact is counted once.
  A contact whose normal rebound speed is below ``rest_speed`` ends the rollout
  ("rest": resting and rolling contact are not modelled).
- **Toss.** With ``ball="cup"`` the ball rides in the cup (at the ``ball_cup`` site of
  the predicted motion) until :func:`studio.toss.model.find_release` says the contact force
  vanishes; then it flies from the release state. Cup geoms touching the ball at that
  instant count only once the ball has left them (see above).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal, cast

import mujoco
import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq

from studio import constants as C
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
from studio.physics.court import DEFAULT_COURT, Box, Court
from studio.errors import InvalidInputError, RobotModelError, checked_array
from studio.paths import robots_dir
from studio.robot.model import JointDynamics
from studio.robot.description import BALL_CUP_FRAME, MJCF_NAME, RACKET_BLADE_GEOM, RACKET_FRAME
from studio.toss.model import Release, find_release

FloatArray = npt.NDArray[np.float64]

ContactKind = Literal["racket", "robot", "table", "net", "post", "floor"]
"""What the ball touched (the legality chain's categories, :mod:`studio.serve.rules`)."""


BALL_NAME: Final[str] = "ball"
"""Name of the ball's body, free joint and geom in the scene."""

FLOOR_NAME: Final[str] = "floor"
"""Name of the floor plane geom."""

# Collision bits. Robot collision geoms (generated MJCF) have contype=2, conaffinity=1:
# MuJoCo pairs two geoms when (contype1 & conaffinity2) or (contype2 & conaffinity1).
_STATIC_CONTYPE, _STATIC_CONAFFINITY = 2, 1  # court geoms: touch the ball, not the robot
_BALL_CONTYPE, _BALL_CONAFFINITY = 1, 2  # the ball touches robot and court geoms
_LEG_CONTYPE, _LEG_CONAFFINITY = 0, 2  # table legs: robot only (Court.legs docstring)

_FLOOR_HALF_SIZE: Final[float] = 6.0
"""Half size of the drawn floor plane [m] (the plane itself is infinite for contacts)."""


# =====================================================================================
# Scene
# =====================================================================================


@dataclass(frozen=True, eq=False)
class Scene:
    """A compiled MuJoCo model of robot, court and ball, with the indices a rollout needs.

    The model is shared (cached by :func:`build_scene`): treat it as read-only and make
    your own ``mujoco.MjData`` for it.
    """

    model: mujoco.MjModel
    """The compiled model (timestep 1 ms, gravity -Z :data:`studio.constants.GRAVITY`)."""
    court: Court
    """The court the static geoms were built from."""
    joint_names: tuple[str, ...]
    """Robot joint names in the order of ``robot_qpos`` (8)."""
    robot_qpos: npt.NDArray[np.intp]
    """qpos addresses of the robot joints (8,)."""
    robot_dof: npt.NDArray[np.intp]
    """qvel (dof) addresses of the robot joints (8,)."""
    ball_body: int
    """Body id of the ball."""
    ball_geom: int
    """Geom id of the ball sphere."""
    ball_joint: int
    """Joint id of the ball's free joint."""
    ball_qpos: int
    """qpos address of the ball's free joint (position xyz then quaternion wxyz)."""
    ball_dof: int
    """qvel address of the ball's free joint (linear velocity then angular, world frame)."""
    racket_body: int
    """Body id of the racket frame."""
    cup_site: int
    """Site id of the ball-in-cup centre."""
    geom_kind: tuple[str, ...]
    """Per geom: the contact kind ("racket", "robot", "table", "net", "post", "floor") of
    the geoms the ball can touch, "" for the rest (visuals, legs, lines, the ball)."""
    contact_geoms: npt.NDArray[np.intp]
    """Ids of the geoms the ball can touch (kind != "")."""

    def geom_name(self, geom: int) -> str:
        """Name of geom ``geom`` (``""`` if unnamed)."""
        return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, geom) or ""

    def body_name(self, body: int) -> str:
        """Name of body ``body`` (``""`` if unnamed)."""
        return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_BODY, body) or ""

    def geom_id(self, name: str) -> int:
        """Geom id by name; InvalidInputError if there is none."""
        gid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if gid < 0:
            raise InvalidInputError(f"scene has no geom named {name!r}")
        return int(gid)


def _box_kind(box: Box) -> str:
    return {"table": "table", "net": "net", "post": "post"}.get(box.kind, "")


def _add_box(spec: mujoco.MjSpec, box: Box, *, contype: int, conaffinity: int, rgba: tuple[float, ...], group: int) -> None:
    g = spec.worldbody.add_geom()
    g.name = box.name
    g.type = mujoco.mjtGeom.mjGEOM_BOX
    g.size = list(box.half_size)
    g.pos = list(box.center)
    g.contype = contype
    g.conaffinity = conaffinity
    g.rgba = list(rgba)
    g.group = group


_RGBA = {
    "table": (0.05, 0.2, 0.45, 1.0),
    "net": (0.9, 0.9, 0.9, 0.6),
    "post": (0.2, 0.2, 0.2, 1.0),
    "leg": (0.25, 0.25, 0.25, 1.0),
    "line": (1.0, 1.0, 1.0, 1.0),
    "floor": (0.55, 0.5, 0.45, 1.0),
    "ball": (1.0, 0.55, 0.1, 1.0),
}


def _compose(robot_path: Path, court: Court) -> mujoco.MjModel:
    try:
        spec = mujoco.MjSpec.from_file(str(robot_path))
    except Exception as exc:  # mujoco raises ValueError on parse errors
        raise RobotModelError(f"{robot_path}: cannot read the robot MJCF: {exc}") from exc
    spec.modelname = "serve_scene"
    spec.option.timestep = 1e-3
    spec.option.gravity = [0.0, 0.0, -C.GRAVITY]

    for box in court.boxes():
        kind = _box_kind(box)
        if kind:
            _add_box(spec, box, contype=_STATIC_CONTYPE, conaffinity=_STATIC_CONAFFINITY, rgba=_RGBA[kind], group=0)
        else:  # extras of other kinds: visual only
            _add_box(spec, box, contype=0, conaffinity=0, rgba=_RGBA["leg"], group=1)
    for leg in court.legs():
        _add_box(spec, leg, contype=_LEG_CONTYPE, conaffinity=_LEG_CONAFFINITY, rgba=_RGBA["leg"], group=0)
    for line in court.lines():
        _add_box(spec, line, contype=0, conaffinity=0, rgba=_RGBA["line"], group=1)

    floor = spec.worldbody.add_geom()
    floor.name = FLOOR_NAME
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [_FLOOR_HALF_SIZE, _FLOOR_HALF_SIZE, 0.1]
    floor.pos = [0.0, 0.0, court.floor_z]
    floor.contype = _STATIC_CONTYPE
    floor.conaffinity = _STATIC_CONAFFINITY
    floor.rgba = list(_RGBA["floor"])

    body = spec.worldbody.add_body()
    body.name = BALL_NAME
    body.pos = [0.0, 0.0, 0.3]
    body.mass = C.BALL_MASS
    body.inertia = [C.BALL_INERTIA] * 3
    body.explicitinertial = True
    joint = body.add_freejoint()
    joint.name = BALL_NAME
    geom = body.add_geom()
    geom.name = BALL_NAME
    geom.type = mujoco.mjtGeom.mjGEOM_SPHERE
    geom.size = [C.BALL_RADIUS, 0.0, 0.0]
    geom.contype = _BALL_CONTYPE
    geom.conaffinity = _BALL_CONAFFINITY
    geom.mass = 0.0  # the body's explicit inertial holds the mass
    geom.rgba = list(_RGBA["ball"])
    try:
        return spec.compile()
    except Exception as exc:
        raise RobotModelError(f"{robot_path}: the scene does not compile: {exc}") from exc


@functools.lru_cache(maxsize=8)
def _scene_cached(robot_path: str, mtime_ns: int, court: Court) -> Scene:
    path = Path(robot_path)
    model = _compose(path, court)
    # Robot joints: every hinge/slide joint (the ball's is the only free joint).
    names: list[str] = []
    qadr: list[int] = []
    dadr: list[int] = []
    for j in range(model.njnt):
        if int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            names.append(model.joint(j).name)
            qadr.append(int(model.jnt_qposadr[j]))
            dadr.append(int(model.jnt_dofadr[j]))

    def must(obj: mujoco.mjtObj, name: str, what: str) -> int:
        i = mujoco.mj_name2id(model, obj, name)
        if i < 0:
            raise RobotModelError(f"{path}: {what} {name!r} missing")
        return int(i)

    racket = must(mujoco.mjtObj.mjOBJ_BODY, RACKET_FRAME, "body")
    cup_site = must(mujoco.mjtObj.mjOBJ_SITE, BALL_CUP_FRAME, "site")
    must(mujoco.mjtObj.mjOBJ_GEOM, RACKET_BLADE_GEOM, "geom")
    ball_body = must(mujoco.mjtObj.mjOBJ_BODY, BALL_NAME, "body")
    ball_geom = must(mujoco.mjtObj.mjOBJ_GEOM, BALL_NAME, "geom")
    ball_joint = must(mujoco.mjtObj.mjOBJ_JOINT, BALL_NAME, "joint")

    # Bodies of the racket subtree (racket and its children, e.g. the ball_cup body).
    racket_bodies = {racket}
    for b in range(model.nbody):
        p = b
        while p > 0:
            if p == racket:
                racket_bodies.add(b)
                break
            p = int(model.body_parentid[p])
    static_kind = {b.name: _box_kind(b) for b in court.boxes()}
    static_kind[FLOOR_NAME] = "floor"
    kinds: list[str] = []
    for g in range(model.ngeom):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
        pairs = bool(model.geom_contype[g] & _BALL_CONAFFINITY) or bool(_BALL_CONTYPE & model.geom_conaffinity[g])
        body = int(model.geom_bodyid[g])
        if g == ball_geom or not pairs:
            kinds.append("")
        elif body == 0:
            kinds.append(static_kind.get(name, ""))
        elif body in racket_bodies:
            kinds.append("racket" if name == RACKET_BLADE_GEOM else "robot")
        else:
            kinds.append("robot")
    return Scene(
        model=model,
        court=court,
        joint_names=tuple(names),
        robot_qpos=np.array(qadr, dtype=np.intp),
        robot_dof=np.array(dadr, dtype=np.intp),
        ball_body=ball_body,
        ball_geom=ball_geom,
        ball_joint=ball_joint,
        ball_qpos=int(model.jnt_qposadr[ball_joint]),
        ball_dof=int(model.jnt_dofadr[ball_joint]),
        racket_body=racket,
        cup_site=cup_site,
        geom_kind=tuple(kinds),
        contact_geoms=np.array([g for g, k in enumerate(kinds) if k], dtype=np.intp),
    )


def build_scene(*, robot_xml: str | Path | None = None, court: Court = DEFAULT_COURT) -> Scene:
    """The MuJoCo scene: robot + table top, legs, net, posts, lines, floor + ball.

    The robot MJCF is used as the base spec (names unchanged, no prefix); the court's
    geometry comes from ``court`` (:meth:`Court.boxes`, :meth:`Court.legs`,
    :meth:`Court.lines`), the floor plane is at ``court.floor_z``. Collision bits: the
    ball pairs with the robot's collision geoms, the table top, net, posts and floor;
    the legs pair with the robot only; lines and visual geoms with nothing. Compiled
    scenes are cached per (file, modification time, court).

    Args:
        robot_xml: robot MJCF file (default: ``robots/serve_robot.xml``). Its robot must
            carry the body/site ``racket``, the site ``ball_cup`` and the geom ``blade``.
        court: the court geometry.

    Raises:
        RobotModelError: the file is missing, unreadable, or lacks the named elements.
    """
    path = Path(robot_xml) if robot_xml is not None else robots_dir() / MJCF_NAME
    if not path.is_file():
        raise RobotModelError(f"{path}: robot MJCF file not found")
    path = path.resolve()
    return _scene_cached(str(path), path.stat().st_mtime_ns, court)


# =====================================================================================
# Results
# =====================================================================================


@dataclass(frozen=True, slots=True)
class RolloutOptions:
    """Numerical settings of :func:`rollout` and the impulse of non-blade robot contacts."""

    substep: float = 0.25e-3
    """Spacing of the narrowphase grid near a geom [s]; grid points that provably hold no
    contact (conservative advancement) are skipped. At 0.25 ms a ball cannot cross any
    geom of the scene between two grid points below ~170 m/s of relative speed."""
    time_tolerance: float = 1e-9
    """Tolerance of the contact instant found by root finding on the distance [s]."""
    rearm_distance: float = 1e-5
    """A geom the ball has just touched counts again only once the ball has been this far
    from it [m] (one contact is counted once; small enough for near-rest bounces)."""
    sink_depth: float = 1e-3
    """A geom not yet re-armed counts again if the ball sinks this deep into it [m]
    (the geom pushes the ball again before it got away: a double hit / carry)."""
    max_step: float = 0.01
    """RK4 step of the ball flight [s] (the same as :func:`studio.physics.ball.simulate`'s
    default, so free flights agree to round-off)."""
    robot_restitution: float = 0.5
    """Normal restitution [-] of the ball on robot geoms other than the blade faces
    (links, handle, cup, blade rim); tangential velocity and spin are kept (assumption:
    such a contact makes the serve illegal, only its qualitative outcome matters)."""
    stop_on_floor: bool = True
    """End the rollout at the first floor contact (the contact is recorded)."""
    max_contacts: int = 64
    """Safety limit on the number of contacts."""
    rest_speed: float = 0.02
    """Normal rebound speed relative to the touched surface [m/s] below which a contact
    ends the rollout ("rest": the ball would rest or roll on it, which the impulse maps do
    not model)."""
    rim_cosine: float = 0.5
    """Blade contacts whose normal makes an angle with the face normal larger than
    ``acos(rim_cosine)`` (60 deg) hit the rim: simple restitution instead of the rubber model."""

    def __post_init__(self) -> None:
        for name in ("substep", "time_tolerance", "rearm_distance", "sink_depth", "max_step", "rest_speed"):
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0.0):
                raise InvalidInputError(f"RolloutOptions.{name} must be a positive finite number, got {val!r}")
        for name in ("robot_restitution", "rim_cosine"):
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and 0.0 <= val <= 1.0):
                raise InvalidInputError(f"RolloutOptions.{name} must be in [0, 1], got {val!r}")
        if not (isinstance(self.max_contacts, int) and self.max_contacts >= 1):
            raise InvalidInputError(f"RolloutOptions.max_contacts must be an int >= 1, got {self.max_contacts!r}")


@dataclass(frozen=True, slots=True)
class Contact:
    """One ball contact of a rollout (world frame, SI units)."""

    t: float
    """Contact instant [s] (clock of the rollout's ``t``)."""
    kind: ContactKind
    """``"racket"`` (blade), ``"robot"`` (any other robot geom), ``"table"``, ``"net"``,
    ``"post"`` or ``"floor"``."""
    geom: str
    """Name of the MuJoCo geom the ball touched."""
    body: str
    """Name of the body of that geom (``"world"`` for the court)."""
    part: str
    """Racket: ``"face_a"``, ``"face_b"`` or ``"rim"``; table: ``"top"`` or ``"edge"``;
    otherwise the geom name."""
    p: FloatArray
    """Ball centre at contact [m], (3,)."""
    point: FloatArray
    """Contact point on the geom's surface [m], (3,)."""
    normal: FloatArray
    """Unit contact normal (3,), from the geom towards the ball centre."""
    v_before: FloatArray
    """Ball velocity just before [m/s], (3,)."""
    v_after: FloatArray
    """Ball velocity just after [m/s], (3,)."""
    w_before: FloatArray
    """Ball spin just before [rad/s], (3,)."""
    w_after: FloatArray
    """Ball spin just after [rad/s], (3,)."""
    surface_velocity: FloatArray
    """Velocity of the touched surface at the contact point [m/s], (3,) (0 for the court)."""
    side: Literal["server", "receiver"] | None = None
    """Table half for table and floor contacts (x < 0: server), else None."""

    @property
    def position(self) -> FloatArray:
        """Alias of :attr:`p`: ball centre at contact [m]."""
        return self.p


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
    """The :class:`studio.toss.model.Release` when the ball started in the cup and left it, else
    None."""
    t_final: float
    """Time the rollout ended [s] (``t_end``, or the instant of the stopping contact)."""
    end_reason: Literal["t_end", "floor", "rest", "max_contacts", "in_cup"]
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


# =====================================================================================
# Rollout engine
# =====================================================================================

_CHUNK: Final[int] = 128
"""Robot samples posed per batch (the robot is posed lazily, as far as the ball flies)."""

_BROAD_MARGIN: Final[float] = 0.005
"""Extra broadphase margin [m]: curvature of ball and robot paths between samples."""

_SPEED_SLACK: Final[float] = 0.1
"""Added to speed bounds of the conservative advancement [m/s] (curvature of the paths
within a sample interval)."""

_DISTMAX: Final[float] = 0.05
"""Cut-off of the narrowphase distance queries [m] (farther geoms report this)."""

Piece = tuple[float, float, list[float], list[float], list[float], list[float]]
"""A flight interval ``(ta, tb, y(ta), y'(ta), y(tb), y'(tb))`` of the 9-state [p, v, w]."""


@functools.lru_cache(maxsize=1)
def _default_dynamics() -> JointDynamics:
    from studio.robot.model import load_robot

    return load_robot().dynamics


def _hermite_rows(theta: FloatArray, h: FloatArray, ya: FloatArray, fa: FloatArray, yb: FloatArray, fb: FloatArray) -> FloatArray:
    """Vectorized cubic Hermite: theta, h (K,), the rest (K, n) -> (K, n)."""
    th = theta[:, None]
    t2 = th * th
    t3 = t2 * th
    hh = h[:, None]
    return (2 * t3 - 3 * t2 + 1) * ya + (t3 - 2 * t2 + th) * hh * fa + (-2 * t3 + 3 * t2) * yb + (t3 - t2) * hh * fb


def _surface_frame(n: FloatArray) -> FloatArray:
    """Rotation (3, 3) whose third column is the unit vector ``n``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, n)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], axis=1)


class _RobotTrack:
    """The predicted robot motion on the command grid, posed in MuJoCo batch by batch.

    Per sample: centres of the robot's contact geoms, the union box of their bounding
    spheres, the cup site and the racket orientation. Between samples the joints are
    cubic-Hermite interpolated from the predicted positions and velocities.
    """

    def __init__(self, scene: Scene, data: mujoco.MjData, t0: float, dt: float, Q: FloatArray, QD: FloatArray) -> None:
        m = scene.model
        self.scene = scene
        self.m = m
        self.d = data
        self.t0 = t0
        self.dt = dt
        self.Q = Q
        self.QD = QD
        self.n = Q.shape[0]
        self.geoms = np.array([g for g in scene.contact_geoms if m.geom_bodyid[g] != 0], dtype=np.intp)
        self.rb = np.array(m.geom_rbound[self.geoms], dtype=float)
        # hinge_chain[i, j]: robot joint j is a hinge that moves geom i (its angular speed
        # bound is the sum of these joints' speeds)
        self.hinge_chain = np.zeros((self.geoms.size, scene.robot_dof.size))
        dof_index = {int(a): j for j, a in enumerate(scene.robot_dof)}
        for i, g in enumerate(self.geoms):
            b = int(m.geom_bodyid[g])
            while b > 0:
                for jnt in range(int(m.body_jntadr[b]), int(m.body_jntadr[b] + m.body_jntnum[b])):
                    if int(m.jnt_type[jnt]) == int(mujoco.mjtJoint.mjJNT_HINGE):
                        j = dof_index.get(int(m.jnt_dofadr[jnt]))
                        if j is not None:
                            self.hinge_chain[i, j] = 1.0
                b = int(m.body_parentid[b])
        G = self.geoms.size
        self.centers = np.empty((self.n, G, 3))
        self.lo = np.empty((self.n, 3))
        self.hi = np.empty((self.n, 3))
        self.cup = np.empty((self.n, 3))
        self.R = np.empty((self.n, 3, 3))
        self._gx = np.empty((self.n, m.ngeom, 3))
        self._sx = np.empty((self.n, m.nsite, 3))
        self._xm = np.empty((self.n, 9))
        self.done = 0
        adr = scene.robot_qpos
        self.qslice = slice(int(adr[0]), int(adr[0]) + adr.size) if np.all(np.diff(adr) == 1) else None
        self.qadr = adr
        self.dof = scene.robot_dof

    def _set_q(self, q: FloatArray) -> None:
        if self.qslice is not None:
            self.d.qpos[self.qslice] = q
        else:
            self.d.qpos[self.qadr] = q

    def ensure(self, k: int) -> None:
        """Pose samples up to index ``k`` (inclusive)."""
        k = min(k, self.n - 1)
        if k < self.done:
            return
        m, d = self.m, self.d
        start = self.done
        stop = min(self.n, max(k + 1, start + _CHUNK))
        gx, sx, xm = d.geom_xpos, d.site_xpos, d.xmat
        GX, SX, XM = self._gx, self._sx, self._xm
        qv = d.qpos[self.qslice] if self.qslice is not None else None
        racket = self.scene.racket_body
        for i in range(start, stop):
            if qv is not None:
                qv[:] = self.Q[i]
            else:
                d.qpos[self.qadr] = self.Q[i]
            mujoco.mj_kinematics(m, d)
            GX[i] = gx
            SX[i] = sx
            XM[i] = xm[racket]
        c = GX[start:stop][:, self.geoms]
        self.centers[start:stop] = c
        self.cup[start:stop] = SX[start:stop, self.scene.cup_site]
        self.R[start:stop] = XM[start:stop].reshape(-1, 3, 3)
        self.lo[start:stop] = np.min(c - self.rb[None, :, None], axis=1)
        self.hi[start:stop] = np.max(c + self.rb[None, :, None], axis=1)
        self.done = stop

    def _interp(self, tau: float) -> tuple[int, float]:
        x = (tau - self.t0) / self.dt
        k = min(max(int(math.floor(x)), 0), self.n - 2)
        return k, min(max(x - k, 0.0), 1.0)

    def q_at(self, tau: float) -> tuple[FloatArray, FloatArray]:
        """Joint positions and velocities (8,) at time ``tau`` (Hermite interpolation)."""
        k, th = self._interp(tau)
        h = self.dt
        qa, qb, va, vb = self.Q[k], self.Q[k + 1], self.QD[k], self.QD[k + 1]
        t2 = th * th
        t3 = t2 * th
        q = (2 * t3 - 3 * t2 + 1) * qa + (t3 - 2 * t2 + th) * h * va + (-2 * t3 + 3 * t2) * qb + (t3 - t2) * h * vb
        qd = ((6 * t2 - 6 * th) * qa + (-6 * t2 + 6 * th) * qb) / h + (3 * t2 - 4 * th + 1) * va + (3 * t2 - 2 * th) * vb
        return q, qd

    def q_batch(self, taus: FloatArray) -> FloatArray:
        """Joint positions (K, 8) at times ``taus`` (K,) (Hermite interpolation)."""
        x = (taus - self.t0) / self.dt
        k = np.clip(np.floor(x).astype(np.intp), 0, self.n - 2)
        th = np.clip(x - k, 0.0, 1.0)
        return _hermite_rows(th, np.full(k.size, self.dt), self.Q[k], self.QD[k], self.Q[k + 1], self.QD[k + 1])

    def set_pose(self, q: FloatArray) -> None:
        """Pose the robot in ``data`` at joint positions ``q`` (8,) (mj_kinematics)."""
        self._set_q(q)
        mujoco.mj_kinematics(self.m, self.d)

    def pose(self, tau: float) -> None:
        """Pose the robot in ``data`` at time ``tau`` (mj_kinematics)."""
        q, _ = self.q_at(tau)
        self._set_q(q)
        mujoco.mj_kinematics(self.m, self.d)

    def point_velocity(self, tau: float, body: int, point: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Velocity [m/s] of the body-fixed ``point`` (3,) and the body's angular velocity
        [rad/s] at time ``tau`` (robot posed at ``tau``; point Jacobian of MuJoCo)."""
        _, qd = self.q_at(tau)
        self.pose(tau)
        mujoco.mj_comPos(self.m, self.d)
        jacp = np.zeros((3, self.m.nv))
        jacr = np.zeros((3, self.m.nv))
        mujoco.mj_jac(self.m, self.d, jacp, jacr, point, body)
        return jacp[:, self.dof] @ qd, jacr[:, self.dof] @ qd


def _static_boxes(scene: Scene, d: mujoco.MjData) -> tuple[list[int], FloatArray, FloatArray]:
    """World AABBs (S, 3) lo/hi of the court's contact geoms (planes: the half-space below)."""
    m = scene.model
    ids = [int(g) for g in scene.contact_geoms if m.geom_bodyid[g] == 0]
    lo = np.empty((len(ids), 3))
    hi = np.empty((len(ids), 3))
    for i, g in enumerate(ids):
        R = d.geom_xmat[g].reshape(3, 3)
        c = d.geom_xpos[g]
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            lo[i] = -np.inf
            hi[i] = np.inf
            if R[2, 2] > 1.0 - 1e-12:  # horizontal plane, normal +Z: solid below
                hi[i, 2] = c[2]
        else:
            aabb = m.geom_aabb[g]
            cw = c + R @ aabb[:3]
            hw = np.abs(R) @ aabb[3:]
            lo[i] = cw - hw
            hi[i] = cw + hw
    return ids, lo, hi


def _as_array(value: npt.ArrayLike, name: str, shape: tuple[int, ...]) -> FloatArray:
    """Validated float array (shape, finite) or InvalidInputError naming ``rollout: name``."""
    return checked_array(value, shape, f"rollout: {name}", read_only=False)  # type: ignore[no-any-return]


def _restitution(v: FloatArray, v_surface: FloatArray, n: FloatArray, e: float) -> FloatArray:
    """Velocity after a frictionless impact with restitution ``e`` on a surface moving at
    ``v_surface`` with unit normal ``n`` (towards the ball)."""
    vn = float((v - v_surface) @ n)
    if vn >= 0.0:
        return v.copy()
    return v - (1.0 + e) * vn * n


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
    options: RolloutOptions = RolloutOptions(),
) -> RolloutResult:
    """Roll out joint commands on the MuJoCo scene: robot motion, ball flight and contacts.

    The robot follows the joint motion predicted from the commands by the joint model
    (``dynamics.simulate(u, dt, X0)``), or the given predicted states ``X``. The ball
    either starts from ``ball`` (a :class:`~studio.physics.ball.BallState` at ``t[0]``) or, with
    ``ball="cup"``, rides in the ball cup until :func:`studio.toss.model.find_release` (on the
    predicted cup motion) releases it. See the module docstring for flight, contact
    search and impact maps.

    Args:
        scene: from :func:`build_scene`.
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
    if not isinstance(scene, Scene):
        raise InvalidInputError(f"rollout: scene must be a Scene (build_scene()), got {type(scene).__name__}")
    if not isinstance(options, RolloutOptions):
        raise InvalidInputError(f"rollout: options must be RolloutOptions, got {type(options).__name__}")
    try:
        tt = np.array(t, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"rollout: t must be an array of times, got {type(t).__name__}") from exc
    if tt.ndim != 1 or tt.size < 3:
        raise InvalidInputError(f"rollout: t must have shape (N,) with N >= 3, got {tt.shape}")
    if not np.all(np.isfinite(tt)):
        raise InvalidInputError("rollout: t must be finite")
    N = tt.size
    dt = float(tt[1] - tt[0])
    steps = np.diff(tt)
    if not dt > 0.0 or float(np.max(np.abs(steps - dt))) > 1e-9 + 1e-6 * dt:
        raise InvalidInputError("rollout: t must be strictly increasing with a uniform step")
    t0 = float(tt[0])
    nq = scene.robot_qpos.size
    if isinstance(ball, str):
        if ball != "cup":
            raise InvalidInputError(f"rollout: ball must be a BallState or 'cup', got {ball!r}")
    elif not isinstance(ball, BallState):
        raise InvalidInputError(f"rollout: ball must be a BallState or 'cup', got {type(ball).__name__}")
    if t_end is not None and not isinstance(t_end, (int, float, np.floating, np.integer)):
        raise InvalidInputError(f"rollout: t_end must be a number [s] or None, got {type(t_end).__name__}")
    t_stop = float(tt[-1]) if t_end is None else float(t_end)
    if not (math.isfinite(t_stop) and t_stop > t0):
        raise InvalidInputError(f"rollout: t_end must be finite and > t[0] = {t0}, got {t_end!r}")
    n_total = max(N, int(math.ceil((t_stop - t0) / dt - 1e-9)) + 1)

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
        Xa = _as_array(Xa[:n_total], "X", (n_total, nq, 2))
    else:
        if u is None:
            raise InvalidInputError("rollout: give the joint commands u (or the predicted states X)")
        U = _as_array(u, "u", (N, nq))
        dyn = dynamics if dynamics is not None else _default_dynamics()
        if tuple(dyn.names) != scene.joint_names:
            raise RobotModelError(f"rollout: joint model joints {tuple(dyn.names)} differ from the scene's {scene.joint_names}")
        X0a = np.stack([U[0], np.zeros(nq)], axis=1) if X0 is None else _as_array(X0, "X0", (nq, 2))
        if n_total > N:
            U = np.concatenate([U, np.repeat(U[-1:], n_total - N, axis=0)])
        Xa = dyn.simulate(U, dt, X0a)
    Q = np.ascontiguousarray(Xa[:, :, 0])
    QD = np.ascontiguousarray(Xa[:, :, 1])
    grid = t0 + dt * np.arange(n_total)
    if abs(flight.gravity - float(-scene.model.opt.gravity[2])) > 1e-9:
        raise InvalidInputError(
            f"rollout: flight.gravity = {flight.gravity} differs from the scene's {-scene.model.opt.gravity[2]}"
        )

    m = scene.model
    d = mujoco.MjData(m)
    track = _RobotTrack(scene, d, t0, dt, Q, QD)
    mujoco.mj_kinematics(m, d)
    static_ids, static_lo, static_hi = _static_boxes(scene, d)
    bg = scene.ball_geom
    r = float(m.geom_size[bg, 0])
    if abs(flight.radius - r) > 1e-12:
        raise InvalidInputError(f"rollout: flight.radius = {flight.radius} differs from the scene's ball radius {r}")
    opts = options
    geom_body = m.geom_bodyid
    rearm = opts.rearm_distance
    sink = opts.sink_depth
    geom_distance = mujoco.mj_geomDistance
    deriv = flight.scalar_derivative()  # the flight equations of studio.physics.ball, on floats

    # --- start: ball in the cup or given ---------------------------------------------
    release: Release | None = None
    cup_until = -1  # last grid index at which the ball is in the cup
    if isinstance(ball, str):
        track.ensure(n_total - 1)
        release = find_release(grid, track.cup, track.R[:, :, 2], rotation=track.R, gravity=flight.gravity, drag_k=flight.drag_constant)
        if release is None or release.time >= t_stop:
            return _in_cup_result(grid, track, Q, t_stop)
        t_start = float(release.time)
        y = [*release.position.tolist(), *release.velocity.tolist(), *release.angular_velocity.tolist()]
        cup_until = int(np.searchsorted(grid, t_start, side="left")) - 1
    else:
        t_start = t0
        y = [*ball.p.tolist(), *ball.v.tolist(), *ball.w.tolist()]

    # geoms touching the ball at the start (e.g. the cup at release) count only once left
    track.pose(t_start)
    d.geom_xpos[bg] = y[0:3]
    disarmed: set[int] = {
        int(g) for g in scene.contact_geoms if geom_distance(m, d, bg, int(g), _DISTMAX, None) <= rearm
    }

    def ball_pos(tau: float, ta: float, h: float, ya: list[float], fa: list[float], yb: list[float], fb: list[float]) -> list[float]:
        return hermite((tau - ta) / h if h > 0.0 else 0.0, h, ya, fa, yb, fb, 3)

    def search(ta: float, h: float, ya: list[float], fa: list[float], yb: list[float], fb: list[float]) -> tuple[float, int] | None:
        """First contact with a geom in [ta, ta + h], or None.

        Broadphase: the court's boxes against the ball's box over the step; the robot's
        geoms by their bounding spheres at the grid samples. Narrowphase near the
        candidates: signed distances (MuJoCo) on a grid of ``substep`` spacing, skipping
        grid points by conservative advancement (no contact can happen before
        ``distance / closing-speed bound``), the crossing refined by Brent's method.
        """
        tb = ta + h
        pad = r + _BROAD_MARGIN
        plo = np.minimum(ya[0:3], yb[0:3]) - pad
        phi = np.maximum(ya[0:3], yb[0:3]) + pad
        s_hit = np.all(static_lo <= phi, axis=1) & np.all(static_hi >= plo, axis=1)
        cands = [static_ids[i] for i in np.flatnonzero(s_hit)]
        speeds = [0.0] * len(cands)  # speed bound of each candidate's surface [m/s]
        w_lo, w_hi = ta, tb
        ka = min(max(int(math.floor((ta - t0) / dt)), 0), n_total - 1)
        kb = min(int(math.ceil((tb - t0) / dt)), n_total - 1)
        track.ensure(kb)
        any_robot = False
        if np.all(np.min(track.lo[ka : kb + 1], axis=0) <= phi) and np.all(np.max(track.hi[ka : kb + 1], axis=0) >= plo):
            ks = np.arange(ka, kb + 1)
            ts = grid[ks]
            K = ks.size
            th = np.clip((ts - ta) / h, 0.0, 1.0) if h > 0.0 else np.zeros(K)
            ones = np.ones((K, 1))
            P = _hermite_rows(th, np.full(K, h), ones * ya[0:3], ones * fa[0:3], ones * yb[0:3], ones * fb[0:3])
            Cg = track.centers[ka : kb + 1]
            gap = np.linalg.norm(P[:, None, :] - Cg, axis=2) - track.rb[None, :] - r
            if K > 1:
                dP = float(np.max(np.linalg.norm(np.diff(P, axis=0), axis=1)))
                dC = np.max(np.linalg.norm(np.diff(Cg, axis=0), axis=2), axis=0)
            else:
                dP, dC = 0.0, np.zeros(Cg.shape[1])
            near = gap <= (dP + dC + _BROAD_MARGIN)[None, :]
            gsel = np.flatnonzero(np.any(near, axis=0))
            if gsel.size:
                any_robot = True
                # surface speed bound: centre chord speed (+ slack for its curvature)
                # + angular speed bound (sum of the chain's hinge speeds) x bounding radius
                omega = np.max(np.abs(track.QD[ka : kb + 1]) @ track.hinge_chain[gsel].T, axis=0)
                vg = dC[gsel] / dt + _SPEED_SLACK + omega * track.rb[gsel]
                cands.extend(int(g) for g in track.geoms[gsel])
                speeds.extend(float(x) for x in vg)
                if not s_hit.any():  # restrict the fine search to the robot's window
                    rows = np.flatnonzero(np.any(near, axis=1))
                    w_lo = max(ta, float(ts[rows[0]]) - dt)
                    w_hi = min(tb, float(ts[rows[-1]]) + dt)
        if disarmed:
            for g in [g for g in disarmed if g not in cands]:
                disarmed.discard(g)  # far from the ball: armed again
        if not cands:
            return None
        span = w_hi - w_lo
        if span <= 0.0:
            return None
        n_sub = max(1, math.ceil(span / opts.substep - 1e-9))
        h_sub = span / n_sub
        taus = w_lo + h_sub * np.arange(n_sub + 1)
        th = (taus - ta) / h if h > 0.0 else np.zeros(n_sub + 1)
        ones = np.ones((n_sub + 1, 1))
        Pb = _hermite_rows(th, np.full(n_sub + 1, h), ones * ya[0:3], ones * fa[0:3], ones * yb[0:3], ones * fb[0:3])
        Qs = track.q_batch(taus) if any_robot else None
        v_ball = math.sqrt(max(ya[3] ** 2 + ya[4] ** 2 + ya[5] ** 2, yb[3] ** 2 + yb[4] ** 2 + yb[5] ** 2))
        a_ball = math.sqrt(max(fa[3] ** 2 + fa[4] ** 2 + fa[5] ** 2, fb[3] ** 2 + fb[4] ** 2 + fb[5] ** 2))
        v_ball += a_ball * h + _SPEED_SLACK
        closing = [v_ball + vg for vg in speeds]
        prev = None
        i = 0
        while i <= n_sub:
            tau = float(taus[i])
            if Qs is not None:
                track.set_pose(Qs[i])
            d.geom_xpos[bg] = Pb[i]
            crossing: list[tuple[int, float]] = []
            safe = math.inf
            for j, g in enumerate(cands):
                dist = geom_distance(m, d, bg, g, _DISTMAX, None)
                level = 0.0
                if g in disarmed:
                    if dist > rearm:
                        disarmed.discard(g)
                    else:
                        level = -sink  # touching since the last contact: only a new push counts
                if dist <= level:
                    crossing.append((g, level))
                else:
                    safe = min(safe, (dist - level) / closing[j])
            if crossing:
                if prev is None:
                    return tau, crossing[0][0]
                best: tuple[float, int] | None = None
                for g, level in crossing:
                    robot_g = bool(geom_body[g] != 0)

                    def gap_at(s: float, g: int = g, robot_g: bool = robot_g, level: float = level) -> float:
                        if robot_g:
                            track.pose(s)
                        d.geom_xpos[bg] = ball_pos(s, ta, h, ya, fa, yb, fb)
                        return geom_distance(m, d, bg, g, _DISTMAX, None) - level

                    if gap_at(prev) <= 0.0:
                        tc = prev
                    else:
                        tc = float(brentq(gap_at, prev, tau, xtol=opts.time_tolerance, rtol=1e-15))
                    if best is None or tc < best[0]:
                        best = (tc, g)
                return best
            prev = tau
            i += max(1, int(safe / h_sub)) if safe < math.inf else n_sub + 1
        return None

    # --- flight with contacts ------------------------------------------------------------
    f = deriv(y)
    t_cur = t_start
    pieces: list[Piece] = []
    contacts: list[Contact] = []
    end_reason: Literal["t_end", "floor", "rest", "max_contacts", "in_cup"] = "t_end"
    fromto = np.zeros(6)
    while t_cur < t_stop - 1e-12:
        h = min(opts.max_step, t_stop - t_cur)
        if t_stop - (t_cur + h) < 1e-9:
            h = t_stop - t_cur
        y1, f1 = rk4_step(deriv, y, f, h)
        hit = search(t_cur, h, y, f, y1, f1)
        if hit is None:
            pieces.append((t_cur, t_cur + h, y, f, y1, f1))
            t_cur, y, f = t_cur + h, y1, f1
            continue

        tc, g = hit
        ye = hermite((tc - t_cur) / h, h, y, f, y1, f1, 9)
        fe = deriv(ye)
        pieces.append((t_cur, tc, y, f, ye, fe))
        contact = _impact(
            scene, track, d, g, tc, ye, r, fromto, table=table, net=net, racket_model=racket_model, options=opts
        )
        contacts.append(contact)
        disarmed.add(g)
        t_cur = tc
        y = [*ye[0:3], *contact.v_after.tolist(), *contact.w_after.tolist()]
        f = deriv(y)
        if contact.kind == "floor" and opts.stop_on_floor:
            end_reason = "floor"
            break
        if float((contact.v_after - contact.surface_velocity) @ contact.normal) < opts.rest_speed:
            end_reason = "rest"  # no rebound worth the name: resting/rolling contact
            break
        if len(contacts) >= opts.max_contacts:
            end_reason = "max_contacts"
            break
    pieces.append((t_cur, t_cur, y, f, y, f))
    return _assemble(grid, track, Q, pieces, contacts, release, cup_until, t_cur, end_reason)


def _impact(
    scene: Scene,
    track: _RobotTrack,
    d: mujoco.MjData,
    g: int,
    tc: float,
    ye: list[float],
    r: float,
    fromto: FloatArray,
    *,
    table: TableBounceModel,
    net: NetModel,
    racket_model: RacketModel | None,
    options: RolloutOptions,
) -> Contact:
    """Contact geometry from MuJoCo at ``tc`` and the rebound from the impulse maps."""
    m = scene.model
    bg = scene.ball_geom
    body = int(m.geom_bodyid[g])
    if body != 0:
        track.pose(tc)
    p = np.array(ye[0:3])
    v_b = np.array(ye[3:6])
    w_b = np.array(ye[6:9])
    d.geom_xpos[bg] = p
    mujoco.mj_geomDistance(m, d, bg, g, _DISTMAX, fromto)
    point = fromto[3:6].copy()
    nv = p - point
    nn = float(np.linalg.norm(nv))
    if nn > 1e-9:
        normal = nv / nn
    else:  # degenerate (cannot happen at a first touch): use the ball's surface point
        nv = p - fromto[0:3]
        normal = nv / max(float(np.linalg.norm(nv)), 1e-12)
    kind = cast(ContactKind, scene.geom_kind[g])
    name = scene.geom_name(g)
    v_s = np.zeros(3)
    side: Literal["server", "receiver"] | None = None
    if kind == "floor":
        part = "floor"
        v_a, w_a = table.bounce(v_b, w_b)
        side = scene.court.side(float(p[0]))
    elif kind == "table":
        part = "top" if normal[2] > 1.0 - 1e-9 else "edge"
        if part == "top":
            v_a, w_a = table.bounce(v_b, w_b)
        else:
            F = _surface_frame(normal)
            v2, w2 = table.bounce(F.T @ v_b, F.T @ w_b)
            v_a, w_a = F @ v2, F @ w2
        side = scene.court.side(float(p[0]))
    elif kind in ("net", "post"):
        part = name
        v_a, w_a = net.bounce(v_b, w_b, normal, "net" if kind == "net" else "post")
    else:
        v_s, w_s = track.point_velocity(tc, body, point)
        part = name
        v_a, w_a = _restitution(v_b, v_s, normal, options.robot_restitution), w_b.copy()
        if kind == "racket":
            R = d.xmat[scene.racket_body].reshape(3, 3).copy()
            c = float(normal @ R[:, 2])
            if abs(c) >= options.rim_cosine:
                s = 1.0 if c > 0.0 else -1.0
                part = "face_a" if s > 0.0 else "face_b"
                if racket_model is None:
                    racket_model = RacketModel.default()
                v_c, _ = track.point_velocity(tc, body, p)  # racket point at the ball centre
                v_a, w_a = racket_model.bounce_moving(v_b, w_b, R, v_c, s, omega=w_s)
            else:
                part = "rim"
    for a in (p, point, normal, v_b, v_a, w_b, w_a, v_s):
        a.setflags(write=False)
    return Contact(
        t=float(tc),
        kind=kind,
        geom=name,
        body=scene.body_name(body),
        part=part,
        p=p,
        point=point,
        normal=normal,
        v_before=v_b,
        v_after=v_a,
        w_before=w_b,
        w_after=w_a,
        surface_velocity=v_s,
        side=side,
    )


def _cup_states(grid: FloatArray, track: _RobotTrack, n: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Ball in the cup on the first ``n`` samples: cup centre, its velocity (second-order
    differences, as :func:`studio.toss.model.find_release`) and the racket's angular velocity."""
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


def _in_cup_result(grid: FloatArray, track: _RobotTrack, Q: FloatArray, t_stop: float) -> RolloutResult:
    M = int(np.searchsorted(grid, t_stop + 1e-9, side="right"))
    p, v, w = _cup_states(grid, track, M)
    tq, q = grid[:M].copy(), Q[:M].copy()
    _frozen(tq, p, v, w, q)
    return RolloutResult(
        t=tq, p=p, v=v, w=w, q=q, contacts=(), release=None, t_final=float(t_stop), end_reason="in_cup"
    )


def _assemble(
    grid: FloatArray,
    track: _RobotTrack,
    Q: FloatArray,
    pieces: list[Piece],
    contacts: list[Contact],
    release: Release | None,
    cup_until: int,
    t_final: float,
    end_reason: Literal["t_end", "floor", "rest", "max_contacts", "in_cup"],
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
        yq = _hermite_rows(th, h, arr[idx, 0], arr[idx, 1], arr[idx, 2], arr[idx, 3])
        P[n_cup:], V[n_cup:], W[n_cup:] = yq[:, 0:3], yq[:, 3:6], yq[:, 6:9]
    q = Q[:M].copy()
    _frozen(tq, P, V, W, q)
    return RolloutResult(
        t=tq, p=P, v=V, w=W, q=q, contacts=tuple(contacts), release=release, t_final=float(t_final), end_reason=end_reason
    )
