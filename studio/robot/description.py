"""Robot description generator: ``robots/serve_robot.toml`` -> URDF and MJCF.

The TOML file is the single source of truth of the 8-DoF serve robot (XY gantry +
KUKA KR 6 R900 sixx + racket with ball cup). This module reads and validates it
(:func:`load_spec`, errors are :class:`~studio.errors.RobotModelError` naming the key)
and renders

- ``robots/serve_robot.urdf`` (:func:`to_urdf`) for pinocchio, coal, yourdfpy/viser;
- ``robots/serve_robot.xml`` (:func:`to_mjcf`) for MuJoCo: the robot alone.

Run ``serve-studio robot-files`` to (re)write both files, ``--check`` to
verify that the committed files are what the TOML generates (exit code 1 otherwise).

Both files use the same link / joint names. Frames ``racket`` (blade centre, z = face-A
normal, y towards the blade tip) and ``ball_cup`` (centre of the resting ball) are
URDF links on fixed joints and MJCF bodies carrying sites of the same names.

Composing a MuJoCo scene (robot + table + ball)::

    import mujoco
    from studio.robot.description import robot_mjspec

    scene = mujoco.MjSpec()                # or mujoco.MjSpec.from_string(court_xml)
    scene.option.timestep = 0.001          # recommended; integrator implicitfast
    frame = scene.worldbody.add_frame()    # identity: the robot is in world coordinates
    scene.attach(robot_mjspec(), frame=frame, prefix="")   # keeps joint/site names
    model = scene.compile()

The robot's bodies are placed in world coordinates already (``[base]`` of the TOML),
so the attachment frame is the identity; an empty prefix keeps the joint, actuator,
geom and site names of this module (MuJoCo warns that such a model may not be
saveable as XML; compile it from the spec instead). The robot MJCF sets no
``<option>``: the scene owns the time step and integrator.

MuJoCo conventions of the generated model:

- collision geoms: group 3, ``contype=2, conaffinity=1``: the robot does not collide
  with itself in MuJoCo (self-collision is checked with coal on the URDF), but does
  collide with any geom of ``contype`` 1 (MuJoCo's default: table, ball, floor);
  collision geom names are the TOML names (``blade``, ``handle``, ``cup_plate``,
  ``cup_wall_<k>`` are the racket's; :data:`RACKET_GEOMS` lists them);
- visual geoms: group 1, no contacts, no mass, name ``<collision name>_visual``;
- one ``position`` actuator per actuated joint (same name as the joint) with
  ``kp = armature * wn^2`` and ``kv = 2 zeta wn armature``: with the (large) joint
  armature dominating the inertia this approximates the joint model of
  :class:`studio.robot.model.JointDynamics`; for an exact match drive ``qpos`` from
  ``JointDynamics.simulate`` instead;
- ``gravcomp="1"`` on every body with mass: gravity is compensated as by the robot's
  own controller, so a held command does not sag.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal
from xml.sax.saxutils import quoteattr

import numpy as np

from studio import constants as C
from studio.errors import RobotModelError
from studio.paths import robots_dir
from studio.storage.jsonfile import not_utf8_message

ROBOT_NAME: Final[str] = "serve_robot"
"""Stem of the robot files in ``robots/``."""

TOML_NAME: Final[str] = f"{ROBOT_NAME}.toml"
"""File name of the source of truth."""

URDF_NAME: Final[str] = f"{ROBOT_NAME}.urdf"
"""File name of the generated URDF."""

MJCF_NAME: Final[str] = f"{ROBOT_NAME}.xml"
"""File name of the generated MJCF."""

SCHEMA_VERSION: Final[int] = 1
"""Version of the TOML layout understood by this module."""

RACKET_FRAME: Final[str] = "racket"
"""Name of the racket frame (URDF link, MJCF body and site)."""

BALL_CUP_FRAME: Final[str] = "ball_cup"
"""Name of the resting-ball frame (URDF link, MJCF body and site)."""

RACKET_BLADE_GEOM: Final[str] = "blade"
"""Name of the blade collision geom (MJCF geom, URDF collision name)."""

GeomKind = Literal["box", "cylinder", "sphere"]
GeomUse = Literal["visual", "collision", "both"]
JointType = Literal["prismatic", "revolute", "fixed"]

_RACKET_TOL: Final[float] = 1e-9


# --------------------------------------------------------------------------------------
# Data model
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class GeomSpec:
    """One geometric primitive of a link, in the link frame."""

    name: str
    """Unique name (collision name in URDF, geom name in MJCF)."""
    kind: GeomKind
    """Primitive type."""
    use: GeomUse
    """Whether the primitive is drawn, collides, or both."""
    xyz: tuple[float, float, float]
    """Origin of the primitive in the link frame [m]."""
    rpy: tuple[float, float, float]
    """Orientation (URDF roll-pitch-yaw) in the link frame [rad]; cylinders' axis is z."""
    size: tuple[float, float, float]
    """Box full extents [m] (zeros for other kinds)."""
    radius: float
    """Cylinder / sphere radius [m] (0 for boxes)."""
    length: float
    """Cylinder length along its z axis [m] (0 otherwise)."""
    rgba: tuple[float, float, float, float]
    """Display colour, components in [0, 1]."""


@dataclass(frozen=True, slots=True)
class LinkSpec:
    """A rigid link: inertial properties and primitives, in its own frame."""

    name: str
    """Link name (URDF link, MJCF body)."""
    mass: float
    """Mass [kg] (0: massless frame or static link)."""
    com: tuple[float, float, float]
    """Centre of mass in the link frame [m]."""
    inertia: tuple[float, float, float]
    """Principal moments (ixx, iyy, izz) about the com, link axes [kg m^2]."""
    geoms: tuple[GeomSpec, ...]
    """Visual and collision primitives."""


