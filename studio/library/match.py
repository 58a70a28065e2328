"""Match log, the paper's Table I statistics, per-serve records and pruning.

Match log (``matches.jsonl`` in a library folder, one JSON object per point, schema
``serve-studio/point@1`` implied by the fields):

- ``time``: ISO 8601 time with a UTC offset, e.g. ``"2026-04-12T10:31:02+00:00"``;
- ``server``: ``"robot"`` or ``"opponent"``;
- ``serve``: the library id of the robot's serve, ``null`` when the opponent serves;
- ``winner``: ``"robot"`` or ``"opponent"``;
- ``ace``: true when the serve won the point directly (the receiver failed to return it
  legally); then ``winner`` must be the server;
- ``opponent`` (optional): the opponent's name.

Points are appended with append + flush + fsync (one ``write`` of a whole line,
:func:`studio.storage.jsonlog.append_jsonl`); a line cut short by a crash is reported by
:func:`load_points` with its line number, and nothing is appended to such a log (the user
completes or removes the line; a valid last line without its newline gets one first).

Every writer (:func:`record_point`, :func:`sync_usage`, :func:`prune`) holds the library's
lock (:meth:`studio.library.store.ServeLibrary.lock`) across its read-modify-write of the log and
the index, and reads and validates both before writing anything: a corrupt file stops it
(DataFileError naming file and line/field) and is kept byte for byte.

Statistics (the paper's Table I): the robot's win probability while serving and while
receiving with Binomial 95 % Wilson score intervals, aces (count and % of robot serves).

Pruning rule (:func:`prune_candidates`): a serve is statistically worst when it was used
at least ``min_uses`` times and the upper bound of the Wilson 95 % interval of its win
rate is below the serving win rate of the whole library (all robot serves in the log
whose serve is in the current library), i.e. it is worse than the library's average
with ~97.5 % one-sided confidence.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from studio.errors import DataFileError, InvalidInputError
from studio.library.store import LibraryEntry, ServeLibrary
from studio.storage.confined import confined
from studio.storage.jsonfile import lone_surrogate, parse_json, read_file_bytes
from studio.storage.jsonlog import append_jsonl

MATCH_LOG = "matches.jsonl"
"""File name of the match log inside a library folder."""
PRUNED_DIR = "pruned"
"""Sub-folder of a library that receives pruned serves (a library itself: index + NPZ)."""
Z95 = 1.959963984540054
"""Standard normal quantile for a two-sided 95 % interval (Φ⁻¹(0.975))."""
MIN_USES = 10
"""Default minimum number of uses before a serve can be pruned (engineering choice: with
fewer points a Wilson upper bound below ~50 % needs nearly all points lost)."""
SIDES = ("robot", "opponent")
_KEYS = {"time", "server", "serve", "winner", "ace"}
_OPTIONAL = {"opponent"}


def wilson_interval(successes: int, n: int, *, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion.

    Args:
        successes: number of successes k (0 ≤ k ≤ n).
        n: number of trials; for n = 0 the interval is the uninformative (0, 1).
        z: normal quantile (default: two-sided 95 %).

    Returns:
        (lower, upper), both in [0, 1].
    """
    if n < 0 or successes < 0 or successes > n:
        raise InvalidInputError(f"Wilson interval needs 0 <= successes <= n, got {successes}/{n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    lower = 0.0 if successes == 0 else max(0.0, centre - half)  # exact 0 and 1 at the edges (no round-off)
    upper = 1.0 if successes == n else min(1.0, centre + half)
    return lower, upper


@dataclass(frozen=True)
class Point:
    """One point of a match (a line of the match log)."""

    time: str
    """ISO 8601 time with a UTC offset."""
    server: str
    """``"robot"`` or ``"opponent"``."""
    serve: str | None
    """Library id of the robot's serve; None when the opponent serves."""
    winner: str
    """``"robot"`` or ``"opponent"``."""
    ace: bool
    """The serve won the point directly."""
    opponent: str | None = None
    """Opponent's name, if known."""

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "time": self.time,
            "server": self.server,
            "serve": self.serve,
            "winner": self.winner,
            "ace": self.ace,
        }
        if self.opponent is not None:
            out["opponent"] = self.opponent
        return out


