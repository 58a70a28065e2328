"""Serve library: a folder a robot controller can read without this program's objects.

Format (``DESIGN.md``, schema ``serve-studio/library@1``):

- ``index.json``: ``{"schema": ..., "serves": [entry, ...]}``; each entry holds a stable
  ``id``, ``name``, ``side``, ``task``, the serve parameters ``params`` (physical units,
  as in serve JSON files), the predicted ball state at the net crossing and at the
  second bounce, ``legal``, ``reward`` and its ``terms``, ``provenance`` (hand-designed
  or optimizer run and seed), ``robot`` (model name and SHA-256 of the robot source and
  URDF, the serve's ``limit_scale`` and the effective derivative ``limits`` it was
  planned with, and the peak joint ``efforts`` of its motion with the limits checked), ``created`` (UTC ISO time), ``usage`` counters and the
  ``arrays`` file name;
- ``<id>.npz`` per serve (plain arrays, no pickled objects): ``t`` (M,) [s] and ``u``
  (M, 8) joint commands of preparation + toss + strike + return + final hold at 1 kHz
  on one clock from 0, ``q`` (M, 8) predicted joint positions, ``t_toss`` (when the toss
  starts), ``ball_t`` (K,), ``ball_p`` (K, 3) predicted ball path on the same clock,
  ``joint_names``.

Command semantics (what a controller must do for ``q`` to be the prediction): send
``u[k]`` at ``t[k]`` and hold it until ``t[k+1]`` (zero-order hold at 1 kHz, as
:meth:`studio.robot.model.JointDynamics.simulate` discretizes the joint model
q'' = wn^2 (u - q) - 2 zeta wn q'); ``q[k]`` is the predicted joint position at ``t[k]``,
before ``u[k]`` acts. Each ``u[k]`` is the planned smooth command at the interval's
midpoint t_k + dt/2, so the held steps follow the smooth plan to O(dt^2); a controller
that interpolates linearly from ``u[k]`` at t_k to ``u[k+1]`` at t_k+1 runs the motion
~0.5 ms late. The arrays end with the last (rest) command held until the predicted joints
are within :data:`studio.planning.settle.SETTLE` (|q - u| <= 0.1 mm / 0.1 mrad, |q'| <= 1 mm/s /
1 mrad/s on the last two samples): a controller may stop streaming after ``t[-1]``. The
entry's ``cup_hold`` records the ball-in-cup check of preparation + toss (times on ``t``).

Writes are atomic (temporary file, then rename); loads validate the schema and fail with
a :class:`~studio.errors.DataFileError` naming the file and the field; arrays are read
with ``allow_pickle=False``. The index must be strict JSON: every number finite (no
``NaN``/``Infinity``; the one exception is ``cup_hold.worst_ratio`` = ``Infinity`` that
libraries of a short-lived earlier version wrote), every integer within +-(2**53 - 1),
every string valid Unicode (no lone surrogates), ``net`` and ``second_bounce`` null or a
ball state (``p``, ``v``, ``w`` 3 numbers each; ``topspin``, ``sidespin``, ``cork`` numbers).

Writers never rewrite or delete a file they could not read: every write (export, usage
sync, prune; :mod:`studio.library.match`) first reads and validates the index, and a corrupt index
stops it with the DataFileError, the file kept byte for byte. Writers of one library
exclude each other with :meth:`ServeLibrary.lock` (:mod:`studio.storage.filelock`, ``.lock`` in the
folder), held across the read-modify-write, so the studio, the CLI and training can write
to the same library at once without losing an entry. An export writes its NPZ first and
the index last (an index entry never points at a missing NPZ; an NPZ whose index write
failed is removed again).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import tempfile
import uuid
import zipfile
from collections.abc import Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from studio.errors import DataFileError, InvalidInputError
from studio.paths import robots_dir
from studio.robot.description import load_spec
from studio.serve.params import HandServe, LimitScale, serve_from_json
from studio.storage.confined import confined
from studio.storage.filelock import locked
from studio.storage.jsonfile import check_values, read_file_bytes, read_json_file

LIBRARY_SCHEMA = "serve-studio/library@1"
"""Schema tag of the index file."""
INDEX_NAME = "index.json"
"""File name of the index inside a library folder."""
_ID = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
_ENTRY_KEYS = {"id", "name", "side", "task", "params", "legal", "reward", "arrays", "created"}
_ARRAYS = ("t", "u", "q", "ball_t", "ball_p")
MAX_NPZ_BYTES = 256 * 2**20
"""Size limit of one serve's arrays file [bytes] (a 10 s motion is ~0.5 MB)."""
_LEGACY_INF = ("cup_hold.worst_ratio",)
"""Fields where ``Infinity`` is accepted (written by an earlier version; now ``null``)."""
_STATE_VECTORS = ("p", "v", "w")
_STATE_NUMBERS = ("topspin", "sidespin", "cork")
_STATE_OPTIONAL = ("speed", "height", "clearance")
USAGE_KEYS = ("used", "won", "lost", "aces")
"""Usage counters of an entry (``usage`` object): serves executed, points won and lost
after them, aces (direct serve points)."""