@dataclass(frozen=True, slots=True)
class JointSpec:
    """A joint from ``parent`` to ``child``; actuated joints carry limits and dynamics."""

    name: str
    """Joint name (identical in URDF and MJCF)."""
    type: JointType
    """``prismatic``, ``revolute`` or ``fixed``."""
    parent: str
    """Parent link name."""
    child: str
    """Child link name."""
    xyz: tuple[float, float, float]
    """Child frame origin in the parent frame at q = 0 [m]."""
    rpy: tuple[float, float, float]
    """Child frame orientation in the parent frame (URDF rpy) [rad]."""
    axis: tuple[float, float, float]
    """Unit joint axis in the child frame (zeros for fixed joints)."""
    lower: float = 0.0
    """Lower position limit [m | rad]."""
    upper: float = 0.0
    """Upper position limit [m | rad]."""
    velocity: float = 0.0
    """Speed limit [m/s | rad/s]."""
    acceleration: float = 0.0
    """Acceleration limit [m/s^2 | rad/s^2]."""
    jerk: float = 0.0
    """Jerk limit [m/s^3 | rad/s^3]."""
    effort: float = 0.0
    """Nominal force / torque [N | N m] (URDF attribute)."""
    wn: float = 0.0
    """Natural frequency of the command->position model [rad/s]."""
    zeta: float = 0.0
    """Damping ratio of the command->position model [-]."""
    armature: float = 0.0
    """Reflected drive inertia [kg | kg m^2] (MuJoCo)."""

    @property
    def actuated(self) -> bool:
        """True for prismatic and revolute joints."""
        return self.type != "fixed"


@dataclass(frozen=True, slots=True)
class RacketSpec:
    """Racket on the flange and its ball cup (see the ``[racket]``/``[cup]`` tables)."""

    parent: str
    """Link the racket is mounted on (the flange)."""
    adapter_length: float
    """Flange face to handle butt, along the handle axis [m]."""
    adapter_radius: float
    """Radius of the adapter cylinder [m]."""
    blade_width: float
    """Blade extent along racket x [m]."""
    blade_length: float
    """Blade extent along racket y [m]."""
    half_thickness: float
    """Half thickness of blade + rubbers [m]."""
    handle_length: float
    """Handle length along racket y [m]."""
    handle_width: float
    """Handle extent along racket x [m]."""
    handle_thickness: float
    """Handle extent along racket z [m]."""
    mass: float
    """Mass of racket + adapter + cup [kg]."""
    com: tuple[float, float, float]
    """Centre of mass in the racket frame [m]."""
    inertia: tuple[float, float, float]
    """Principal moments about the com, racket axes [kg m^2]."""
    cup_y: float
    """Cup centre along racket y [m] (negative: on the handle)."""
    cup_plate_radius: float
    """Radius of the cup's base plate [m]."""
    cup_plate_thickness: float
    """Thickness of the cup's base plate [m]."""
    cup_wall_height: float
    """Height of the cup wall above the plate [m]."""
    cup_wall_thickness: float
    """Radial thickness of the cup wall blocks [m]."""
    cup_wall_count: int
    """Number of wall blocks in the ring."""
    cup_rim_radius: float
    """Inner radius of the wall ring [m] (< ball radius: the ball rests on the rim)."""
    ball_radius: float
    """Ball radius [m]."""

    @property
    def mount_offset(self) -> float:
        """Distance flange face -> racket origin along the handle axis [m]."""
        return self.adapter_length + self.handle_length + 0.5 * self.blade_length

    @property
    def rim_top(self) -> float:
        """Height of the top of the cup wall above the racket mid-plane [m]."""
        return 0.5 * self.handle_thickness + self.cup_plate_thickness + self.cup_wall_height

    @property
    def ball_centre(self) -> tuple[float, float, float]:
        """Resting ball centre in the racket frame [m].

        The ball sits on the inner top edges of the wall blocks (distance ``rim_radius``
        from the cup axis), so its centre is sqrt(R^2 - r_rim^2) above the rim top.
        """
        z = self.rim_top + math.sqrt(self.ball_radius**2 - self.cup_rim_radius**2)
        return (0.0, self.cup_y, z)