def point_from_json(doc: Any, *, where: str) -> Point:
    """Validate one log record; InvalidInputError with ``where`` and the field otherwise."""
    if not isinstance(doc, dict):
        raise InvalidInputError(f"{where}: a point must be a JSON object")
    missing = sorted(_KEYS - set(doc))
    if missing:
        raise InvalidInputError(f"{where}: missing field(s) {missing}")
    unknown = sorted(set(doc) - _KEYS - _OPTIONAL)
    if unknown:
        raise InvalidInputError(f"{where}: unknown field(s) {unknown}")
    t = doc["time"]
    try:
        parsed = datetime.fromisoformat(t) if isinstance(t, str) else None
    except ValueError:
        parsed = None
    if parsed is None or parsed.tzinfo is None:
        raise InvalidInputError(f"{where}: field 'time' must be an ISO 8601 time with a UTC offset, got {t!r}")
    for key in ("server", "winner"):
        if doc[key] not in SIDES:
            raise InvalidInputError(f"{where}: field {key!r} must be 'robot' or 'opponent', got {doc[key]!r}")
    serve = doc["serve"]
    if doc["server"] == "robot" and (not isinstance(serve, str) or not serve):
        raise InvalidInputError(
            f"{where}: field 'serve' must be the robot serve's id when the robot serves, got {serve!r}"
        )
    if doc["server"] == "opponent" and serve is not None:
        raise InvalidInputError(f"{where}: field 'serve' must be null when the opponent serves, got {serve!r}")
    if not isinstance(doc["ace"], bool):
        raise InvalidInputError(f"{where}: field 'ace' must be true or false")
    if doc["ace"] and doc["winner"] != doc["server"]:
        raise InvalidInputError(
            f"{where}: field 'ace': an ace is won by the server ({doc['server']}), but the winner is {doc['winner']}"
        )
    opponent = doc.get("opponent")
    if opponent is not None and not isinstance(opponent, str):
        raise InvalidInputError(f"{where}: field 'opponent' must be a string or absent")
    for key in ("serve", "opponent"):
        if isinstance(doc.get(key), str) and lone_surrogate(doc[key]) is not None:
            raise InvalidInputError(f"{where}: field {key!r} is not valid Unicode (lone surrogate)")
    return Point(time=t, server=doc["server"], serve=serve, winner=doc["winner"], ace=doc["ace"], opponent=opponent)


def load_points(path: str | Path) -> list[Point]:
    """All points of a match log, validated (an absent log is empty).

    Raises DataFileError naming the file, the line and the field.
    """
    path = Path(path)
    if not path.exists():
        return []
    lines = read_file_bytes(path).split(b"\n")  # the writer's line end only
    out: list[Point] = []
    for i, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        doc = parse_json(line, path, line=i)
        try:
            out.append(point_from_json(doc, where=f"line {i}"))
        except InvalidInputError as err:
            raise DataFileError(path, str(err)) from None
    return out


def append_point(path: str | Path, point: Point) -> None:
    """Append one point to the log: validated, one write of a whole line, flushed and fsynced.

    A valid last point without its newline gets one first; a torn last line stops it
    (DataFileError naming file and line, nothing appended). Callers writing a library's
    log hold its lock (:func:`record_point` does).
    """
    path = Path(path)
    if path.is_symlink():
        raise DataFileError(path, "is a symbolic link: a match log is appended only in place")
    point_from_json(point.to_json(), where=f"{path}: new point")
    path.parent.mkdir(parents=True, exist_ok=True)
    append_jsonl(path, point.to_json(), parse=lambda d: point_from_json(d, where=f"{path}: last line"))


