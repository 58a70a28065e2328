"""Serve parameters: the paper's genome, its normalized form, and hand-designed serve files.

The paper ("Optimizing serve parameters") optimizes up to ten decision variables: the
contact time tau, the racket velocity at contact v_tau (3), the racket orientation as two
Euler angles (yaw, roll), the return-to-rest duration and an optional contact offset
delta_p (3), with the contact position tied to the toss's mean path,
p_tau = p_bar(tau) + delta_p. Each normalized gene in [0, 1] maps linearly to its
physical range.

Conventions (world frame of ``DESIGN.md``):

- ``tau`` [s] is measured on the toss command clock (t = 0 at the start of the toss
  primitive), like the paper's hit-timing index.
- ``t_return`` [s] is the duration from contact to rest (the planner's tau_f - tau).
- The racket face normal at contact is
  ``n = (cos(roll) sin(yaw), -cos(roll) cos(yaw), sin(roll))``: yaw = pi/2, roll = 0
  faces the receiver (+X); yaw turns the normal about +Z; positive roll tilts it up
  (an open face). The paper's ranges are yaw in pi/2 +/- pi and roll in +/- pi.
- ``velocity`` [m/s] is the racket's linear velocity at contact, world frame.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from studio.errors import DataFileError, InvalidInputError
from studio.storage.jsonfile import lone_surrogate, read_json_file

if TYPE_CHECKING:
    from studio.robot.model import JointLimits

TossSide = Literal["right", "left"]
SERVE_SCHEMA = "serve-studio/serve@1"
"""Schema tag written into hand-designed serve JSON files."""

GENE_NAMES: tuple[str, ...] = (
    "tau",
    "vx",
    "vy",
    "vz",
    "yaw",
    "roll",
    "t_return",
    "dpx",
    "dpy",
    "dpz",
)
"""Order of the genes in the genome vector (10-D; the offset genes are optional)."""


def racket_normal(yaw: float, roll: float) -> npt.NDArray[np.float64]:
    """Unit racket face normal (3,) in the world frame from the genome's yaw and roll [rad]."""
    cr = math.cos(roll)
    return np.array([cr * math.sin(yaw), -cr * math.cos(yaw), math.sin(roll)])


def yaw_roll_from_normal(n: npt.ArrayLike) -> tuple[float, float]:
    """Inverse of :func:`racket_normal`: (yaw, roll) [rad] with roll in [-pi/2, pi/2] and
    yaw in [-pi/2, 3 pi/2) (the paper's yaw range around pi/2)."""
    n = np.asarray(n, dtype=float)
    norm = float(np.linalg.norm(n))
    if not np.isfinite(norm) or norm < 1e-12:
        raise InvalidInputError(f"normal must be a finite non-zero 3-vector, got {n!r}")
    n = n / norm
    roll = math.asin(max(-1.0, min(1.0, n[2])))
    yaw = math.atan2(n[0], -n[1]) if math.hypot(n[0], n[1]) > 1e-12 else math.pi / 2
    if yaw < -math.pi / 2:
        yaw += 2 * math.pi
    return yaw, roll