@dataclass(frozen=True, slots=True)
class RobotSpec:
    """The validated content of the robot TOML file."""

    name: str
    """Robot name."""
    base_xyz: tuple[float, float, float]
    """World position of ``gantry_base`` [m]."""
    base_rpy: tuple[float, float, float]
    """World orientation of ``gantry_base`` (URDF rpy) [rad]."""
    joints: tuple[JointSpec, ...]
    """All joints of the TOML, chain order (racket joints excluded)."""
    links: tuple[LinkSpec, ...]
    """All links of the TOML (racket links excluded)."""
    racket: RacketSpec
    """Racket and cup."""
    q_rest: tuple[float, ...]
    """Rest configuration (8,) [m, m, rad x 6]."""
    q_flat: tuple[float, ...]
    """Toss-start configuration (8,) [m, m, rad x 6]."""
    sources: Mapping[str, str]
    """Citations of the data used."""

    @property
    def actuated_joints(self) -> tuple[JointSpec, ...]:
        """The 8 actuated joints in chain order."""
        return tuple(j for j in self.joints if j.actuated)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the actuated joints in chain order."""
        return tuple(j.name for j in self.actuated_joints)


# --------------------------------------------------------------------------------------
# TOML parsing and validation
# --------------------------------------------------------------------------------------


def default_toml_path() -> Path:
    """Path of the shipped ``serve_robot.toml``."""
    return robots_dir() / TOML_NAME


def _err(key: str, message: str, path: Path | None) -> RobotModelError:
    where = f"{path}: " if path is not None else ""
    return RobotModelError(f"{where}key '{key}': {message}")


class _Reader:
    """Typed access to a TOML table with errors naming the full key."""

    def __init__(self, table: Mapping[str, Any], prefix: str, path: Path | None) -> None:
        if not isinstance(table, Mapping):
            raise _err(prefix, "must be a table", path)
        self.table = table
        self.prefix = prefix
        self.path = path

    def key(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def err(self, name: str, message: str) -> RobotModelError:
        return _err(self.key(name), message, self.path)

    def raw(self, name: str, default: Any = ...) -> Any:
        if name not in self.table:
            if default is ...:
                raise self.err(name, "missing")
            return default
        return self.table[name]

    def string(self, name: str, default: Any = ...) -> str:
        value = self.raw(name, default)
        if not isinstance(value, str) or not value:
            raise self.err(name, f"must be a non-empty string, got {value!r}")
        return value

    def number(
        self,
        name: str,
        default: Any = ...,
        *,
        positive: bool = False,
        nonnegative: bool = False,
    ) -> float:
        value = self.raw(name, default)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.err(name, f"must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.err(name, f"must be finite, got {value!r}")
        if positive and value <= 0.0:
            raise self.err(name, f"must be > 0, got {value!r}")
        if nonnegative and value < 0.0:
            raise self.err(name, f"must be >= 0, got {value!r}")
        return value

    def integer(self, name: str, *, minimum: int) -> int:
        value = self.raw(name)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise self.err(name, f"must be an integer >= {minimum}, got {value!r}")
        return value

    def vector(self, name: str, n: int, default: Any = ..., *, nonnegative: bool = False) -> tuple[float, ...]:
        value = self.raw(name, default)
        if not isinstance(value, list | tuple) or len(value) != n:
            raise self.err(name, f"must be a list of {n} numbers, got {value!r}")
        out: list[float] = []
        for k, v in enumerate(value):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
                raise self.err(f"{name}[{k}]", f"must be a finite number, got {v!r}")
            if nonnegative and v < 0:
                raise self.err(f"{name}[{k}]", f"must be >= 0, got {v!r}")
            out.append(float(v))
        return tuple(out)

    def sub(self, name: str) -> _Reader:
        return _Reader(self.raw(name), self.key(name), self.path)

    def array_of_tables(self, name: str, default: Any = ...) -> list[_Reader]:
        value = self.raw(name, default)
        if not isinstance(value, list):
            raise self.err(name, "must be an array of tables")
        return [_Reader(item, f"{self.key(name)}[{k}]", self.path) for k, item in enumerate(value)]

    def check_unknown(self, allowed: set[str]) -> None:
        for name in self.table:
            if name not in allowed:
                raise self.err(name, f"unknown key (allowed: {', '.join(sorted(allowed))})")


def _v3(t: tuple[float, ...]) -> tuple[float, float, float]:
    return (t[0], t[1], t[2])


_GEOM_KEYS: Final[set[str]] = {"name", "kind", "use", "xyz", "rpy", "size", "radius", "length", "color"}
_LINK_KEYS: Final[set[str]] = {"name", "mass", "com", "inertia", "geoms"}
_JOINT_KEYS_FIXED: Final[set[str]] = {"name", "type", "parent", "child", "xyz", "rpy"}
_JOINT_KEYS_ACTUATED: Final[set[str]] = _JOINT_KEYS_FIXED | {
    "axis",
    "lower",
    "upper",
    "velocity",
    "acceleration",
    "jerk",
    "effort",
    "wn",
    "zeta",
    "armature",
}
_RACKET_KEYS: Final[set[str]] = {
    "parent",
    "adapter_length",
    "adapter_radius",
    "blade_width",
    "blade_length",
    "half_thickness",
    "handle_length",
    "handle_width",
    "handle_thickness",
    "mass",
    "inertia",
    "com",
}
_CUP_KEYS: Final[set[str]] = {
    "y",
    "plate_radius",
    "plate_thickness",
    "wall_height",
    "wall_thickness",
    "wall_count",
    "rim_radius",
    "ball_radius",
}
_TOP_KEYS: Final[set[str]] = {
    "schema_version",
    "name",
    "base",
    "colors",
    "joints",
    "links",
    "racket",
    "cup",
    "poses",
    "sources",
}


def _parse_geom(r: _Reader, colors: Mapping[str, tuple[float, float, float, float]]) -> GeomSpec:
    r.check_unknown(_GEOM_KEYS)
    kind = r.string("kind")
    if kind not in ("box", "cylinder", "sphere"):
        raise r.err("kind", f"must be 'box', 'cylinder' or 'sphere', got {kind!r}")
    use = r.string("use", "both")
    if use not in ("visual", "collision", "both"):
        raise r.err("use", f"must be 'visual', 'collision' or 'both', got {use!r}")
    color = r.string("color", "gantry")
    if color not in colors:
        raise r.err("color", f"unknown colour {color!r} (defined in [colors]: {', '.join(sorted(colors))})")
    size = (0.0, 0.0, 0.0)
    radius = length = 0.0
    if kind == "box":
        size = _v3(r.vector("size", 3))
        if min(size) <= 0:
            raise r.err("size", f"box extents must be > 0, got {size}")
    else:
        radius = r.number("radius", positive=True)
        if kind == "cylinder":
            length = r.number("length", positive=True)
    return GeomSpec(
        name=r.string("name"),
        kind=kind,  # type: ignore[arg-type]
        use=use,  # type: ignore[arg-type]
        xyz=_v3(r.vector("xyz", 3, [0.0, 0.0, 0.0])),
        rpy=_v3(r.vector("rpy", 3, [0.0, 0.0, 0.0])),
        size=size,
        radius=radius,
        length=length,
        rgba=colors[color],
    )


def _parse_joint(r: _Reader) -> JointSpec:
    jtype = r.string("type")
    if jtype not in ("prismatic", "revolute", "fixed"):
        raise r.err("type", f"must be 'prismatic', 'revolute' or 'fixed', got {jtype!r}")
    common = dict(
        name=r.string("name"),
        type=jtype,
        parent=r.string("parent"),
        child=r.string("child"),
        xyz=_v3(r.vector("xyz", 3, [0.0, 0.0, 0.0])),
        rpy=_v3(r.vector("rpy", 3, [0.0, 0.0, 0.0])),
    )
    if jtype == "fixed":
        r.check_unknown(_JOINT_KEYS_FIXED)
        return JointSpec(axis=(0.0, 0.0, 0.0), **common)  # type: ignore[arg-type]
    r.check_unknown(_JOINT_KEYS_ACTUATED)
    axis = np.asarray(r.vector("axis", 3), dtype=float)
    if abs(float(np.linalg.norm(axis)) - 1.0) > 1e-9:
        raise r.err("axis", f"must be a unit vector, got {tuple(axis)}")
    lower = r.number("lower")
    upper = r.number("upper")
    if not lower < upper:
        raise r.err("upper", f"must be > lower ({lower}), got {upper}")
    zeta = r.number("zeta", positive=True)
    return JointSpec(
        axis=_v3(tuple(float(a) for a in axis)),
        lower=lower,
        upper=upper,
        velocity=r.number("velocity", positive=True),
        acceleration=r.number("acceleration", positive=True),
        jerk=r.number("jerk", positive=True),
        effort=r.number("effort", positive=True),
        wn=r.number("wn", positive=True),
        zeta=zeta,
        armature=r.number("armature", positive=True),
        **common,  # type: ignore[arg-type]
    )


def _parse_racket(rr: _Reader, rc: _Reader) -> RacketSpec:
    rr.check_unknown(_RACKET_KEYS)
    rc.check_unknown(_CUP_KEYS)
    spec = RacketSpec(
        parent=rr.string("parent"),
        adapter_length=rr.number("adapter_length", nonnegative=True),
        adapter_radius=rr.number("adapter_radius", positive=True),
        blade_width=rr.number("blade_width", positive=True),
        blade_length=rr.number("blade_length", positive=True),
        half_thickness=rr.number("half_thickness", positive=True),
        handle_length=rr.number("handle_length", positive=True),
        handle_width=rr.number("handle_width", positive=True),
        handle_thickness=rr.number("handle_thickness", positive=True),
        mass=rr.number("mass", positive=True),
        com=_v3(rr.vector("com", 3)),
        inertia=_v3(rr.vector("inertia", 3, nonnegative=True)),
        cup_y=rc.number("y"),
        cup_plate_radius=rc.number("plate_radius", positive=True),
        cup_plate_thickness=rc.number("plate_thickness", positive=True),
        cup_wall_height=rc.number("wall_height", positive=True),
        cup_wall_thickness=rc.number("wall_thickness", positive=True),
        cup_wall_count=rc.integer("wall_count", minimum=3),
        cup_rim_radius=rc.number("rim_radius", positive=True),
        ball_radius=rc.number("ball_radius", positive=True),
    )
    expected = {
        ("racket", "blade_width"): C.RACKET_BLADE_WIDTH,
        ("racket", "blade_length"): C.RACKET_BLADE_LENGTH,
        ("racket", "half_thickness"): C.RACKET_HALF_THICKNESS,
        ("racket", "handle_length"): C.RACKET_HANDLE_LENGTH,
        ("cup", "ball_radius"): C.BALL_RADIUS,
    }
    for (table, key), value in expected.items():
        reader = rr if table == "racket" else rc
        got = reader.number(key)
        if abs(got - value) > _RACKET_TOL:
            raise reader.err(key, f"must equal studio.constants value {value}, got {got}")
    handle_end = -0.5 * spec.blade_length - spec.handle_length
    if not handle_end + spec.cup_plate_radius <= spec.cup_y <= -0.5 * spec.blade_length - spec.cup_plate_radius + 1e-12:
        raise rc.err("y", f"cup (radius {spec.cup_plate_radius}) must lie on the handle, got y = {spec.cup_y}")
    if not spec.cup_rim_radius < spec.ball_radius:
        raise rc.err("rim_radius", f"must be < ball_radius {spec.ball_radius} (the ball rests on the rim)")
    if spec.cup_rim_radius + spec.cup_wall_thickness > spec.cup_plate_radius + 1e-12:
        raise rc.err("plate_radius", "must be >= rim_radius + wall_thickness")
    sag = spec.ball_radius - math.sqrt(spec.ball_radius**2 - spec.cup_rim_radius**2)
    if sag >= spec.cup_wall_height:
        raise rc.err(
            "wall_height", f"must exceed the ball's sag below the rim ({sag:.4f} m) so it does not touch the plate"
        )
    return spec


def _parse_colors(col: _Reader) -> dict[str, tuple[float, float, float, float]]:
    """The ``[colors]`` table: name -> RGBA, components in [0, 1]."""
    colors: dict[str, tuple[float, float, float, float]] = {}
    for cname in col.table:
        rgba = col.vector(cname, 4)
        if not all(0.0 <= c <= 1.0 for c in rgba):
            raise col.err(cname, f"components must be in [0, 1], got {rgba}")
        colors[cname] = (rgba[0], rgba[1], rgba[2], rgba[3])
    return colors


def _parse_link(lr: _Reader, colors: Mapping[str, tuple[float, float, float, float]]) -> LinkSpec:
    """One ``[[links]]`` entry with its geoms (a link with mass needs positive inertia)."""
    lr.check_unknown(_LINK_KEYS)
    mass = lr.number("mass", nonnegative=True)
    geoms = tuple(_parse_geom(g, colors) for g in lr.array_of_tables("geoms", []))
    link = LinkSpec(
        name=lr.string("name"),
        mass=mass,
        com=_v3(lr.vector("com", 3, [0.0, 0.0, 0.0])),
        inertia=_v3(lr.vector("inertia", 3, [0.0, 0.0, 0.0], nonnegative=True)),
        geoms=geoms,
    )
    if mass > 0 and min(link.inertia) <= 0:
        raise lr.err("inertia", "must be > 0 for a link with mass")
    return link


def _check_tree(link_names: list[str], joints: list[JointSpec], path: Path | None) -> None:
    """A single tree rooted at gantry_base: names unique and not reserved, one parent per link."""
    reserved = {"world", RACKET_FRAME, BALL_CUP_FRAME}
    for k, lname in enumerate(link_names):
        if lname in reserved:
            raise _err(f"links[{k}].name", f"{lname!r} is reserved (generated)", path)
        if link_names.count(lname) > 1:
            raise _err(f"links[{k}].name", f"duplicate link name {lname!r}", path)
    children: set[str] = set()
    for k, j in enumerate(joints):
        for role in ("parent", "child"):
            lname = getattr(j, role)
            if lname not in link_names:
                raise _err(f"joints[{k}].{role}", f"unknown link {lname!r}", path)
        if j.child in children:
            raise _err(f"joints[{k}].child", f"link {j.child!r} has two parent joints", path)
        children.add(j.child)
        if [jj.name for jj in joints].count(j.name) > 1:
            raise _err(f"joints[{k}].name", f"duplicate joint name {j.name!r}", path)
    roots = [n for n in link_names if n not in children]
    if roots != ["gantry_base"]:
        raise _err("links", f"exactly one root link 'gantry_base' expected, found roots {roots}", path)


def _check_geom_names(links: list[LinkSpec], racket: RacketSpec, path: Path | None) -> None:
    """Every geom name, the generated racket geoms' included, is unique."""
    geom_names = [g.name for lk in links for g in lk.geoms] + list(_racket_geom_names(racket))
    for gname in geom_names:
        if geom_names.count(gname) > 1:
            raise _err("links", f"duplicate geom name {gname!r}", path)