def robot_identity(limit_scale: LimitScale | None = None) -> dict[str, Any]:
    """Name and SHA-256 digests of the shipped robot source (TOML) and URDF, the
    dynamic limit expansion a serve was planned with (``limit_scale``) and the effective
    derivative limits it needs (``limits``: ``velocity`` [m/s | rad/s], ``acceleration``
    [m/s^2 | rad/s^2], ``jerk`` [m/s^3 | rad/s^3], 8 values each in joint order): a
    controller can refuse a plan that needs more than its robot is set up for."""
    folder = robots_dir()
    out: dict[str, Any] = {"name": "serve_robot"}
    for key, name in (("toml_sha256", "serve_robot.toml"), ("urdf_sha256", "serve_robot.urdf")):
        out[key] = hashlib.sha256((folder / name).read_bytes()).hexdigest()
    scale = limit_scale if limit_scale is not None else LimitScale()
    joints = load_spec().actuated_joints
    out["limit_scale"] = scale.to_json()
    out["limits"] = {
        order: [float(getattr(j, order)) * getattr(scale, order) for j in joints]
        for order in ("velocity", "acceleration", "jerk")
    }
    return out


_UMASK = os.umask(0o022)
os.umask(_UMASK)
FILE_MODE = 0o666 & ~_UMASK
"""Mode of the files a library writes: what ``open()`` would give under the user's umask
(usually 0644: a controller running as another user of the group can read them; the
temporary file's own 0600 is not kept)."""


def _atomic_write(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, FILE_MODE)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _strict_json(value: Any, where: str, path: Path) -> None:
    """Raise DataFileError naming ``where`` unless ``value`` is strict JSON (module doc;
    :func:`studio.storage.jsonfile.check_values`)."""
    check_values(value, path, root=where, infinity_at=_LEGACY_INF)


def _check_ball_state(state: Any, where: str, path: Path) -> None:
    """DataFileError unless ``state`` is null or a ball state (``p``, ``v``, ``w``: 3 numbers;
    ``topspin``, ``sidespin``, ``cork``: numbers; ``speed``, ``height``, ``clearance``:
    numbers or null when present). Finiteness is :func:`_strict_json`'s."""
    if state is None:
        return
    if not isinstance(state, dict):
        raise DataFileError(path, f"field '{where}': must be null or a ball state object, got {type(state).__name__}")

    def number(x: Any) -> bool:
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    for key in _STATE_VECTORS:
        vec = state.get(key)
        if not isinstance(vec, list) or len(vec) != 3 or not all(number(x) for x in vec):
            raise DataFileError(path, f"field '{where}.{key}': must be 3 numbers, got {vec!r}"[:300])
    for key in _STATE_NUMBERS:
        if not number(state.get(key)):
            raise DataFileError(path, f"field '{where}.{key}': must be a number, got {state.get(key)!r}"[:300])
    for key in _STATE_OPTIONAL:
        if state.get(key) is not None and not number(state[key]):
            raise DataFileError(path, f"field '{where}.{key}': must be a number or null, got {state[key]!r}"[:300])


def _index_bytes(doc: dict[str, Any]) -> bytes:
    """The index file's content for ``doc`` (validated before: only the legacy Infinity)."""
    return (json.dumps(doc, indent=2) + "\n").encode("utf-8")


