"""The MuJoCo scene of a rollout: robot (``robots/serve_robot.xml``), ITTF table top and
legs, net, posts, lines, floor plane and the ball (free joint, 40 mm sphere, 2.7 g,
thin-shell inertia), with the indices a rollout needs (:func:`build_scene`).

World frame of ``DESIGN.md``, SI units.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import mujoco
import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import InvalidInputError, RobotModelError
from studio.paths import robots_dir
from studio.physics.court import DEFAULT_COURT, Box, Court
from studio.robot.description import (
    BALL_CUP_FRAME,
    MJCF_NAME,
    RACKET_BLADE_GEOM,
    RACKET_FRAME,
)

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


def _add_box(
    spec: mujoco.MjSpec, box: Box, *, contype: int, conaffinity: int, rgba: tuple[float, ...], group: int
) -> None:
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