def _parse_poses(poses: _Reader, actuated: list[JointSpec]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(q_rest, q_flat) of the ``[poses]`` table, each within the actuated joints' limits."""
    poses.check_unknown({"q_rest", "q_flat"})
    q_rest = poses.vector("q_rest", 8)
    q_flat = poses.vector("q_flat", 8)
    for pname, q in (("q_rest", q_rest), ("q_flat", q_flat)):
        for k, (j, v) in enumerate(zip(actuated, q, strict=True)):
            if not j.lower <= v <= j.upper:
                raise poses.err(f"{pname}[{k}]", f"joint {j.name!r}: {v} outside [{j.lower}, {j.upper}]")
    return q_rest, q_flat


def parse_spec(data: Mapping[str, Any], *, path: Path | None = None) -> RobotSpec:
    """Validate a parsed TOML document and return the :class:`RobotSpec`.

    Raises:
        RobotModelError: naming the offending key (and ``path`` when given).
    """
    top = _Reader(data, "", path)
    top.check_unknown(_TOP_KEYS)
    version = top.raw("schema_version")
    if version != SCHEMA_VERSION:
        raise top.err("schema_version", f"must be {SCHEMA_VERSION}, got {version!r}")
    name = top.string("name")
    base = top.sub("base")
    base.check_unknown({"xyz", "rpy"})
    colors = _parse_colors(top.sub("colors"))
    links = [_parse_link(lr, colors) for lr in top.array_of_tables("links")]
    joints = [_parse_joint(jr) for jr in top.array_of_tables("joints")]
    racket = _parse_racket(top.sub("racket"), top.sub("cup"))
    # Structure: a single chain / tree rooted at gantry_base, names unique.
    _check_tree([lk.name for lk in links], joints, path)
    if racket.parent not in [lk.name for lk in links]:
        raise _err("racket.parent", f"unknown link {racket.parent!r}", path)
    actuated = [j for j in joints if j.actuated]
    if len(actuated) != 8:
        raise _err("joints", f"the serve robot needs 8 actuated joints, found {len(actuated)}", path)
    _check_geom_names(links, racket, path)
    q_rest, q_flat = _parse_poses(top.sub("poses"), actuated)
    src = top.sub("sources")
    sources = {k: src.string(k) for k in src.table}
    if not sources:
        raise _err("sources", "must cite at least one source", path)
    return RobotSpec(
        name=name,
        base_xyz=_v3(base.vector("xyz", 3)),
        base_rpy=_v3(base.vector("rpy", 3)),
        joints=tuple(joints),
        links=tuple(links),
        racket=racket,
        q_rest=q_rest,
        q_flat=q_flat,
        sources=sources,
    )


def load_spec(path: str | Path | None = None) -> RobotSpec:
    """Read and validate the robot TOML (default: the shipped ``serve_robot.toml``).

    Raises:
        RobotModelError: file missing / not TOML (message names the path), or a key
            missing or malformed (message names the key).
    """
    p = Path(path) if path is not None else default_toml_path()
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise RobotModelError(f"{p}: the robot description is {not_utf8_message(exc)}") from None
    except OSError as exc:
        raise RobotModelError(f"{p}: cannot read robot description: {exc.strerror or exc}") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RobotModelError(f"{p}: not valid TOML: {exc}") from exc
    return parse_spec(data, path=p)


# --------------------------------------------------------------------------------------
# Racket geometry (generated from [racket] and [cup])
# --------------------------------------------------------------------------------------

_RACKET_COLORS: Final[dict[str, tuple[float, float, float, float]]] = {
    "red": (0.80, 0.08, 0.08, 1.0),
    "black": (0.08, 0.08, 0.08, 1.0),
    "wood": (0.80, 0.62, 0.40, 1.0),
    "cup": (0.20, 0.45, 0.85, 1.0),
    "flange": (0.75, 0.75, 0.78, 1.0),
}


def _racket_geom_names(r: RacketSpec) -> tuple[str, ...]:
    adapter = ("racket_adapter",) if r.adapter_length > 0 else ()
    return (
        adapter + ("handle", RACKET_BLADE_GEOM, "cup_plate") + tuple(f"cup_wall_{k}" for k in range(r.cup_wall_count))
    )


def _racket_geom(
    name: str,
    kind: GeomKind,
    use: GeomUse,
    xyz: tuple[float, float, float],
    rpy: tuple[float, float, float],
    *,
    size: tuple[float, float, float] = (0.0, 0.0, 0.0),
    radius: float = 0.0,
    length: float = 0.0,
    color: str,
) -> GeomSpec:
    """One racket primitive in one of the racket's named colours."""
    return GeomSpec(name, kind, use, xyz, rpy, size, radius, length, _RACKET_COLORS[color])


def _handle_geoms(r: RacketSpec) -> list[GeomSpec]:
    """The flange adapter (when it has a length) and the handle box."""
    handle_y = -0.5 * r.blade_length - 0.5 * r.handle_length
    adapter_y = -0.5 * r.blade_length - r.handle_length - 0.5 * r.adapter_length
    out: list[GeomSpec] = []
    if r.adapter_length > 0:
        out.append(
            _racket_geom(
                "racket_adapter",
                "cylinder",
                "both",
                (0.0, adapter_y, 0.0),
                (0.5 * math.pi, 0.0, 0.0),
                radius=r.adapter_radius,
                length=r.adapter_length,
                color="flange",
            )
        )
    size = (r.handle_width, r.handle_length, r.handle_thickness)
    out.append(_racket_geom("handle", "box", "both", (0.0, handle_y, 0.0), (0.0, 0.0, 0.0), size=size, color="wood"))
    return out


def _blade_geoms(r: RacketSpec) -> list[GeomSpec]:
    """The blade's collision cylinder and its two visual faces (red A at z > 0, black B)."""
    blade_r = 0.25 * (r.blade_width + r.blade_length)
    h = r.half_thickness
    origin = (0.0, 0.0, 0.0)
    return [
        _racket_geom(RACKET_BLADE_GEOM, "cylinder", "collision", origin, origin, radius=blade_r, length=2 * h, color="red"),
        _racket_geom("face_a", "cylinder", "visual", (0.0, 0.0, 0.5 * h), origin, radius=blade_r, length=h, color="red"),
        _racket_geom("face_b", "cylinder", "visual", (0.0, 0.0, -0.5 * h), origin, radius=blade_r, length=h, color="black"),
    ]  # fmt: skip


def _cup_geoms(r: RacketSpec) -> list[GeomSpec]:
    """The cup plate on face A of the handle and its ring of ``wall_count`` wall blocks."""
    z_plate = 0.5 * r.handle_thickness + 0.5 * r.cup_plate_thickness
    out = [
        _racket_geom(
            "cup_plate",
            "cylinder",
            "both",
            (0.0, r.cup_y, z_plate),
            (0.0, 0.0, 0.0),
            radius=r.cup_plate_radius,
            length=r.cup_plate_thickness,
            color="cup",
        )
    ]
    r_in = r.cup_rim_radius
    r_mid = r_in + 0.5 * r.cup_wall_thickness
    n = r.cup_wall_count
    chord = 2.0 * (r_in + r.cup_wall_thickness) * math.tan(math.pi / n)
    z_wall = 0.5 * r.handle_thickness + r.cup_plate_thickness + 0.5 * r.cup_wall_height
    for k in range(n):
        a = 2.0 * math.pi * k / n
        out.append(
            _racket_geom(
                f"cup_wall_{k}",
                "box",
                "both",
                (r_mid * math.cos(a), r.cup_y + r_mid * math.sin(a), z_wall),
                (0.0, 0.0, a),
                size=(r.cup_wall_thickness, chord, r.cup_wall_height),
                color="cup",
            )
        )
    return out


def racket_geoms(r: RacketSpec) -> tuple[GeomSpec, ...]:
    """Primitives of the ``racket`` link, in the racket frame.

    Blade: a cylinder (axis = racket z) of radius (width + length)/4 and thickness
    2 * half_thickness, drawn as a red face A (z > 0) and a black face B. Handle: a box.
    Cup: a plate on face A of the handle and a ring of ``wall_count`` blocks whose inner
    faces are ``rim_radius`` from the cup axis; the ball rests on their inner top edges.
    """
    return tuple(_handle_geoms(r) + _blade_geoms(r) + _cup_geoms(r))


RACKET_GEOMS: Final[tuple[str, ...]] = ("racket_adapter", "handle", RACKET_BLADE_GEOM, "cup_plate")
"""Names of the racket's collision geoms (plus ``cup_wall_<k>``, k < cup.wall_count)."""


def _racket_mount_rpy() -> tuple[float, float, float]:
    # racket x = flange y, racket y = flange z, racket z = flange x.
    return (0.5 * math.pi, 0.0, 0.5 * math.pi)


def full_tree(spec: RobotSpec) -> tuple[tuple[LinkSpec, ...], tuple[JointSpec, ...]]:
    """All links and joints of the robot, racket and cup frames included, in tree order."""
    r = spec.racket
    racket_link = LinkSpec(RACKET_FRAME, r.mass, r.com, r.inertia, racket_geoms(r))
    cup_link = LinkSpec(BALL_CUP_FRAME, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), ())
    zero3 = (0.0, 0.0, 0.0)
    joints = list(spec.joints) + [
        JointSpec(
            f"{r.parent}_to_racket",
            "fixed",
            r.parent,
            RACKET_FRAME,
            (0.0, 0.0, r.mount_offset),
            _racket_mount_rpy(),
            zero3,
        ),
        JointSpec("racket_to_ball_cup", "fixed", RACKET_FRAME, BALL_CUP_FRAME, r.ball_centre, zero3, zero3),
    ]
    links = list(spec.links) + [racket_link, cup_link]
    # Depth-first order from the root so that MJCF bodies and pinocchio joints agree.
    by_parent: dict[str, list[JointSpec]] = {}
    for j in joints:
        by_parent.setdefault(j.parent, []).append(j)
    ordered: list[JointSpec] = []

    def visit(link: str) -> None:
        for j in by_parent.get(link, []):
            ordered.append(j)
            visit(j.child)

    visit("gantry_base")
    return tuple(links), tuple(ordered)