@dataclass(frozen=True)
class LibraryEntry:
    """One serve of a library (the index entry; arrays are loaded on demand)."""

    data: dict[str, Any]
    """The validated JSON entry."""
    folder: Path
    """The library folder."""

    @property
    def id(self) -> str:
        return str(self.data["id"])

    @property
    def serve(self) -> HandServe:
        """The serve parameters as a hand-designed serve (for the studio or as a seed)."""
        d = self.data
        serve = serve_from_json(
            {"name": d["name"], "side": d["side"], "params": d["params"], "task": d.get("task")},
            source=f"{self.folder / INDEX_NAME}: serve {self.id}",
        )
        return replace(serve, limit_scale=self.limit_scale)

    @property
    def limit_scale(self) -> LimitScale:
        """The dynamic limit expansion the serve was planned with (``robot.limit_scale``;
        the identity for entries written before it was recorded)."""
        robot = self.data.get("robot")
        raw = robot.get("limit_scale") if isinstance(robot, dict) else None
        if raw is None:
            return LimitScale()
        return LimitScale.from_json(raw, source=f"{self.folder / INDEX_NAME}: serve {self.id}: robot")

    def arrays(self) -> dict[str, npt.NDArray[Any]]:
        """The serve's arrays, validated (never unpickled)."""
        path = confined(self.folder, str(self.data["arrays"]))
        raw = read_file_bytes(path, max_bytes=MAX_NPZ_BYTES)  # a pipe or a link out of the library is refused
        try:
            with np.load(io.BytesIO(raw), allow_pickle=False) as npz:
                out = {k: npz[k] for k in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise DataFileError(path, f"cannot read arrays: {err}") from None
        for key in _ARRAYS:
            if key not in out:
                raise DataFileError(path, f"missing array {key!r}")
        m = out["t"].shape[0]
        if out["u"].shape != (m, 8) or out["q"].shape != (m, 8):
            raise DataFileError(path, f"arrays 'u' and 'q' must be ({m}, 8), got {out['u'].shape} and {out['q'].shape}")
        if out["ball_p"].shape != (out["ball_t"].shape[0], 3):
            raise DataFileError(
                path, f"array 'ball_p' must be ({out['ball_t'].shape[0]}, 3), got {out['ball_p'].shape}"
            )
        for key in _ARRAYS:
            if not np.all(np.isfinite(out[key])):
                raise DataFileError(path, f"array {key!r} holds non-finite values")
        if "t_toss" in out:  # absent in libraries written before the preparation phase was exported
            tt = out["t_toss"]
            if tt.shape != () or not np.isfinite(tt) or not (m == 0 or out["t"][0] <= float(tt) <= out["t"][-1]):
                raise DataFileError(path, f"array 't_toss' must be one time within t, got {tt!r}")
        else:
            out["t_toss"] = np.array(0.0)
        return out


def _export_preparation(preparation: Any, motion: Any) -> Any:
    """The preparation to export (the one given, else the motion's), its arrays checked to be (P, 8)."""
    preparation = preparation if preparation is not None else getattr(motion, "preparation", None)
    if preparation is not None:
        pu, pq = np.asarray(preparation.u, dtype=float), np.asarray(preparation.q, dtype=float)
        if pu.ndim != 2 or pu.shape[1:] != (8,) or pq.shape != pu.shape:
            raise InvalidInputError(f"preparation arrays must be (P, 8), got {pu.shape} and {pq.shape}")
    return preparation


def _new_serve_id(name: str) -> str:
    """A fresh entry id: the serve's name as a slug and 8 random hex digits."""
    slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")[:40] or "serve"
    return f"{slug}-{uuid.uuid4().hex[:8]}"


def _arrays_npz(ev: Any, arr: Any) -> bytes:
    """The entry's compressed NPZ: the exported arrays and the ball path on their clock."""
    t_toss = arr.t_toss
    ball_t = np.asarray(ev.ball.t) - float(np.asarray(ev.t)[0]) + t_toss if ev.ball is not None else np.zeros(0)
    ball_p = np.asarray(ev.ball.p) if ev.ball is not None else np.zeros((0, 3))
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        t=arr.t,
        u=arr.u,
        q=arr.q,
        ball_t=ball_t,
        ball_p=ball_p,
        t_toss=np.array(t_toss),
        joint_names=np.array(load_spec().joint_names),
    )
    return buf.getvalue()


def _evaluation_fields(ev: Any, task: str | None) -> dict[str, Any]:
    """The index fields describing the evaluated serve: name, side, task, params, ball, verdict and reward."""
    m = ev.metrics
    return {
        "name": ev.serve.name,
        "side": ev.serve.side,
        "task": task or ev.serve.task,
        "params": ev.serve.to_json()["params"],
        "net": m.net if m else None,
        "second_bounce": m.second_bounce if m else None,
        "legal": bool(ev.legal),
        "reward": float(ev.reward.total),
        "terms": ev.reward.as_dict(),
    }