@dataclass(frozen=True, slots=True)
class GenomeBounds:
    """Physical ranges that the normalized genes [0, 1] map onto (paper's bounds by default)."""

    tau: tuple[float, float] = (0.55, 1.05)
    """Contact time range on the toss clock [s]; should lie after the toss's lift and apex
    (see :meth:`for_toss`)."""
    velocity: tuple[float, float, float] = (10.0, 5.0, 5.0)
    """Half-ranges of the racket velocity components (x, y, z) [m/s], centred on 0 (paper)."""
    yaw: tuple[float, float] = (math.pi / 2 - math.pi, math.pi / 2 + math.pi)
    """Yaw range [rad]: pi/2 +/- pi (paper)."""
    roll: tuple[float, float] = (-math.pi, math.pi)
    """Roll range [rad]: +/- pi (paper)."""
    t_return: tuple[float, float] = (0.4, 1.2)
    """Contact-to-rest duration range [s]."""
    offset: float = 0.07
    """Half-range of each contact offset component [m]: +/- 0.07 (paper)."""

    def __post_init__(self) -> None:
        for name in ("tau", "yaw", "roll", "t_return"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise InvalidInputError(
                    f"GenomeBounds.{name} must be a finite (low, high) with low < high, got {(lo, hi)}"
                )
        if not all(np.isfinite(v) and v > 0 for v in self.velocity):
            raise InvalidInputError(f"GenomeBounds.velocity half-ranges must be positive, got {self.velocity}")
        if not (np.isfinite(self.offset) and self.offset >= 0):
            raise InvalidInputError(f"GenomeBounds.offset must be >= 0, got {self.offset}")

    def lows_highs(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(low (10,), high (10,)) in the order of :data:`GENE_NAMES`."""
        vx, vy, vz = self.velocity
        o = self.offset
        low = np.array([self.tau[0], -vx, -vy, -vz, self.yaw[0], self.roll[0], self.t_return[0], -o, -o, -o])
        high = np.array([self.tau[1], vx, vy, vz, self.yaw[1], self.roll[1], self.t_return[1], o, o, o])
        return low, high


PARAM_RANGES: dict[str, tuple[float, float]] = {
    "tau": (0.05, 3.0),
    "velocity": (-30.0, 30.0),
    "yaw": (-4 * math.pi, 4 * math.pi),
    "roll": (-4 * math.pi, 4 * math.pi),
    "t_return": (0.1, 5.0),
    "offset": (-0.5, 0.5),
}
"""Physically possible range of each serve parameter (each component for vectors): a
toss is over within 3 s; no racket moves faster than 30 m/s (elite smashes reach ~15 m/s
at the racket); the angles wrap (two turns either way accepted); a return to rest longer
than 5 s only wastes time (and memory: the plan is sampled at 1 kHz); a contact 0.5 m
off the toss path misses the ball. Outside them a value is a typo, refused with the
range; inside them the planner and the checks judge the serve."""
PARAM_UNITS = {"tau": "s", "velocity": "m/s", "yaw": "rad", "roll": "rad", "t_return": "s", "offset": "m"}


@dataclass(frozen=True, slots=True)
class ServeParams:
    """One serve's strike parameters in physical units (the decoded genome)."""

    tau: float
    """Contact time on the toss command clock [s]."""
    velocity: tuple[float, float, float]
    """Racket linear velocity at contact, world frame [m/s]."""
    yaw: float
    """Racket normal yaw [rad] (see module docstring)."""
    roll: float
    """Racket normal roll [rad] (see module docstring)."""
    t_return: float = 0.7
    """Duration from contact back to rest [s]."""
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Contact offset delta_p from the toss's mean path at tau, world frame [m]."""

    def __post_init__(self) -> None:
        for name in ("tau", "yaw", "roll", "t_return"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InvalidInputError(f"ServeParams.{name} must be a finite number, got {value!r}")
        for name in ("velocity", "offset"):
            value = getattr(self, name)
            if len(value) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in value):
                raise InvalidInputError(f"ServeParams.{name} must be 3 finite numbers, got {value!r}")
            object.__setattr__(self, name, tuple(float(x) for x in value))
        for name, (lo, hi) in PARAM_RANGES.items():
            values = getattr(self, name)
            for value in values if isinstance(values, tuple) else (values,):
                if not lo <= value <= hi:
                    raise InvalidInputError(
                        f"ServeParams.{name} = {value:.6g} is outside the allowed range [{lo:g}, {hi:g}] ({PARAM_UNITS[name]})"
                    )

    @property
    def normal(self) -> npt.NDArray[np.float64]:
        """Racket face normal at contact (3,), world frame."""
        return racket_normal(self.yaw, self.roll)

    def to_vector(self) -> npt.NDArray[np.float64]:
        """Physical genome (10,) in the order of :data:`GENE_NAMES`."""
        return np.array([self.tau, *self.velocity, self.yaw, self.roll, self.t_return, *self.offset])

    @classmethod
    def from_vector(cls, x: npt.ArrayLike) -> ServeParams:
        """Inverse of :meth:`to_vector` (10,) or (7,) without offsets."""
        x = np.asarray(x, dtype=float).ravel()
        if x.shape not in ((10,), (7,)):
            raise InvalidInputError(f"a physical genome has 7 or 10 genes {GENE_NAMES}, got shape {x.shape}")
        offset = tuple(x[7:10]) if x.size == 10 else (0.0, 0.0, 0.0)
        return cls(
            tau=float(x[0]),
            velocity=(float(x[1]), float(x[2]), float(x[3])),
            yaw=float(x[4]),
            roll=float(x[5]),
            t_return=float(x[6]),
            offset=offset,  # type: ignore[arg-type]
        )

    def normalize(self, bounds: GenomeBounds) -> npt.NDArray[np.float64]:
        """Normalized genome (10,) in [0, 1] (values outside the bounds fall outside [0, 1])."""
        low, high = bounds.lows_highs()
        return (self.to_vector() - low) / (high - low)

    @classmethod
    def denormalize(cls, z: npt.ArrayLike, bounds: GenomeBounds) -> ServeParams:
        """Decode a normalized genome (10,) or (7,) (offsets at 0.5) into physical parameters."""
        z = np.asarray(z, dtype=float).ravel()
        if z.size == 7:
            z = np.concatenate([z, [0.5, 0.5, 0.5]])
        if z.shape != (10,) or not np.all(np.isfinite(z)):
            raise InvalidInputError(f"normalized genome must be 7 or 10 finite genes, got {z!r}")
        low, high = bounds.lows_highs()
        return cls.from_vector(low + z * (high - low))


LIMIT_SCALE_RANGE: tuple[float, float] = (0.25, 4.0)
"""Accepted range of each :class:`LimitScale` factor [-]: a guard against typos (a factor
of 10 would ask the stand-in joint dynamics for accelerations no real arm of this size
reaches), not a property of the robot."""


@dataclass(frozen=True, slots=True)
class LimitScale:
    """The paper's "dynamic limit expansion": factors on the robot's derivative limits.

    The strike planner plans with the robot's velocity, acceleration and jerk limits
    (``robots/serve_robot.toml``) times these factors; position limits never change. The
    paper raised the acceleration and jerk limits once the measured joint torques showed
    headroom, which gave faster serves with more spin. A serve carries the scale it was
    planned with, so that its plan can be reproduced and a controller knows the limits it
    needs (library entries record the effective limits).
    """

    velocity: float = 1.0
    """Factor on the joint speed limits [-]."""
    acceleration: float = 1.0
    """Factor on the joint acceleration limits [-]."""
    jerk: float = 1.0
    """Factor on the joint jerk limits [-]."""

    def __post_init__(self) -> None:
        lo, hi = LIMIT_SCALE_RANGE
        for name in ("velocity", "acceleration", "jerk"):
            value = getattr(self, name)
            try:
                ok = not isinstance(value, bool) and isinstance(value, (int, float)) and lo <= float(value) <= hi
            except OverflowError:  # an integer beyond float range
                ok = False
            if not ok:
                raise InvalidInputError(f"LimitScale.{name} must be a number in [{lo}, {hi}], got {value!r}")
            # rounded to 1e-6: slider steps (1.1500000000000001) give the same scale, file and planner
            object.__setattr__(self, name, round(float(value), 6))

    @classmethod
    def uniform(cls, factor: float) -> LimitScale:
        """The paper's expansion: acceleration and jerk limits times ``factor``, speed unchanged."""
        return cls(acceleration=factor, jerk=factor)

    @property
    def is_identity(self) -> bool:
        """True when every factor is 1 (the robot's own limits)."""
        return self.velocity == 1.0 and self.acceleration == 1.0 and self.jerk == 1.0

    def to_json(self) -> dict[str, float]:
        """``{"velocity": ..., "acceleration": ..., "jerk": ...}``."""
        return {"velocity": self.velocity, "acceleration": self.acceleration, "jerk": self.jerk}

    @classmethod
    def from_json(cls, data: Any, *, source: str = "<limit_scale>") -> LimitScale:
        """Inverse of :meth:`to_json`; missing factors are 1. Errors name ``source`` and the field."""
        if not isinstance(data, dict):
            raise DataFileError(
                source, f"field 'limit_scale': must be an object with velocity/acceleration/jerk factors, got {data!r}"
            )
        unknown = set(data) - {"velocity", "acceleration", "jerk"}
        if unknown:
            raise DataFileError(
                source, f"field 'limit_scale': unknown keys {sorted(unknown)} (known: acceleration, jerk, velocity)"
            )
        try:
            return cls(**{k: data[k] for k in ("velocity", "acceleration", "jerk") if k in data})
        except InvalidInputError as err:
            raise DataFileError(source, f"field 'limit_scale': {err}") from None

    @classmethod
    def parse(cls, text: str) -> LimitScale:
        """From a command-line value: ``"1.3"`` (acceleration and jerk, :meth:`uniform`) or
        ``"velocity=1.1,acceleration=1.3,jerk=1.5"`` (missing factors are 1)."""
        text = text.strip()
        try:
            factor = float(text)
        except ValueError:
            pass
        else:
            return cls.uniform(factor)
        values: dict[str, float] = {}
        for part in text.split(","):
            key, sep, value = part.partition("=")
            key = key.strip()
            if not sep or key not in ("velocity", "acceleration", "jerk"):
                raise InvalidInputError(
                    f"limit scale {text!r}: expected a number or velocity=..,acceleration=..,jerk=.. (got part {part!r})"
                )
            if key in values:
                raise InvalidInputError(f"limit scale {text!r}: {key} given twice")
            try:
                values[key] = float(value)
            except ValueError:
                raise InvalidInputError(
                    f"limit scale {text!r}: {key} must be a number, got {value.strip()!r}"
                ) from None
        return cls(**values)

    def apply(self, limits: JointLimits) -> JointLimits:
        """``limits`` with their derivative limits scaled (position limits unchanged)."""
        out = limits
        for name in ("velocity", "acceleration", "jerk"):
            factor = getattr(self, name)
            if factor != 1.0:
                out = out.expanded(factor, orders=(name,))
        return out


@dataclass(frozen=True, slots=True)
class HandServe:
    """A hand-designed serve: what a user saves from the studio as a seed (JSON file)."""

    name: str
    """Short human-readable name."""
    side: TossSide
    """Which toss it starts from: ``"right"`` or ``"left"``."""
    params: ServeParams
    """The strike parameters in physical units."""
    notes: str = ""
    """Free text (intent, who designed it, ...)."""
    task: str | None = None
    """Optional reward task preset the serve was designed for."""
    extra: dict[str, Any] = field(default_factory=dict)
    """The optional ``spin`` label and the user's own JSON fields (names starting with
    ``x_``), kept verbatim on round trips."""
    limit_scale: LimitScale = field(default_factory=LimitScale)
    """Derivative-limit expansion the serve is planned with (JSON field ``limit_scale``,
    written only when it is not the identity)."""

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict of the documented serve format."""
        p = self.params
        out: dict[str, Any] = {
            "schema": SERVE_SCHEMA,
            "name": self.name,
            "side": self.side,
            "params": {
                "tau": p.tau,
                "velocity": list(p.velocity),
                "yaw": p.yaw,
                "roll": p.roll,
                "t_return": p.t_return,
                "offset": list(p.offset),
            },
            "notes": self.notes,
        }
        if self.task is not None:
            out["task"] = self.task
        if not self.limit_scale.is_identity:
            out["limit_scale"] = self.limit_scale.to_json()
        out.update(self.extra)
        return out

    def with_params(self, params: ServeParams) -> HandServe:
        """A copy with other strike parameters."""
        return replace(self, params=params)


MAX_SERVE_BYTES = 1_000_000
"""Size limit of a serve file [bytes] (a serve is ~1 kB; notes of a few pages fit)."""
_PARAM_KEYS = {"tau", "velocity", "yaw", "roll", "t_return", "offset"}
_TOP_KEYS = {"schema", "name", "side", "params", "notes", "task", "limit_scale"}
_LABEL_KEYS = {"spin"}
"""Optional free labels kept verbatim (``spin``: the intended spin, e.g. "backspin")."""
MAX_NAME_LENGTH = 200
"""Longest serve name accepted [characters]."""
EXTENSION_PREFIX = "x_"
"""Top-level fields of a serve file starting with this are the user's own: kept verbatim
on round trips. Any other unknown field is refused (a typo such as ``limit_scales``
would otherwise plan silently at the robot's own limits)."""


def serve_from_json(data: Any, *, source: str = "<serve>") -> HandServe:
    """Validate a decoded serve JSON document; errors name ``source`` and the field."""

    def fail(msg: str) -> DataFileError:
        return DataFileError(source, msg)

    if not isinstance(data, dict):
        raise fail("a serve file must hold a JSON object")
    schema = data.get("schema", SERVE_SCHEMA)
    if schema != SERVE_SCHEMA:
        raise fail(f"field 'schema': expected {SERVE_SCHEMA!r}, got {schema!r}")
    name = data.get("name")
    if not isinstance(name, str) or not name.strip() or len(name) > MAX_NAME_LENGTH:
        raise fail(f"field 'name': must be a non-empty string of at most {MAX_NAME_LENGTH} characters")
    if lone_surrogate(name) is not None:
        raise fail("field 'name': not valid Unicode (a lone surrogate cannot be shown or saved)")
    side = data.get("side")
    if side not in ("right", "left"):
        raise fail(f"field 'side': must be 'right' or 'left', got {side!r}")
    raw = data.get("params")
    if not isinstance(raw, dict):
        raise fail("field 'params': must be an object")
    unknown = set(raw) - _PARAM_KEYS
    if unknown:
        raise fail(f"field 'params': unknown keys {sorted(unknown)} (known: {sorted(_PARAM_KEYS)})")
    for key in ("tau", "velocity", "yaw", "roll"):
        if key not in raw:
            raise fail(f"field 'params.{key}': missing")

    def number(key: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise fail(f"field 'params.{key}': must be a finite number, got {value!r}")
        return float(value)

    def vec3(key: str, value: Any) -> tuple[float, float, float]:
        if not isinstance(value, list) or len(value) != 3:
            raise fail(f"field 'params.{key}': must be a list of 3 numbers, got {value!r}")
        a, b, c = (number(f"{key}[{i}]", v) for i, v in enumerate(value))
        return (a, b, c)

    try:
        params = ServeParams(
            tau=number("tau", raw["tau"]),
            velocity=vec3("velocity", raw["velocity"]),
            yaw=number("yaw", raw["yaw"]),
            roll=number("roll", raw["roll"]),
            t_return=number("t_return", raw.get("t_return", 0.7)),
            offset=vec3("offset", raw.get("offset", [0.0, 0.0, 0.0])),
        )
    except InvalidInputError as err:
        if isinstance(err, DataFileError):
            raise
        raise fail(str(err)) from None
    notes = data.get("notes", "")
    if not isinstance(notes, str):
        raise fail("field 'notes': must be a string")
    task = data.get("task")
    if task is not None and not isinstance(task, str):
        raise fail("field 'task': must be a string or absent")
    limit_scale = LimitScale.from_json(data["limit_scale"], source=source) if "limit_scale" in data else LimitScale()
    unknown_fields = sorted(k for k in data if k not in _TOP_KEYS | _LABEL_KEYS and not k.startswith(EXTENSION_PREFIX))
    if unknown_fields:
        raise fail(
            f"unknown fields {unknown_fields} (known: {sorted(_TOP_KEYS | _LABEL_KEYS)}; your own fields must start with {EXTENSION_PREFIX!r})"
        )
    for key in _LABEL_KEYS & set(data):
        if not isinstance(data[key], str) or len(data[key]) > MAX_NAME_LENGTH:
            raise fail(f"field '{key}': must be a string of at most {MAX_NAME_LENGTH} characters")
    extra = {k: v for k, v in data.items() if k.startswith(EXTENSION_PREFIX) or k in _LABEL_KEYS}
    return HandServe(
        name=name.strip(), side=side, params=params, notes=notes, task=task, extra=extra, limit_scale=limit_scale
    )


def load_serve(path: str | Path) -> HandServe:
    """Read and validate a hand-designed serve JSON file (strict JSON of at most
    :data:`MAX_SERVE_BYTES`, :mod:`studio.storage.jsonfile`)."""
    return serve_from_json(read_json_file(path, max_bytes=MAX_SERVE_BYTES), source=str(path))


def save_serve(path: str | Path, serve: HandServe) -> Path:
    """Write a serve JSON file atomically (temporary file, then rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(serve.to_json(), indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path