# --------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------


def _f(x: float) -> str:
    """Stable number formatting (no -0, 10 significant digits)."""
    s = f"{x:.10g}"
    return "0" if s in ("-0", "0") else s


def _vec(v: Sequence[float]) -> str:
    return " ".join(_f(x) for x in v)


def _rpy_to_quat(rpy: Sequence[float]) -> tuple[float, float, float, float]:
    """URDF rpy (R = Rz(yaw) Ry(pitch) Rx(roll)) -> quaternion (w, x, y, z)."""
    cr, sr = math.cos(rpy[0] / 2), math.sin(rpy[0] / 2)
    cp, sp = math.cos(rpy[1] / 2), math.sin(rpy[1] / 2)
    cy, sy = math.cos(rpy[2] / 2), math.sin(rpy[2] / 2)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    return (w, x, y, z)


def _urdf_geometry(g: GeomSpec) -> str:
    if g.kind == "box":
        return f'<box size="{_vec(g.size)}"/>'
    if g.kind == "cylinder":
        return f'<cylinder radius="{_f(g.radius)}" length="{_f(g.length)}"/>'
    return f'<sphere radius="{_f(g.radius)}"/>'


def to_urdf(spec: RobotSpec) -> str:
    """Render the URDF text (primitives only, materials inline, root link ``world``)."""
    links, joints = full_tree(spec)
    lines = [
        '<?xml version="1.0"?>',
        "<!-- GENERATED by `serve-studio robot-files` from robots/serve_robot.toml: do not edit. -->",
        f"<robot name={quoteattr(spec.name)}>",
        '  <link name="world"/>',
        '  <joint name="world_to_gantry_base" type="fixed">',
        f'    <origin xyz="{_vec(spec.base_xyz)}" rpy="{_vec(spec.base_rpy)}"/>',
        '    <parent link="world"/>',
        '    <child link="gantry_base"/>',
        "  </joint>",
    ]
    for lk in links:
        lines.append(f"  <link name={quoteattr(lk.name)}>")
        if lk.mass > 0:
            ixx, iyy, izz = lk.inertia
            lines += [
                "    <inertial>",
                f'      <origin xyz="{_vec(lk.com)}" rpy="0 0 0"/>',
                f'      <mass value="{_f(lk.mass)}"/>',
                f'      <inertia ixx="{_f(ixx)}" ixy="0" ixz="0" iyy="{_f(iyy)}" iyz="0" izz="{_f(izz)}"/>',
                "    </inertial>",
            ]
        for g in lk.geoms:
            origin = f'<origin xyz="{_vec(g.xyz)}" rpy="{_vec(g.rpy)}"/>'
            if g.use in ("visual", "both"):
                lines += [
                    f"    <visual name={quoteattr(g.name + '_visual')}>",
                    f"      {origin}",
                    f"      <geometry>{_urdf_geometry(g)}</geometry>",
                    f'      <material name={quoteattr(g.name + "_material")}><color rgba="{_vec(g.rgba)}"/></material>',
                    "    </visual>",
                ]
            if g.use in ("collision", "both"):
                lines += [
                    f"    <collision name={quoteattr(g.name)}>",
                    f"      {origin}",
                    f"      <geometry>{_urdf_geometry(g)}</geometry>",
                    "    </collision>",
                ]
        lines.append("  </link>")
    for j in joints:
        lines += [
            f"  <joint name={quoteattr(j.name)} type={quoteattr(j.type)}>",
            f'    <origin xyz="{_vec(j.xyz)}" rpy="{_vec(j.rpy)}"/>',
            f"    <parent link={quoteattr(j.parent)}/>",
            f"    <child link={quoteattr(j.child)}/>",
        ]
        if j.actuated:
            lines += [
                f'    <axis xyz="{_vec(j.axis)}"/>',
                f'    <limit lower="{_f(j.lower)}" upper="{_f(j.upper)}" velocity="{_f(j.velocity)}" effort="{_f(j.effort)}"/>',
            ]
        lines.append("  </joint>")
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def _mjcf_geom_size(g: GeomSpec) -> str:
    if g.kind == "box":
        return _vec(tuple(0.5 * s for s in g.size))
    if g.kind == "cylinder":
        return _vec((g.radius, 0.5 * g.length))
    return _f(g.radius)