def record_point(
    library: ServeLibrary,
    *,
    server: str,
    winner: str,
    serve: str | None = None,
    ace: bool = False,
    opponent: str | None = None,
    time: str | None = None,
) -> list[Point]:
    """Append one point to the library's match log and re-sync its usage counters.

    Args:
        library: the library whose ``matches.jsonl`` receives the point.
        server, winner: ``"robot"`` or ``"opponent"``.
        serve: the library id of the robot's serve (required when the robot serves, absent
            otherwise).
        ace: the serve won the point directly (then ``winner == server``).
        opponent: the opponent's name, if known (empty: unknown).
        time: ISO 8601 time with offset (default: now, UTC).

    Returns:
        Every point of the log, the new one last.

    Raises:
        InvalidInputError: the serve is missing, unknown or given for an opponent serve, or
            the point is malformed (field named); DataFileError: the log or the index is
            corrupt (nothing is written then); LockTimeoutError: another writer holds the
            library too long.
    """
    if server == "opponent" and serve is not None:
        raise InvalidInputError("a serve id is only for robot serves (server 'robot')")
    if server == "robot" and serve is None:
        raise InvalidInputError("the robot's serve (library id) is required when the robot serves")
    point = Point(
        time=time or datetime.now(UTC).isoformat(timespec="seconds"),
        server=server,
        serve=serve,
        winner=winner,
        ace=ace,
        opponent=opponent or None,
    )
    point_from_json(point.to_json(), where="new point")
    with library.lock():  # log + counters: one read-modify-write among all writers
        entries = library.entries()  # refuse to write to a library with a corrupt index
        if server == "robot" and serve not in {e.id for e in entries}:
            raise InvalidInputError(f"serve {serve!r} not found in library {library.folder}")
        log = library.folder / MATCH_LOG
        points = load_points(log)  # refuse to append to a corrupt log
        append_point(log, point)
        sync_usage(library, points + [point])
    return points + [point]


def last_robot_serve(points: Sequence[Point]) -> str | None:
    """Library id of the robot's most recent serve in ``points`` (None if it never served)."""
    return next((p.serve for p in reversed(points) if p.server == "robot"), None)


def next_serve(library: ServeLibrary, previous_id: str | None = None, *, strict: bool = False) -> LibraryEntry:
    """The robot's next serve by the paper's strategy (:func:`studio.library.selection.select_next`):
    the least-used legal serve of a cluster other than the previous serve's. Previous:
    ``previous_id``, else the robot's last serve in the match log; one no longer in the
    library (pruned meanwhile) counts as none, unless ``strict`` (then InvalidInputError
    names it). Usage from the entries' counters (kept in step with the log by
    :func:`record_point`).
    """
    from studio.library.selection import select_next

    entries = library.entries()
    ids = {e.id for e in entries}
    if previous_id is None:
        previous_id = last_robot_serve(load_points(library.folder / MATCH_LOG))
    elif strict and previous_id not in ids:
        raise InvalidInputError(f"previous serve {previous_id!r} is not in the library {library.folder}")
    return select_next(entries, previous_id if previous_id in ids else None)


@dataclass(frozen=True)
class Rate:
    """A win rate with its Wilson 95 % interval."""

    won: int
    """Points won."""
    n: int
    """Points played."""

    @property
    def rate(self) -> float:
        """won / n (NaN when n = 0)."""
        return self.won / self.n if self.n else math.nan

    @property
    def interval(self) -> tuple[float, float]:
        """Wilson 95 % score interval."""
        return wilson_interval(self.won, self.n)


@dataclass(frozen=True)
class MatchStats:
    """The paper's Table I row over a set of points (cumulative)."""

    serving: Rate
    """Robot's points won while the robot serves."""
    receiving: Rate
    """Robot's points won while the opponent serves."""
    aces: int
    """Robot aces (direct serve points)."""
    opponents: tuple[str, ...]
    """Opponents named in the log, in order of appearance."""

    @property
    def robot_serves(self) -> int:
        return self.serving.n

    @property
    def ace_fraction(self) -> float:
        """Aces per robot serve (NaN without robot serves)."""
        return self.aces / self.serving.n if self.serving.n else math.nan


def match_stats(points: Iterable[Point]) -> MatchStats:
    """Win probability while serving and receiving, and aces, over ``points``."""
    sw = sn = rw = rn = aces = 0
    opponents: list[str] = []
    for p in points:
        if p.opponent is not None and p.opponent not in opponents:
            opponents.append(p.opponent)
        won = p.winner == "robot"
        if p.server == "robot":
            sn += 1
            sw += won
            aces += p.ace
        else:
            rn += 1
            rw += won
    return MatchStats(serving=Rate(sw, sn), receiving=Rate(rw, rn), aces=aces, opponents=tuple(opponents))