class ServeLibrary:
    """A serve library folder: read, validate and add serves.

    Args:
        folder: the library folder; created on the first write.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    @property
    def index_path(self) -> Path:
        return self.folder / INDEX_NAME

    def lock(self, timeout: float | None = None) -> AbstractContextManager[None]:
        """Context manager: hold the library's write lock (:func:`studio.storage.filelock.locked` on
        the folder) across a read-modify-write of ``index.json`` / ``matches.jsonl``.
        Re-entrant in one thread; :class:`~studio.storage.filelock.LockTimeoutError` after
        ``timeout`` seconds (default :func:`studio.storage.filelock.default_timeout`)."""
        return locked(self.folder, timeout=timeout)

    def entries(self) -> list[LibraryEntry]:
        """All entries, validated (strict JSON, see the module doc). An absent library is empty."""
        if not self.index_path.exists():
            return []
        doc = read_json_file(self.index_path, infinity_at=_LEGACY_INF)
        if isinstance(doc, dict):
            _strict_json({k: v for k, v in doc.items() if k != "serves"}, "index", self.index_path)
        if not isinstance(doc, dict) or doc.get("schema") != LIBRARY_SCHEMA:
            raise DataFileError(
                self.index_path,
                f"field 'schema': expected {LIBRARY_SCHEMA!r}, got {doc.get('schema') if isinstance(doc, dict) else type(doc).__name__!r}",
            )
        serves = doc.get("serves")
        if not isinstance(serves, list):
            raise DataFileError(self.index_path, "field 'serves': must be a list")
        return self._validated(serves)

    def _validated(self, serves: list[Any]) -> list[LibraryEntry]:
        """Validate index entries (as read from or about to be written to the index)."""
        out: list[LibraryEntry] = []
        seen: set[str] = set()
        for i, entry in enumerate(serves):
            where = f"serves[{i}]"
            if not isinstance(entry, dict):
                raise DataFileError(self.index_path, f"field '{where}': must be an object")
            _strict_json(entry, where, self.index_path)
            missing = sorted(_ENTRY_KEYS - set(entry))
            if missing:
                raise DataFileError(self.index_path, f"field '{where}': missing {missing}")
            sid = entry["id"]
            if not isinstance(sid, str) or not _ID.match(sid):
                raise DataFileError(self.index_path, f"field '{where}.id': must match {_ID.pattern}, got {sid!r}")
            if sid in seen:
                raise DataFileError(self.index_path, f"field '{where}.id': duplicate id {sid!r}")
            seen.add(sid)
            if entry["arrays"] != f"{sid}.npz":
                raise DataFileError(
                    self.index_path, f"field '{where}.arrays': must be '{sid}.npz', got {entry['arrays']!r}"
                )
            if not isinstance(entry["legal"], bool):
                raise DataFileError(self.index_path, f"field '{where}.legal': must be true or false")
            reward = entry["reward"]
            if isinstance(reward, bool) or not isinstance(reward, (int, float)) or not np.isfinite(reward):
                raise DataFileError(self.index_path, f"field '{where}.reward': must be a finite number")
            t_toss = entry.get("t_toss", 0.0)
            if (
                isinstance(t_toss, bool)
                or not isinstance(t_toss, (int, float))
                or not np.isfinite(t_toss)
                or t_toss < 0
            ):
                raise DataFileError(
                    self.index_path, f"field '{where}.t_toss': must be a finite time >= 0 [s], got {t_toss!r}"
                )
            usage = entry.get("usage")
            if usage is not None:
                if not isinstance(usage, dict):
                    raise DataFileError(self.index_path, f"field '{where}.usage': must be an object")
                for key in USAGE_KEYS:
                    n = usage.get(key, 0)
                    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
                        raise DataFileError(
                            self.index_path, f"field '{where}.usage.{key}': must be a non-negative integer, got {n!r}"
                        )
            for key in ("net", "second_bounce"):
                _check_ball_state(entry.get(key), f"{where}.{key}", self.index_path)
            robot = entry.get("robot")
            if robot is not None and not isinstance(robot, dict):
                raise DataFileError(self.index_path, f"field '{where}.robot': must be an object")
            if isinstance(robot, dict) and "limit_scale" in robot:
                LimitScale.from_json(robot["limit_scale"], source=f"{self.index_path}: {where}.robot")
            e = LibraryEntry(entry, self.folder)
            _ = e.serve  # validates name, side and params, naming the entry
            out.append(e)
        return out

    def replace_entries(self, serves: list[dict[str, Any]]) -> list[LibraryEntry]:
        """Rewrite the index with ``serves`` (entry dicts), validated first, written atomically.

        Used to update usage counters and to remove (prune) serves; the arrays files are
        not touched. Holds the library lock; the index there now must be readable (a
        corrupt one is never overwritten: DataFileError, file kept). The caller holds the
        lock too when ``serves`` derive from a read of the index (read-modify-write).
        Raises DataFileError naming the field if an entry is malformed.
        """
        doc = {"schema": LIBRARY_SCHEMA, "serves": serves}
        data = json.loads(json.dumps(doc))  # plain JSON values only, validated as they will be read
        out = self._validated(data["serves"])
        with self.lock():
            self.entries()  # refuse to overwrite an index that cannot be read
            self.folder.mkdir(parents=True, exist_ok=True)
            _atomic_write(self.index_path, _index_bytes(data))
        return out

    def get(self, serve_id: str) -> LibraryEntry:
        """The entry with ``serve_id`` (InvalidInputError if absent)."""
        for e in self.entries():
            if e.id == serve_id:
                return e
        raise InvalidInputError(f"serve {serve_id!r} not found in library {self.folder}")

    def add(
        self,
        evaluation: Any,
        *,
        provenance: dict[str, Any] | None = None,
        task: str | None = None,
        preparation: Any = None,
        effort_limits: Mapping[str, float] | None = None,
    ) -> LibraryEntry:
        """Export an evaluated serve (:class:`studio.serve.evaluate.Evaluation`) with its plan.

        ``preparation``: the :class:`studio.planning.preparation.PreparationPhase` before the toss
        (default: the one the evaluation was planned with, ``evaluation.motion.preparation``,
        i.e. ``EvaluationContext.preparation(side)``); the arrays then hold preparation +
        toss + strike + return to rest + final hold on one clock from 0 (DESIGN.md,
        :func:`studio.planning.serve_plan.serve_arrays`), the toss starting at ``t_toss`` (stored in the
        NPZ and the index). Without any, the arrays start with the toss (``t_toss`` = 0).

        The peak joint efforts of the arrays written (:mod:`studio.serve.efforts`) go into the
        entry's ``robot.efforts``; a plan beyond a joint's effort limit is refused
        (:class:`studio.serve.efforts.EffortLimitError`, nothing written) unless ``effort_limits``
        (joint name -> limit [N | N m], set on purpose by the user) covers it, which the
        entry records (``robot.efforts.raised``).

        Raises InvalidInputError when the evaluation has no motion plan to export,
        DataFileError (nothing written) when the library's index cannot be read,
        :class:`~studio.storage.filelock.LockTimeoutError` when another writer holds the library.
        """
        ev = evaluation
        if ev.t is None or ev.u is None or ev.q is None:
            raise InvalidInputError(f"serve {ev.serve.name!r} has no motion plan to export ({ev.status}: {ev.reason})")
        self.entries()  # a corrupt library stops the export before any work (checked again under the lock)
        from studio.planning.serve_plan import serve_arrays  # casadi & pinocchio: not at import (dashboard)
        from studio.planning.settle import SETTLE
        from studio.robot.model import load_robot
        from studio.serve.efforts import arrays_effort_report

        motion = getattr(ev, "motion", None)
        preparation = _export_preparation(preparation, motion)
        robot = load_robot()  # its own pinocchio data: exports may run beside an evaluation thread
        arr = serve_arrays(ev.t, ev.u, ev.q, getattr(motion, "qd", None), robot.dynamics, preparation=preparation)
        efforts = arrays_effort_report(robot, arr).with_limits(effort_limits or {})
        efforts.require_within()
        sid = _new_serve_id(ev.serve.name)
        npz = _arrays_npz(ev, arr)
        entry = {
            "id": sid,
            **_evaluation_fields(ev, task),
            "provenance": provenance or {"kind": "hand-designed"},
            "robot": {**robot_identity(ev.serve.limit_scale), "efforts": efforts.to_json()},
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "usage": {"used": 0, "won": 0, "lost": 0, "aces": 0},
            "arrays": f"{sid}.npz",
            "t_toss": arr.t_toss,
            "settle": {"samples": arr.settle_samples, "position": SETTLE.position, "velocity": SETTLE.velocity},
        }
        cup = getattr(ev, "cup_hold", None)
        if cup is not None and preparation is not None and preparation is getattr(motion, "preparation", None):
            entry["cup_hold"] = cup.to_json()  # checked on this preparation, on the arrays' clock
        entry = json.loads(json.dumps(entry))  # plain JSON values, validated as they will be read
        self._validated([entry])
        return self._commit(entry, npz)

    def _commit(self, entry: dict[str, Any], npz: bytes) -> LibraryEntry:
        """Under the library lock: re-read and validate the index, write the entry's NPZ,
        then the index with the entry appended (both atomic). A corrupt index stops it
        before anything is written; if the index write fails the NPZ is removed again."""
        npz_path = self.folder / str(entry["arrays"])
        with self.lock():
            entries = self.entries()  # what is there now (another writer may have added)
            _atomic_write(npz_path, npz)
            doc = {"schema": LIBRARY_SCHEMA, "serves": [e.data for e in entries] + [entry]}
            try:
                _atomic_write(self.index_path, _index_bytes(doc))
            except BaseException:
                npz_path.unlink(missing_ok=True)  # no orphan arrays
                raise
        return LibraryEntry(entry, self.folder)


def orphan_files(library: ServeLibrary, entries: list[LibraryEntry]) -> list[str]:
    """Names of the NPZ and temporary files in ``library``'s folder that no entry refers to
    (left by an export killed between its two writes, or by hand), sorted."""
    used = {str(e.data["arrays"]) for e in entries}
    found = [p.name for p in library.folder.glob("*.npz") if p.name not in used]
    found += [p.name for p in library.folder.glob(".*.tmp")]
    return sorted(found)


# -- "open in the studio" requests --------------------------------------------------------

OPEN_REQUEST_NAME = "open-request.json"
"""File in a library folder through which the dashboard asks a running studio (same
library) to load a serve into its controls."""
OPEN_REQUEST_SCHEMA = "serve-studio/open-request@1"
"""Schema tag of :data:`OPEN_REQUEST_NAME`."""


@dataclass(frozen=True, slots=True)
class OpenRequest:
    """A request to open serve ``id`` of the library in the studio."""

    id: str
    """Library serve id."""
    nonce: str
    """Changes with every request (a studio acts on each nonce once)."""


def request_open(folder: str | Path, serve_id: str) -> OpenRequest:
    """Ask a studio running on library ``folder`` to load serve ``serve_id`` (atomic write).

    Raises:
        InvalidInputError: malformed id, or no such serve in the library.
        DataFileError: the library index is corrupt.
    """
    if not isinstance(serve_id, str) or not _ID.match(serve_id):
        raise InvalidInputError(f"open request: bad serve id {serve_id!r}")
    library = ServeLibrary(folder)
    library.get(serve_id)  # must exist
    req = OpenRequest(serve_id, uuid.uuid4().hex)
    doc = {
        "schema": OPEN_REQUEST_SCHEMA,
        "id": req.id,
        "nonce": req.nonce,
        "requested": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    _atomic_write(library.folder / OPEN_REQUEST_NAME, (json.dumps(doc) + "\n").encode("utf-8"))
    return req


def read_open_request(folder: str | Path) -> OpenRequest | None:
    """The current open request of library ``folder`` (None if there is none).

    Raises:
        DataFileError: the request file is malformed (file and field named).
    """
    path = Path(folder) / OPEN_REQUEST_NAME
    if not path.exists():
        return None
    doc = read_json_file(path, max_bytes=4096)
    if not isinstance(doc, dict) or doc.get("schema") != OPEN_REQUEST_SCHEMA:
        raise DataFileError(str(path), f"schema must be {OPEN_REQUEST_SCHEMA!r}")
    sid, nonce = doc.get("id"), doc.get("nonce")
    if not isinstance(sid, str) or not _ID.match(sid):
        raise DataFileError(str(path), f"id: bad serve id {sid!r}")
    if not isinstance(nonce, str) or not (0 < len(nonce) <= 64):
        raise DataFileError(str(path), "nonce: must be a non-empty string")
    return OpenRequest(sid, nonce)