def to_mjcf(spec: RobotSpec) -> str:
    """Render the MJCF text of the robot alone (see the module docstring for composing)."""
    links, joints = full_tree(spec)
    link_by_name = {lk.name: lk for lk in links}
    children: dict[str, list[JointSpec]] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)

    out = [
        "<!-- GENERATED by `serve-studio robot-files` from robots/serve_robot.toml: do not edit. -->",
        f"<mujoco model={quoteattr(spec.name)}>",
        '  <compiler angle="radian" autolimits="true" inertiafromgeom="false"/>',
        "  <worldbody>",
    ]

    def pose_attrs(xyz: Sequence[float], rpy: Sequence[float]) -> str:
        attrs = f'pos="{_vec(xyz)}"'
        if any(abs(a) > 0 for a in rpy):
            attrs += f' quat="{_vec(_rpy_to_quat(rpy))}"'
        return attrs

    def body(name: str, xyz: Sequence[float], rpy: Sequence[float], joint: JointSpec | None, indent: int) -> None:
        pad = "  " * indent
        lk = link_by_name[name]
        grav = ' gravcomp="1"' if lk.mass > 0 else ""
        out.append(f"{pad}<body name={quoteattr(name)} {pose_attrs(xyz, rpy)}{grav}>")
        if joint is not None and joint.actuated:
            kind = "slide" if joint.type == "prismatic" else "hinge"
            out.append(
                f'{pad}  <joint name={quoteattr(joint.name)} type="{kind}" axis="{_vec(joint.axis)}" '
                f'range="{_f(joint.lower)} {_f(joint.upper)}" armature="{_f(joint.armature)}" limited="true"/>'
            )
        if lk.mass > 0:
            out.append(f'{pad}  <inertial pos="{_vec(lk.com)}" mass="{_f(lk.mass)}" diaginertia="{_vec(lk.inertia)}"/>')
        if name in (RACKET_FRAME, BALL_CUP_FRAME):
            out.append(f'{pad}  <site name={quoteattr(name)} pos="0 0 0" size="0.005" rgba="0 1 0 1"/>')
        for g in lk.geoms:
            common = f'type="{g.kind}" size="{_mjcf_geom_size(g)}" {pose_attrs(g.xyz, g.rpy)} rgba="{_vec(g.rgba)}"'
            if g.use in ("collision", "both"):
                out.append(f'{pad}  <geom name={quoteattr(g.name)} {common} group="3" contype="2" conaffinity="1"/>')
            if g.use in ("visual", "both"):
                out.append(
                    f'{pad}  <geom name={quoteattr(g.name + "_visual")} {common} group="1" contype="0" conaffinity="0" mass="0"/>'
                )
        for cj in children.get(name, []):
            body(cj.child, cj.xyz, cj.rpy, cj, indent + 1)
        out.append(f"{pad}</body>")

    body("gantry_base", spec.base_xyz, spec.base_rpy, None, 2)
    out.append("  </worldbody>")
    out.append("  <actuator>")
    for j in spec.actuated_joints:
        kp = j.armature * j.wn**2
        kv = 2.0 * j.zeta * j.wn * j.armature
        out.append(
            f'    <position name={quoteattr(j.name)} joint={quoteattr(j.name)} kp="{_f(kp)}" kv="{_f(kv)}" '
            f'ctrlrange="{_f(j.lower)} {_f(j.upper)}"/>'
        )
    out.append("  </actuator>")
    out.append("</mujoco>")
    return "\n".join(out) + "\n"