@dataclass(frozen=True)
class ServeRecord:
    """Outcomes of the points one serve started."""

    id: str
    """Library id of the serve."""
    used: int
    """Times served."""
    won: int
    """Points the robot won after it."""
    lost: int
    """Points the robot lost after it."""
    aces: int
    """Aces with it."""

    @property
    def win(self) -> Rate:
        return Rate(self.won, self.used)

    def usage(self) -> dict[str, int]:
        """The library's ``usage`` counters."""
        return {"used": self.used, "won": self.won, "lost": self.lost, "aces": self.aces}


def serve_records(points: Iterable[Point], ids: Sequence[str] | None = None) -> dict[str, ServeRecord]:
    """Per-serve records of the robot's serves; ``ids`` adds zero records for unused serves
    and restricts the result to them (serves no longer in the library are left out)."""
    counts: dict[str, list[int]] = {sid: [0, 0, 0, 0] for sid in ids or ()}
    for p in points:
        if p.server != "robot" or p.serve is None:
            continue
        if ids is not None and p.serve not in counts:
            continue
        c = counts.setdefault(p.serve, [0, 0, 0, 0])
        c[0] += 1
        c[1] += p.winner == "robot"
        c[2] += p.winner == "opponent"
        c[3] += p.ace
    return {sid: ServeRecord(sid, *c) for sid, c in counts.items()}


@dataclass(frozen=True)
class PruneCandidate:
    """A serve the pruning rule marks as statistically worst."""

    record: ServeRecord
    """Its record."""
    upper: float
    """Upper bound of its win rate's Wilson 95 % interval."""
    baseline: float
    """Serving win rate of the whole library it falls below."""


def prune_candidates(records: dict[str, ServeRecord], *, min_uses: int = MIN_USES) -> tuple[list[PruneCandidate], Rate]:
    """Serves used ≥ ``min_uses`` times whose Wilson upper bound is below the library's
    serving win rate (over ``records``). Returns them (worst upper bound first) and the
    library's serving rate."""
    if min_uses < 1:
        raise InvalidInputError(f"min_uses must be at least 1, got {min_uses}")
    total = Rate(sum(r.won for r in records.values()), sum(r.used for r in records.values()))
    if total.n == 0:
        return [], total
    out = [
        PruneCandidate(r, r.win.interval[1], total.rate)
        for r in records.values()
        if r.used >= min_uses and r.win.interval[1] < total.rate
    ]
    return sorted(out, key=lambda c: (c.upper, c.record.id)), total


def sync_usage(library: ServeLibrary, points: Sequence[Point]) -> list[LibraryEntry]:
    """Rewrite the library's usage counters from the log (the log is the source of truth;
    serves absent from the log get zero counters). Atomic index write under the library
    lock; the caller holds it too when ``points`` come from its own read of the log."""
    with library.lock():
        entries = library.entries()
        records = serve_records(points, [e.id for e in entries])
        serves = []
        for e in entries:
            d = dict(e.data)
            d["usage"] = records[e.id].usage()
            serves.append(d)
        return library.replace_entries(serves)


def prune(library: ServeLibrary, ids: Sequence[str]) -> list[str]:
    """Move serves ``ids`` out of the library's index into ``<library>/pruned/`` (index + NPZ).

    Order, so that a crash never leaves the main index pointing at a missing NPZ: copy the
    NPZ files into ``pruned/``, write ``pruned/index.json``, rewrite the main index, then
    delete the original NPZ files. Returns the pruned ids.

    Holds the library's lock throughout (and the pruned library's while writing it); both
    indexes are read and validated before anything is copied or written.
    """
    with library.lock():
        return _prune_locked(library, list(dict.fromkeys(ids)))