def robot_mjcf_string(spec: RobotSpec | None = None) -> str:
    """The robot's MJCF text (default: from the shipped TOML)."""
    return to_mjcf(spec if spec is not None else load_spec())


def robot_mjspec(spec: RobotSpec | None = None) -> Any:
    """The robot as a ``mujoco.MjSpec`` (default: from the shipped TOML), ready to attach.

    See the module docstring for composing it into a scene.
    """
    import mujoco

    return mujoco.MjSpec.from_string(robot_mjcf_string(spec))


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------


def generate(spec_path: str | Path | None = None) -> dict[str, str]:
    """Texts of the generated files, keyed by file name (``serve_robot.urdf``/``.xml``)."""
    spec = load_spec(spec_path)
    return {URDF_NAME: to_urdf(spec), MJCF_NAME: to_mjcf(spec)}


def write_files(out_dir: str | Path | None = None, *, spec_path: str | Path | None = None) -> list[Path]:
    """Write the URDF and MJCF into ``out_dir`` (default: ``robots/``); returns the paths."""
    d = Path(out_dir) if out_dir is not None else robots_dir()
    written: list[Path] = []
    for fname, text in generate(spec_path).items():
        p = d / fname
        tmp = p.with_suffix(p.suffix + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(p)
        written.append(p)
    return written


def check_files(out_dir: str | Path | None = None, *, spec_path: str | Path | None = None) -> list[str]:
    """Names of generated files that are missing or differ from what the TOML generates."""
    d = Path(out_dir) if out_dir is not None else robots_dir()
    stale: list[str] = []
    for fname, text in generate(spec_path).items():
        p = d / fname
        if not p.is_file() or p.read_text(encoding="utf-8") != text:
            stale.append(fname)
    return stale