def _prune_locked(library: ServeLibrary, ids: list[str]) -> list[str]:
    """:func:`prune` with the library lock held."""
    entries = library.entries()
    by_id = {e.id: e for e in entries}
    unknown = [i for i in ids if i not in by_id]
    if unknown:
        raise InvalidInputError(f"cannot prune {unknown}: not in library {library.folder}")
    if not ids:
        return []
    pruned_lib = ServeLibrary(confined(library.folder, PRUNED_DIR))  # a pruned/ linked elsewhere is refused
    with pruned_lib.lock():
        kept_pruned = [e.data for e in pruned_lib.entries() if e.id not in ids]
        for sid in ids:
            src = library.folder / str(by_id[sid].data["arrays"])
            if src.exists():
                shutil.copy2(src, pruned_lib.folder / src.name)
        pruned_lib.replace_entries(kept_pruned + [by_id[sid].data for sid in ids])
    library.replace_entries([e.data for e in entries if e.id not in ids])
    for sid in ids:
        (library.folder / str(by_id[sid].data["arrays"])).unlink(missing_ok=True)
    return list(ids)


def _pct(x: float) -> str:
    return "-" if math.isnan(x) else f"{100 * x:.1f}"


def _interval(rate: Rate) -> str:
    if rate.n == 0:
        return "-"
    lo, hi = rate.interval
    return f"{100 * lo:.1f}–{100 * hi:.1f}"


def stats_report(
    entries: Sequence[LibraryEntry], points: Sequence[Point], *, min_uses: int = MIN_USES, compact: bool = False
) -> str:
    """Table-I-like summary and the per-serve table (plain text, markdown tables).

    ``compact``: for a narrow panel (the studio's Match tab): the Table I figures as a list
    and the per-serve table without ids and intervals.
    """
    from studio.library.selection import serve_cluster

    s = match_stats(points)
    right = sum(e.data["side"] == "right" for e in entries)
    records = serve_records(points, [e.id for e in entries])
    candidates, total = prune_candidates(records, min_uses=min_uses)
    flagged = {c.record.id for c in candidates}
    if compact:
        lines = [
            f"- serving: robot won {_pct(s.serving.rate)} % of {s.robot_serves} (95 % WCI {_interval(s.serving)})",
            f"- receiving: robot won {_pct(s.receiving.rate)} % of {s.receiving.n} (95 % WCI {_interval(s.receiving)})",
            f"- aces: {s.aces} ({_pct(s.ace_fraction)} % of robot serves); opponents: {', '.join(s.opponents) or '-'}",
            "",
            "| serve | cluster | used | won | aces | prune |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for e in entries:
            r = records[e.id]
            lines.append(
                f"| {e.data['name']} | {serve_cluster(e)} | {r.used} | {r.won} | {r.aces} | {'yes' if e.id in flagged else ''} |"
            )
        return "\n".join(lines)
    lines = [
        "| serves in library (right, left) | robot serves | win % receiving (95 % WCI) | win % serving (95 % WCI) | aces (% of robot serves) | opponents |",
        "| --- | --- | --- | --- | --- | --- |",
        f"| {len(entries)} ({right}, {len(entries) - right}) | {s.robot_serves} | {_pct(s.receiving.rate)} ({_interval(s.receiving)}) "
        f"| {_pct(s.serving.rate)} ({_interval(s.serving)}) | {s.aces} ({_pct(s.ace_fraction)} %) | {', '.join(s.opponents) or '-'} |",
        "",
    ]
    lines += [
        "| id | name | cluster | used | won | lost | aces | win % | 95 % WCI | prune |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for e in entries:
        r = records[e.id]
        lines.append(
            f"| {e.id} | {e.data['name']} | {serve_cluster(e)} | {r.used} | {r.won} | {r.lost} | {r.aces} "
            f"| {_pct(r.win.rate)} | {_interval(r.win)} | {'yes' if e.id in flagged else ''} |"
        )
    unknown = sorted({p.serve for p in points if p.serve is not None} - set(records))
    lines.append("")
    lines.append(
        f"library serving win rate (pruning baseline): {_pct(total.rate)} % over {total.n} serves; prune rule: used >= {min_uses} and Wilson upper bound < baseline"
    )
    if unknown:
        lines.append(f"serves in the log but not in the library (pruned or foreign): {', '.join(unknown)}")
    return "\n".join(lines)
