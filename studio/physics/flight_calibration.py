"""Ball flight and table bounce models checked and fitted on real match flights.

Data: the Ace public match data (``data/match_data.csv`` of SonyResearch/ace_public,
supplementary data of "Outplaying elite table tennis players with an autonomous robot",
Nature 652, 2026): for every event of a rally (racket shot, table bounce, net touch) the
ball's position and its velocity and spin just *after* the event, world frame of the
project (origin at the centre of the playing surface, +X towards the human, +Z up), SI
units. The file has no licence: it is read from a path (default
:data:`DEFAULT_MATCH_CSV`, outside the repository) and never copied; only derived
figures are written (``studio/data/flight_model.json``).

Between two consecutive events the ball flies freely. A *flight* starts at an event's
post-event state and, when the next event is a table bounce, ends at a measured landing
point and time. :func:`replay` flies every flight with a :class:`FlightModel` (a batch
RK4 integrator, :func:`integrate_to_table`, same equations as :func:`studio.physics.ball.simulate`)
to its predicted table contact and reports the landing position error (horizontal,
[m]), time error [s] and whether the ball was predicted into the net; at the landing it
applies the :class:`TableBounceModel` to the *predicted* pre-bounce state and compares
with the measured post-bounce velocity and spin.

:func:`fit_flight_model` fits drag, lift and spin decay by robust least squares on the
landing errors; :func:`cross_validate` repeats the fit leaving one player (or a group of
rallies) out; :func:`fit_table_friction` refits the table friction on the measured
bounces, the restitution then being re-tuned to the ITTF drop test
(:func:`studio.physics.ball_calibration.tune_table_restitution`). :func:`calibrate_flight` runs
it all and :func:`format_flight_table` prints the calibration table.

Entry point: ``serve-studio calibrate --match [--csv PATH] [--write]``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Literal, Protocol

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from studio.errors import DataFileError, InvalidInputError
from studio.paths import DATA_DIR, SHARED_DATA_DIR
from studio.physics.ball import FlightModel, TableBounceModel, spin_components
from studio.physics.court import DEFAULT_COURT, Court
from studio.storage.jsonfile import not_utf8_file

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

DEFAULT_MATCH_CSV = SHARED_DATA_DIR / "ace_match" / "match_data_dev.csv"
"""Default location of the match data: ``../shared/data/ace_match/`` next to the repository."""

FLIGHT_MODEL_JSON = DATA_DIR / "flight_model.json"
"""Record of the fitted flight/table parameters and their figures (no data rows)."""

SOURCE = (
    "Ace public match data, SonyResearch/ace_public data/match_data.csv "
    "(Nature 652, 2026), players Elite A, Elite B, Elite C, Pro 1"
)
"""Where the fitted figures come from."""

COLUMNS = ("player_id", "rally_id", "type", "timestamp", "ball_pos", "ball_vel_out", "ball_spin_out")
"""Columns the match CSV must have (extra columns are ignored)."""

EVENT_TYPES = ("shot_p1", "shot_p2", "bounce_p1", "bounce_p2", "net")
"""Event kinds of the match data."""

FlightKind = Literal["serve", "serve_bounce", "rally", "net", "other"]
"""``serve``: a rally's first shot to the server's-half bounce; ``serve_bounce``: that
bounce to the receiver's-half bounce; ``rally``: any later shot to its bounce; ``net``:
from a net touch to the bounce; ``other``: any other bounce-to-bounce flight."""

TIME_WEIGHT = 5.0
"""Weight of the landing-time residual in the fit [m/s]: 1 ms of time error counts as 5 mm."""

FIT_SCALE = 0.05
"""Soft-L1 loss scale of the fit [m]: residuals beyond ~5 cm count linearly (outliers)."""


# =====================================================================================
# Data
# =====================================================================================


@dataclass(frozen=True, slots=True)
class MatchEvent:
    """One event of a rally with the measured post-event ball state (world frame, SI)."""

    kind: str
    """One of :data:`EVENT_TYPES`."""
    index: int
    """Event number within the rally (``eventN`` of the rally id)."""
    t: float
    """Event time [s]."""
    p: FloatArray
    """Ball centre position [m], (3,)."""
    v: FloatArray
    """Velocity just after the event [m/s], (3,)."""
    w: FloatArray
    """Spin just after the event [rad/s], (3,)."""
    line: int
    """Line of the CSV file (header = line 1)."""


@dataclass(frozen=True, slots=True)
class Rally:
    """The events of one rally in event order."""

    player: str
    """Human player id (``player_id``)."""
    rally_id: str
    """``/<game>/<rally>`` (unique together with the player)."""
    events: tuple[MatchEvent, ...]
    """Events sorted by event number."""


def _parse_vector(cell: str, where: str, path: Path) -> FloatArray:
    """A ``[x y z]`` (or ``x, y, z``) cell as a finite (3,) array; DataFileError naming ``where``."""
    text = cell.strip().strip("[]()").replace(",", " ")
    parts = text.split()
    try:
        values = [float(s) for s in parts]
    except ValueError:
        raise DataFileError(path, f"{where}: not a vector of 3 numbers: {cell!r}") from None
    if len(values) != 3 or not all(math.isfinite(x) for x in values):
        raise DataFileError(path, f"{where}: expected 3 finite numbers, got {cell!r}")
    arr = np.array(values)
    arr.setflags(write=False)
    return arr


def _parse_row(row: dict[str, str], line: int, path: Path) -> tuple[str, str, MatchEvent]:
    """(player, rally id, event) of one CSV record; DataFileError naming line and column."""
    where = lambda col: f"line {line}, column {col!r}"  # noqa: E731
    player = (row.get("player_id") or "").strip()
    if not player:
        raise DataFileError(path, f"{where('player_id')}: empty")
    rid = (row.get("rally_id") or "").strip()
    parts = rid.strip("/").split("/")
    if len(parts) != 3 or not parts[2].startswith("event") or not parts[2][5:].isdigit():
        raise DataFileError(path, f"{where('rally_id')}: expected '/<game>/<rally>/event<N>', got {rid!r}")
    kind = (row.get("type") or "").strip()
    if kind not in EVENT_TYPES:
        raise DataFileError(path, f"{where('type')}: unknown event type {kind!r} (expected one of {EVENT_TYPES})")
    try:
        t = float(row.get("timestamp") or "")
    except ValueError:
        raise DataFileError(path, f"{where('timestamp')}: not a number: {row.get('timestamp')!r}") from None
    if not math.isfinite(t):
        raise DataFileError(path, f"{where('timestamp')}: not finite")
    vecs = [_parse_vector(row.get(c) or "", where(c), path) for c in ("ball_pos", "ball_vel_out", "ball_spin_out")]
    event = MatchEvent(kind=kind, index=int(parts[2][5:]), t=t, p=vecs[0], v=vecs[1], w=vecs[2], line=line)
    return player, "/" + "/".join(parts[:2]), event


def _rally(player: str, rally_id: str, events: list[MatchEvent], path: Path) -> Rally:
    """Events sorted by number; DataFileError on duplicate numbers or time going back."""
    events = sorted(events, key=lambda e: e.index)
    for a, b in zip(events, events[1:], strict=False):
        if b.index == a.index:
            raise DataFileError(
                path,
                f"line {b.line}, column 'rally_id': event {b.index} of {player} {rally_id} repeated (line {a.line})",
            )
        if b.t < a.t:
            raise DataFileError(
                path, f"line {b.line}, column 'timestamp': time {b.t} before the previous event's {a.t} (line {a.line})"
            )
    return Rally(player=player, rally_id=rally_id, events=tuple(events))


def load_match_events(path: str | os.PathLike[str] | None = None) -> tuple[Rally, ...]:
    """Read the match CSV (columns :data:`COLUMNS`) into rallies, in file order.

    Args:
        path: the CSV; None reads :data:`DEFAULT_MATCH_CSV`.

    Raises:
        DataFileError: missing/unreadable file, missing column, a malformed cell (the
            message names the line and column), a repeated event, or no rows.
    """
    path = Path(DEFAULT_MATCH_CSV if path is None else path)
    if not path.is_file():
        raise DataFileError(
            path,
            "match data file not found (the Ace match CSV is not shipped: "
            "put it at ../shared/data/ace_match/ or pass its path)",
        )
    groups: dict[tuple[str, str], list[MatchEvent]] = {}
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise DataFileError(path, f"line 1: missing column(s) {missing}")
            for row in reader:
                line = reader.line_num
                if None in row or any(row[c] is None for c in COLUMNS):
                    raise DataFileError(
                        path, f"line {line}: {len(row)} fields, expected {len(reader.fieldnames or [])}"
                    )
                player, rid, event = _parse_row(row, line, path)
                groups.setdefault((player, rid), []).append(event)
    except UnicodeDecodeError:
        raise not_utf8_file(path) from None
    except (OSError, csv.Error) as exc:
        raise DataFileError(path, f"cannot read the match data: {exc}") from exc
    if not groups:
        raise DataFileError(path, "no data rows")
    return tuple(_rally(p, r, evs, path) for (p, r), evs in groups.items())


# =====================================================================================
# Flights
# =====================================================================================


@dataclass(frozen=True, slots=True)
class Flights:
    """Free flights between consecutive events (struct of arrays, N flights).

    Flights whose next event is a table bounce have a measured landing (``landed``);
    flights ending at a net touch have ``measured_net`` and no landing. For a flight
    ending at a bounce, ``v_after`` / ``w_after`` hold the bounce's measured post-event
    state (the start of the next flight) when the rally goes on after it, else NaN.
    """

    p0: FloatArray
    """Start position [m] (N, 3): the post-event state of the start event."""
    v0: FloatArray
    """Start velocity [m/s] (N, 3)."""
    w0: FloatArray
    """Start spin [rad/s] (N, 3)."""
    t0: FloatArray
    """Start time [s] (N,)."""
    kind: tuple[FlightKind, ...]
    """Flight kind (:data:`FlightKind`)."""
    start_event: tuple[str, ...]
    """Event type the flight starts at."""
    end_event: tuple[str, ...]
    """Event type the flight ends at."""
    p_end: FloatArray
    """Measured landing position [m] (N, 3), NaN unless ``landed``."""
    t_end: FloatArray
    """Time of the end event [s] (N,)."""
    landed: BoolArray
    """The flight ends at a measured table bounce (N,)."""
    measured_net: BoolArray
    """The flight ends at a measured net touch (N,)."""
    v_after: FloatArray
    """Measured velocity after the landing bounce [m/s] (N, 3), NaN if none."""
    w_after: FloatArray
    """Measured spin after the landing bounce [rad/s] (N, 3), NaN if none."""
    player: tuple[str, ...]
    """Player of the rally."""
    rally: tuple[str, ...]
    """``<player><rally_id>``: a unique rally key."""

    def __len__(self) -> int:
        return int(self.p0.shape[0])

    def subset(self, mask: npt.ArrayLike) -> Flights:
        """The flights selected by a boolean mask or an index array."""
        idx = np.asarray(mask)
        if idx.dtype == bool:
            idx = np.nonzero(idx)[0]
        kw: dict[str, object] = {}
        for f in fields(self):
            val = getattr(self, f.name)
            kw[f.name] = val[idx] if isinstance(val, np.ndarray) else tuple(val[i] for i in idx.tolist())
        return Flights(**kw)  # type: ignore[arg-type]

    def kind_mask(self, *kinds: str) -> BoolArray:
        """Boolean mask (N,) of the flights of the given kinds."""
        return np.array([k in kinds for k in self.kind], dtype=bool)


def _flight_kind(rally: Rally, i: int) -> FlightKind:
    """Kind of the flight from event ``i`` of ``rally`` to event ``i + 1``."""
    a = rally.events[i]
    if a.kind.startswith("shot"):
        return "serve" if i == 0 else "rally"
    if a.kind == "net":
        return "net"
    return "serve_bounce" if i == 1 and rally.events[0].kind.startswith("shot") else "other"


def match_flights(rallies: Iterable[Rally]) -> Flights:
    """Flights from each shot, bounce or net event to the next event when that is a
    table bounce (measured landing) or a net touch (``measured_net``).

    Flights ending at a racket (bounce -> shot) have no measured landing and are left out.
    """
    nan3 = np.full(3, np.nan)
    cols: dict[str, list[object]] = {f.name: [] for f in fields(Flights)}
    for rally in rallies:
        ev = rally.events
        for i in range(len(ev) - 1):
            a, b = ev[i], ev[i + 1]
            landed = b.kind.startswith("bounce")
            if not (landed or b.kind == "net"):
                continue
            goes_on = landed and i + 2 < len(ev)
            for name, val in (
                ("p0", a.p),
                ("v0", a.v),
                ("w0", a.w),
                ("t0", a.t),
                ("kind", _flight_kind(rally, i)),
                ("start_event", a.kind),
                ("end_event", b.kind),
                ("p_end", b.p if landed else nan3),
                ("t_end", b.t),
                ("landed", landed),
                ("measured_net", b.kind == "net"),
                ("v_after", b.v if goes_on else nan3),
                ("w_after", b.w if goes_on else nan3),
                ("player", rally.player),
                ("rally", rally.player + rally.rally_id),
            ):
                cols[name].append(val)
    if not cols["p0"]:
        raise InvalidInputError("match_flights: no flight ends at a table bounce or the net")
    kw: dict[str, object] = {}
    for f in fields(Flights):
        vals = cols[f.name]
        if f.name in ("kind", "start_event", "end_event", "player", "rally"):
            kw[f.name] = tuple(vals)
        else:
            kw[f.name] = np.array(vals, dtype=bool if f.name in ("landed", "measured_net") else float)
    return Flights(**kw)  # type: ignore[arg-type]


# =====================================================================================
# Batch integrator
# =====================================================================================


class FlightEquations(Protocol):
    """What the batch integrator needs of a flight model (:class:`FlightModel` has it)."""

    @property
    def radius(self) -> float:
        """Ball radius [m]."""
        ...

    def acceleration(self, p: npt.ArrayLike, v: npt.ArrayLike, w: npt.ArrayLike) -> FloatArray: ...

    def spin_derivative(self, v: npt.ArrayLike, w: npt.ArrayLike) -> FloatArray: ...


@dataclass(frozen=True, slots=True)
class BatchLanding:
    """Where and when each of N flights first reaches the table plane (ball centre at z = r).

    The table is taken as the infinite plane z = 0 (a landing off the table is still
    located on that plane) and the net as the plane x = 0 (see :func:`integrate_to_table`).
    """

    t: FloatArray
    """Flight time to the contact [s] (N,), NaN if none within ``t_max``."""
    p: FloatArray
    """Ball centre at the contact [m] (N, 3)."""
    v: FloatArray
    """Velocity just before the contact [m/s] (N, 3)."""
    w: FloatArray
    """Spin just before the contact [rad/s] (N, 3)."""
    net: BoolArray
    """The ball crossed the net plane touching the net (N,) (the flight was continued
    through it as if the net were not there)."""
    net_clearance: FloatArray
    """Height of the ball's bottom above the net top when crossing x = 0 [m] (N,), NaN
    if it did not cross before the contact."""


def _state_derivative(model: FlightEquations, y: FloatArray) -> FloatArray:
    """d/dt of states (N, 9) ``[p, v, w]`` with the model's own vectorized equations."""
    v, w = y[:, 3:6], y[:, 6:9]
    return np.concatenate([v, model.acceleration(y[:, 0:3], v, w), model.spin_derivative(v, w)], axis=1)


def _rk4(model: FlightEquations, y: FloatArray, f: FloatArray, h: float) -> tuple[FloatArray, FloatArray]:
    """One classic RK4 step of all states (N, 9); returns the new states and derivatives."""
    k2 = _state_derivative(model, y + 0.5 * h * f)
    k3 = _state_derivative(model, y + 0.5 * h * k2)
    k4 = _state_derivative(model, y + h * k3)
    y1 = y + h / 6.0 * (f + 2.0 * k2 + 2.0 * k3 + k4)
    return y1, _state_derivative(model, y1)


def _hermite(th: FloatArray, h: float, ya: FloatArray, fa: FloatArray, yb: FloatArray, fb: FloatArray) -> FloatArray:
    """Cubic Hermite dense output at fractions ``th`` (M,) of the step, rows (M, k)."""
    t = th[:, None]
    t2, t3 = t * t, t * t * t
    return (2 * t3 - 3 * t2 + 1) * ya + (t3 - 2 * t2 + t) * h * fa + (-2 * t3 + 3 * t2) * yb + (t3 - t2) * h * fb


def _root(g: Callable[[FloatArray], FloatArray], n: int, iters: int = 40) -> FloatArray:
    """Fractions th (n,) in [0, 1] where each of n functions goes from > 0 to <= 0 (bisection)."""
    lo, hi = np.zeros(n), np.ones(n)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        neg = g(mid) <= 0.0
        hi = np.where(neg, mid, hi)
        lo = np.where(neg, lo, mid)
    return hi


def integrate_to_table(
    p0: npt.ArrayLike,
    v0: npt.ArrayLike,
    w0: npt.ArrayLike,
    model: FlightEquations,
    *,
    step: float = 0.004,
    t_max: float = 2.0,
    court: Court = DEFAULT_COURT,
    check_net: npt.ArrayLike | bool = True,
) -> BatchLanding:
    """Fly N balls at once (RK4, fixed ``step`` [s]) to their first table contact.

    The equations are the model's :meth:`FlightModel.acceleration` and
    :meth:`FlightModel.spin_derivative` (those of :func:`studio.physics.ball.simulate`). The
    contact is the first instant the ball centre descends to z = r after having been
    above it (a flight starting at a bounce, centre below r, is armed once it rises),
    located on the cubic Hermite dense output by bisection. The net: when the centre
    crosses x = 0 with ``|y|`` within the net span and its bottom below the net top
    (z - r < net height), the flight is flagged ``net`` and continued through.

    Args:
        p0, v0, w0: start states (N, 3) [m, m/s, rad/s].
        model: the flight equations.
        step: RK4 step [s] (0.004 s keeps the landing point within ~1e-5 m of
            :func:`simulate`'s 0.01 s steps with Hermite event location).
        t_max: longest flight [s].
        court: net height and span.
        check_net: per flight (N,) or for all: look for a net crossing.
    """
    y = np.concatenate([np.atleast_2d(p0), np.atleast_2d(v0), np.atleast_2d(w0)], axis=1).astype(float)
    n = y.shape[0]
    r = model.radius
    f = _state_derivative(model, y)
    out_t, out_y = np.full(n, np.nan), np.full((n, 9), np.nan)
    net, clear = np.zeros(n, dtype=bool), np.full(n, np.nan)
    watch_net = np.broadcast_to(np.asarray(check_net, dtype=bool), (n,)).copy()
    armed = y[:, 2] > r
    open_ = np.ones(n, dtype=bool)
    t = 0.0
    while t < t_max and np.any(open_):
        y1, f1 = _rk4(model, y, f, step)
        hit = open_ & armed & (y1[:, 2] <= r)
        cross = open_ & watch_net & (np.sign(y[:, 0]) != np.sign(y1[:, 0]))
        th_hit = np.ones(n)
        if np.any(hit):
            th_hit[hit] = _contact_fraction(step, y[hit], f[hit], y1[hit], f1[hit], r)
            out_y[hit] = _hermite(th_hit[hit], step, y[hit], f[hit], y1[hit], f1[hit])
            out_t[hit] = t + th_hit[hit] * step
        if np.any(cross):
            _net_crossing(cross, th_hit, step, y, f, y1, f1, r, court, net, clear)
            watch_net &= ~cross
        open_ &= ~hit
        armed |= y1[:, 2] > r
        y, f, t = y1, f1, t + step
    return BatchLanding(t=out_t, p=out_y[:, 0:3], v=out_y[:, 3:6], w=out_y[:, 6:9], net=net, net_clearance=clear)


def _contact_fraction(h: float, ya: FloatArray, fa: FloatArray, yb: FloatArray, fb: FloatArray, r: float) -> FloatArray:
    """Step fractions (M,) where the dense-output height of M states reaches z = r."""

    def height(th: FloatArray) -> FloatArray:
        return _hermite(th, h, ya[:, 2:3], fa[:, 2:3], yb[:, 2:3], fb[:, 2:3])[:, 0] - r

    return _root(height, ya.shape[0])


def _net_crossing(
    cross: BoolArray,
    th_hit: FloatArray,
    h: float,
    y: FloatArray,
    f: FloatArray,
    y1: FloatArray,
    f1: FloatArray,
    r: float,
    court: Court,
    net: BoolArray,
    clear: FloatArray,
) -> None:
    """Fill ``net`` / ``clear`` for flights crossing x = 0 in this step before their contact."""
    k = np.nonzero(cross)[0]
    sign0 = np.sign(y[k, 0])
    th = _root(lambda s: sign0 * _hermite(s, h, y[k, 0:1], f[k, 0:1], y1[k, 0:1], f1[k, 0:1])[:, 0], len(k))
    before = th <= th_hit[k]
    k, th = k[before], th[before]
    if len(k) == 0:
        return
    pc = _hermite(th, h, y[k, 0:3], f[k, 0:3], y1[k, 0:3], f1[k, 0:3])
    clear[k] = pc[:, 2] - r - court.net_height
    net[k] = (clear[k] < 0.0) & (np.abs(pc[:, 1]) <= court.net_half_span + r)


# =====================================================================================
# Replay
# =====================================================================================

VELOCITY_LAG = 0.0187
"""Effective lag of the match data's post-event velocities [s]: the measured
``ball_vel_out`` behaves as the velocity ``VELOCITY_LAG`` after the event, so
:func:`replay` uses ``v(t_event) = v_measured - a(v_measured, w) * VELOCITY_LAG`` (``a``
the flight model's acceleration). Fitted jointly with the flight parameters
(:func:`fit_flight_model`; 18.1-19.1 ms in the leave-one-player-out folds; fitted
separately, 19.4 ms after shots and 17.5 ms after bounces). Without it the serves'
flights from the first to the second bounce land ~30 ms early whatever the drag and
lift, and no drag/lift fit reaches the targets. Presumably the vision system's velocity
estimate averages the first frames after the event (the Ace pseudo-code describes a
filtered estimate from successive 200 Hz positions); this is an inference from the data,
not documented. Consequence for comparisons with the data: its post-event speeds are
~0.2 m/s (vertical: g x lag) below the velocity at the event."""


@dataclass(frozen=True, slots=True)
class Replay:
    """Per-flight results of :func:`replay` (N flights, NaN where not applicable)."""

    landing_error: FloatArray
    """Horizontal distance [m] between predicted and measured landing (N,)."""
    time_error: FloatArray
    """Predicted minus measured flight time [s] (N,)."""
    predicted_net: BoolArray
    """The predicted flight touches the net (N,)."""
    net_clearance: FloatArray
    """Predicted height of the ball's bottom above the net top at x = 0 [m] (N,)."""
    p_land: FloatArray
    """Predicted landing point [m] (N, 3)."""
    v_in: FloatArray
    """Predicted velocity just before the landing [m/s] (N, 3)."""
    w_in: FloatArray
    """Predicted spin just before the landing [rad/s] (N, 3)."""
    v_out: FloatArray
    """Velocity after the landing bounce by the table model [m/s] (N, 3)."""
    w_out: FloatArray
    """Spin after the landing bounce by the table model [rad/s] (N, 3)."""
    v_after: FloatArray
    """Measured velocity after the landing bounce, lag-corrected [m/s] (N, 3)."""
    velocity_lag: float
    """Lag used to correct the measured velocities [s]."""


def corrected_velocity(model: FlightEquations, v: FloatArray, w: FloatArray, lag: float) -> FloatArray:
    """Velocity at the event [m/s] from a measured one that lags by ``lag`` [s] (first order)."""
    if lag == 0.0:
        return np.asarray(v, dtype=float)
    return v - lag * model.acceleration(np.zeros_like(v), v, w)


def replay(
    flights: Flights,
    flight_model: FlightEquations,
    table_model: TableBounceModel | None = None,
    *,
    velocity_lag: float = VELOCITY_LAG,
) -> Replay:
    """Fly every flight from its (lag-corrected) start state to its predicted landing.

    Flights starting at a net touch are not checked against the net. At the landing
    the table model (default :class:`TableBounceModel`) is applied to the predicted
    pre-bounce state, to compare with the measured post-bounce state.
    """
    table = TableBounceModel() if table_model is None else table_model
    v0 = corrected_velocity(flight_model, flights.v0, flights.w0, velocity_lag)
    land = integrate_to_table(flights.p0, v0, flights.w0, flight_model, check_net=~flights.kind_mask("net"))
    err = np.linalg.norm(land.p[:, :2] - flights.p_end[:, :2], axis=1)
    terr = land.t - (flights.t_end - flights.t0)
    ok = np.isfinite(land.t)
    v_out = np.full_like(land.v, np.nan)
    w_out = np.full_like(land.w, np.nan)
    if np.any(ok):
        v_out[ok], w_out[ok] = table.bounce(land.v[ok], land.w[ok])
    has_after = np.isfinite(flights.v_after[:, 0])
    v_after = np.full_like(flights.v_after, np.nan)
    v_after[has_after] = corrected_velocity(
        flight_model, flights.v_after[has_after], flights.w_after[has_after], velocity_lag
    )
    return Replay(
        landing_error=np.where(flights.landed, err, np.nan),
        time_error=np.where(flights.landed, terr, np.nan),
        predicted_net=land.net,
        net_clearance=land.net_clearance,
        p_land=land.p,
        v_in=land.v,
        w_in=land.w,
        v_out=v_out,
        w_out=w_out,
        v_after=v_after,
        velocity_lag=float(velocity_lag),
    )


@dataclass(frozen=True, slots=True)
class GroupFigures:
    """Landing figures of one group of flights with a measured landing."""

    count: int
    """Number of flights."""
    median: float
    """Median landing position error [m]."""
    p90: float
    """90th percentile of the landing position error [m]."""
    time_median_abs: float
    """Median absolute landing time error [s]."""
    time_median: float
    """Median signed time error [s] (< 0: predicted early)."""
    predicted_net: int
    """Flights predicted into the net although they landed without a net touch."""


@dataclass(frozen=True, slots=True)
class ReplaySummary:
    """:func:`replay` figures per flight kind."""

    serve: GroupFigures
    """Serve flights, racket to the first (server's-half) bounce."""
    serve_bounce: GroupFigures
    """Serve flights, first to second bounce."""
    rally: GroupFigures
    """Rally flights (a later shot to its bounce)."""
    net_start: GroupFigures
    """Flights from a net touch to the bounce."""
    measured_net: int
    """Flights ending at a measured net touch."""
    measured_net_predicted: int
    """Of those, the ones the model also sends into the net."""

    @property
    def false_net(self) -> int:
        """Landed flights (any kind) predicted into the net."""
        return self.serve.predicted_net + self.serve_bounce.predicted_net + self.rally.predicted_net


def _group(flights: Flights, rep: Replay, mask: BoolArray) -> GroupFigures:
    """Figures of the landed flights in ``mask`` (NaN figures when there are none)."""
    m = mask & flights.landed & np.isfinite(rep.landing_error)
    e, t = rep.landing_error[m], rep.time_error[m]
    if not np.any(m):
        return GroupFigures(0, math.nan, math.nan, math.nan, math.nan, 0)
    return GroupFigures(
        count=int(m.sum()),
        median=float(np.median(e)),
        p90=float(np.percentile(e, 90)),
        time_median_abs=float(np.median(np.abs(t))),
        time_median=float(np.median(t)),
        predicted_net=int(np.sum(rep.predicted_net & m & ~flights.measured_net)),
    )


def summarize(flights: Flights, rep: Replay) -> ReplaySummary:
    """Per-kind figures of a :func:`replay` (landing errors of flights that landed)."""
    mn = flights.measured_net
    return ReplaySummary(
        serve=_group(flights, rep, flights.kind_mask("serve")),
        serve_bounce=_group(flights, rep, flights.kind_mask("serve_bounce")),
        rally=_group(flights, rep, flights.kind_mask("rally")),
        net_start=_group(flights, rep, flights.kind_mask("net")),
        measured_net=int(mn.sum()),
        measured_net_predicted=int(np.sum(mn & rep.predicted_net)),
    )


# =====================================================================================
# Flight model fit
# =====================================================================================

FIT_PARAMETERS = ("drag_coefficient", "lift_a", "lift_b")
"""Flight model fields fitted by :func:`fit_flight_model` (plus the velocity lag)."""

_BOUNDS = {"drag_coefficient": (0.1, 1.5), "lift_a": (0.01, 10.0), "lift_b": (0.0, 20.0), "lag": (-0.05, 0.1)}
"""Search box of the fitted parameters."""

FIT_KINDS = ("serve", "serve_bounce", "rally")
"""Flight kinds used to fit (flights from a net touch are left out)."""


@dataclass(frozen=True, slots=True)
class FlightFit:
    """Result of :func:`fit_flight_model`."""

    model: FlightModel
    """The fitted flight model."""
    velocity_lag: float
    """Fitted (or fixed) velocity lag of the data [s]."""
    cost: float
    """Final robust cost (scipy ``least_squares``) [m^2]."""
    nfev: int
    """Function evaluations."""
    n_flights: int
    """Flights fitted."""


def spin_decay_from_bounces(flights: Flights, *, min_spin: float = 80.0) -> float:
    """Spin decay per metre [1/m] from the vertical spin ``w_z`` across flights.

    The table bounce leaves ``w_z`` unchanged in the model (a torsional loss at the
    table would only lower it), so ``|w_z|`` after the landing bounce over ``|w_z|`` at
    the start measures the decay over the flight: the median over flights with
    ``|w_z| > min_spin`` [rad/s] of ``-ln(ratio) / path`` (path ~ the straight
    distance). An upper bound of the air's decay if the table takes some ``w_z``.
    """
    m = flights.landed & np.isfinite(flights.w_after[:, 2]) & (np.abs(flights.w0[:, 2]) > min_spin)
    if not np.any(m):
        raise InvalidInputError("spin_decay_from_bounces: no flight with a measured spin after its landing")
    ratio = np.abs(flights.w_after[m, 2]) / np.abs(flights.w0[m, 2])
    path = np.linalg.norm(flights.p_end[m] - flights.p0[m], axis=1)
    return float(max(0.0, np.median(-np.log(np.maximum(ratio, 1e-3)) / np.maximum(path, 0.1))))


def _model_from(x: FloatArray, base: FlightModel) -> FlightModel:
    """``base`` with the :data:`FIT_PARAMETERS` set from ``x``."""
    return replace(base, **{n: float(v) for n, v in zip(FIT_PARAMETERS, x, strict=False)})


def _fit_residuals(
    x: FloatArray, flights: Flights, base: FlightModel, lag: float | None, time_weight: float
) -> FloatArray:
    """Landing position (2 per flight) and weighted time residuals [m]; a flight that
    never lands counts 1 m / 0.2 s."""
    model = _model_from(x, base)
    v0 = corrected_velocity(model, flights.v0, flights.w0, float(x[-1]) if lag is None else lag)
    land = integrate_to_table(flights.p0, v0, flights.w0, model, check_net=False)
    dp = np.nan_to_num(land.p[:, :2] - flights.p_end[:, :2], nan=1.0)
    dt = np.nan_to_num(land.t - (flights.t_end - flights.t0), nan=0.2)
    return np.concatenate([dp.ravel(), time_weight * dt])


def fit_flight_model(
    flights: Flights,
    *,
    initial: FlightModel | None = None,
    spin_decay: float | None = None,
    velocity_lag: float | None = None,
    time_weight: float = TIME_WEIGHT,
    loss: str = "soft_l1",
    f_scale: float = FIT_SCALE,
) -> FlightFit:
    """Fit drag coefficient, lift law (``lift_a``, ``lift_b``) and the data's velocity lag.

    Robust nonlinear least squares (scipy ``least_squares``, soft-L1 loss of scale
    ``f_scale`` [m]) on the landing position errors [m] and the landing time errors
    times ``time_weight`` [m/s] of the landed flights of kinds :data:`FIT_KINDS`.
    The spin decay is not identifiable from landings (the cost changes by < 0.1 % from
    0 to 0.12 /m): it is fixed, by default from :func:`spin_decay_from_bounces`.

    Args:
        flights: flights (others than :data:`FIT_KINDS` or without landing are ignored).
        initial: start point and the fixed fields (default :class:`FlightModel`).
        spin_decay: fixed spin decay [1/m] (None: measured from the flights).
        velocity_lag: fixed lag [s] (None: fitted).
        time_weight, loss, f_scale: the cost, see above.
    """
    use = flights.subset(flights.landed & flights.kind_mask(*FIT_KINDS))
    if len(use) < 5:
        raise InvalidInputError(f"fit_flight_model: {len(use)} landed flights, need at least 5")
    decay = spin_decay_from_bounces(use) if spin_decay is None else float(spin_decay)
    base = replace(FlightModel() if initial is None else initial, spin_decay=decay)
    names = FIT_PARAMETERS + (("lag",) if velocity_lag is None else ())
    x0 = [getattr(base, n) for n in FIT_PARAMETERS] + ([VELOCITY_LAG] if velocity_lag is None else [])
    lo, hi = zip(*(_BOUNDS[n] for n in names), strict=True)
    x0 = np.clip(x0, np.array(lo) + 1e-9, np.array(hi) - 1e-9)
    sol = least_squares(
        _fit_residuals,
        x0,
        args=(use, base, velocity_lag, time_weight),
        bounds=(lo, hi),
        loss=loss,
        f_scale=f_scale,
        diff_step=1e-3,
        x_scale=[0.1, 0.1, 0.5] + [0.01] * (velocity_lag is None),
    )
    lag = float(sol.x[-1]) if velocity_lag is None else float(velocity_lag)
    return FlightFit(
        model=_model_from(sol.x, base), velocity_lag=lag, cost=float(sol.cost), nfev=int(sol.nfev), n_flights=len(use)
    )


# =====================================================================================
# Cross-validation
# =====================================================================================


@dataclass(frozen=True, slots=True)
class FoldResult:
    """One cross-validation fold: fit on the other groups, figures on this one."""

    held_out: str
    """The held-out player or rally group."""
    n_flights: int
    """Held-out flights with a measured landing or net touch."""
    before: ReplaySummary
    """Held-out figures of the reference model (before)."""
    after: ReplaySummary
    """Held-out figures of the model fitted without these flights."""
    fit: FlightFit
    """The fold's fit."""


def rally_groups(flights: Flights, folds: int = 5, seed: int = 0) -> tuple[str, ...]:
    """Label each flight with one of ``folds`` random groups of whole rallies."""
    rallies = sorted(set(flights.rally))
    order = np.random.default_rng(seed).permutation(len(rallies))
    label = {rallies[i]: f"rallies {k % folds + 1}/{folds}" for k, i in enumerate(order.tolist())}
    return tuple(label[r] for r in flights.rally)


def cross_validate(
    flights: Flights,
    groups: Sequence[str],
    *,
    reference: FlightModel,
    reference_lag: float = 0.0,
    spin_decay: float | None = None,
) -> tuple[FoldResult, ...]:
    """Grouped cross-validation: for each group, fit on the others and replay it.

    Args:
        flights: all flights.
        groups: a label per flight (e.g. ``flights.player`` or :func:`rally_groups`).
        reference: the "before" model, replayed with ``reference_lag`` [s].
        spin_decay: fixed spin decay for the fits (None: measured on the training flights).
    """
    labels = np.array(groups)
    out: list[FoldResult] = []
    for g in sorted(set(groups)):
        test = flights.subset(labels == g)
        fit = fit_flight_model(flights.subset(labels != g), initial=reference, spin_decay=spin_decay)
        out.append(
            FoldResult(
                held_out=g,
                n_flights=len(test),
                before=summarize(test, replay(test, reference, velocity_lag=reference_lag)),
                after=summarize(test, replay(test, fit.model, velocity_lag=fit.velocity_lag)),
                fit=fit,
            )
        )
    return tuple(out)


def pooled_replay(flights: Flights, groups: Sequence[str], folds: Sequence[FoldResult]) -> Replay:
    """Held-out replay of every flight by the model of its fold (pooled CV figures)."""
    labels = np.array(groups)
    parts = {
        f.held_out: replay(flights.subset(labels == f.held_out), f.fit.model, velocity_lag=f.fit.velocity_lag)
        for f in folds
    }
    kw: dict[str, object] = {}
    for fld in fields(Replay):
        if fld.name == "velocity_lag":
            kw[fld.name] = math.nan
            continue
        first = getattr(next(iter(parts.values())), fld.name)
        arr = np.zeros((len(flights), *first.shape[1:]), dtype=first.dtype)
        for g, rep in parts.items():
            arr[labels == g] = getattr(rep, fld.name)
        kw[fld.name] = arr
    return Replay(**kw)  # type: ignore[arg-type]


# =====================================================================================
# Table bounce check
# =====================================================================================

BOUNCE_VELOCITY_SCALE = 0.3
"""Normalization of post-bounce velocity residuals in the friction fit [m/s]."""

BOUNCE_SPIN_SCALE = 30.0
"""Normalization of post-bounce spin residuals in the friction fit [rad/s]."""


@dataclass(frozen=True, slots=True)
class BounceCheck:
    """Table model applied to predicted pre-bounce states vs the measured post-bounce states."""

    count: int
    """Bounces compared (a flight landing on the table and the rally going on)."""
    rms_velocity: float
    """RMS of the post-bounce velocity error norm [m/s]."""
    rms_spin: float
    """RMS of the post-bounce spin error norm [rad/s]."""
    median_velocity: float
    """Median post-bounce velocity error norm [m/s]."""
    median_spin: float
    """Median post-bounce spin error norm [rad/s]."""
    rms_tangential_velocity: float
    """RMS of the horizontal post-bounce velocity error [m/s] (friction only)."""
    vz_ratio_data: float
    """Median measured |v_z out| / predicted |v_z in| [-] (an apparent restitution)."""
    sliding_fraction: float
    """Fraction of the bounces the model puts in the sliding regime."""
    spin_gain_data: float
    """Median change of the topspin component per m/s of incoming vertical speed over
    the sliding bounces, measured [rad/s per m/s] (backspin lost / topspin gained)."""
    spin_gain_model: float
    """The same for the model on the same bounces [rad/s per m/s]."""


def _bounce_rows(flights: Flights, rep: Replay) -> BoolArray:
    """Flights with a predicted pre-bounce state and a measured post-bounce state."""
    return flights.landed & np.isfinite(rep.v_after[:, 0]) & np.isfinite(rep.v_in[:, 0]) & (rep.v_in[:, 2] < 0.0)


def bounce_check(flights: Flights, rep: Replay, table: TableBounceModel) -> BounceCheck:
    """Compare ``table`` applied to the replay's predicted pre-bounce states with the data."""
    m = _bounce_rows(flights, rep)
    v_in, w_in = rep.v_in[m], rep.w_in[m]
    v_out, w_out = table.bounce(v_in, w_in)
    v_meas, w_meas = rep.v_after[m], flights.w_after[m]
    dv = np.linalg.norm(v_out - v_meas, axis=1)
    dw = np.linalg.norm(w_out - w_meas, axis=1)
    vz = -v_in[:, 2]
    r = table.radius
    slip = np.hypot(v_in[:, 0] - r * w_in[:, 1], v_in[:, 1] + r * w_in[:, 0])
    sliding = slip > 2.5 * table.friction * (1.0 + table.restitution) * vz
    tb_in = spin_components(v_in, w_in)[0]
    gain_data = (spin_components(v_in, w_meas)[0] - tb_in) / vz
    gain_model = (spin_components(v_in, w_out)[0] - tb_in) / vz
    return BounceCheck(
        count=int(m.sum()),
        rms_velocity=float(np.sqrt(np.mean(dv**2))),
        rms_spin=float(np.sqrt(np.mean(dw**2))),
        median_velocity=float(np.median(dv)),
        median_spin=float(np.median(dw)),
        rms_tangential_velocity=float(np.sqrt(np.mean(np.sum((v_out[:, :2] - v_meas[:, :2]) ** 2, axis=1)))),
        vz_ratio_data=float(np.median(v_meas[:, 2] / vz)),
        sliding_fraction=float(np.mean(sliding)),
        spin_gain_data=float(np.median(gain_data[sliding])) if np.any(sliding) else math.nan,
        spin_gain_model=float(np.median(gain_model[sliding])) if np.any(sliding) else math.nan,
    )


def fit_table_friction(flights: Flights, rep: Replay, restitution: float) -> float:
    """Friction coefficient of :class:`TableBounceModel` fitted on the measured bounces.

    Robust least squares (soft-L1) on the horizontal post-bounce velocity
    (/ :data:`BOUNCE_VELOCITY_SCALE`) and horizontal spin (/ :data:`BOUNCE_SPIN_SCALE`)
    errors, the model applied to the replay's predicted pre-bounce states with the given
    ``restitution`` (the drop-test value: the data's vertical speeds do not set it).
    """
    m = _bounce_rows(flights, rep)
    v_in, w_in, v_meas, w_meas = rep.v_in[m], rep.w_in[m], rep.v_after[m], flights.w_after[m]

    def res(x: FloatArray) -> FloatArray:
        v_out, w_out = TableBounceModel(restitution=restitution, friction=float(x[0])).bounce(v_in, w_in)
        return np.concatenate(
            [
                ((v_out - v_meas)[:, :2] / BOUNCE_VELOCITY_SCALE).ravel(),
                ((w_out - w_meas)[:, :2] / BOUNCE_SPIN_SCALE).ravel(),
            ]
        )

    sol = least_squares(res, [0.25], bounds=([0.0], [1.0]), loss="soft_l1", f_scale=1.0)
    return float(sol.x[0])


# =====================================================================================
# Noise level of the data
# =====================================================================================


def _robust_std(x: FloatArray) -> float:
    """1.4826 x the median absolute deviation."""
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


@dataclass(frozen=True, slots=True)
class NoiseLevel:
    """The data's own scatter, for scale."""

    position: float
    """Robust std of the ball-centre height at table bounces [m] (it should be r)."""
    spin: float
    """Per-state spin noise [rad/s]: robust std of the w_z change over flight + bounce / sqrt(2)."""
    velocity: float
    """Velocity noise per component [m/s], an upper bound: the value for which start-state
    noise alone (Monte Carlo, with the position and spin noise) gives the fitted
    model's median landing error of the serve flights (racket to first bounce)."""
    serve_floor: float
    """Median landing scatter of serve flights (racket to first bounce) from this noise [m]."""
    serve_bounce_floor: float
    """The same for serve flights from the first to the second bounce [m]."""
    rally_floor: float
    """The same for rally flights [m]."""
    false_net_floor: float
    """Landed flights the fitted model clears that this noise sends into the net (mean
    over the Monte Carlo draws): what a perfect model would still miscount."""


def _perturbed_landing(
    flights: Flights, model: FlightModel, v0: FloatArray, sigmas: tuple[float, float, float], rng: np.random.Generator
) -> BatchLanding:
    """Landing of the flights from start states with Gaussian noise (position, velocity, spin sigmas)."""
    p, v, w = (a + rng.normal(0.0, s, a.shape) for a, s in zip((flights.p0, v0, flights.w0), sigmas, strict=True))
    return integrate_to_table(p, v, w, model, check_net=~flights.kind_mask("net"))


def noise_level(flights: Flights, model: FlightModel, lag: float, *, draws: int = 4, seed: int = 0) -> NoiseLevel:
    """Noise figures of the data (see :class:`NoiseLevel`); Monte Carlo with ``draws`` draws."""
    m = flights.landed & np.isfinite(flights.w_after[:, 2])
    sig_p = _robust_std(flights.p_end[flights.landed, 2])
    sig_w = _robust_std(flights.w_after[m, 2] - flights.w0[m, 2]) / math.sqrt(2.0)
    rep = replay(flights, model, velocity_lag=lag)
    v0 = corrected_velocity(model, flights.v0, flights.w0, lag)
    rng = np.random.default_rng(seed)
    serve = flights.landed & flights.kind_mask("serve")
    probe = _perturbed_landing(flights, model, v0, (sig_p, 0.1, sig_w), rng)
    scatter = np.median(np.linalg.norm(probe.p[serve, :2] - rep.p_land[serve, :2], axis=1))
    sig_v = 0.1 * float(np.median(rep.landing_error[serve]) / scatter)  # the scatter is ~linear in sigma_v
    clear = flights.landed & ~rep.predicted_net & ~flights.kind_mask("net")
    flips, spread = [], []
    for _ in range(draws):
        land = _perturbed_landing(flights, model, v0, (sig_p, sig_v, sig_w), rng)
        flips.append(int(np.sum(land.net & clear)))
        spread.append(np.linalg.norm(land.p[:, :2] - rep.p_land[:, :2], axis=1))
    e = np.concatenate(spread)
    sel = {k: np.tile(flights.landed & flights.kind_mask(k), draws) for k in FIT_KINDS}
    floor = {k: float(np.nanmedian(e[m])) if np.any(m) else math.nan for k, m in sel.items()}
    return NoiseLevel(
        position=sig_p,
        spin=sig_w,
        velocity=sig_v,
        serve_floor=floor["serve"],
        serve_bounce_floor=floor["serve_bounce"],
        rally_floor=floor["rally"],
        false_net_floor=float(np.mean(flips)),
    )


# =====================================================================================
# Calibration table
# =====================================================================================

PREVIOUS_FLIGHT = FlightModel(drag_coefficient=0.45, lift_a=1.0, lift_b=2.0, spin_decay=0.008)
"""The flight model before this calibration (literature values), the "before" reference."""

PREVIOUS_TABLE = TableBounceModel(restitution=0.9052, friction=0.25)
"""The table model before this calibration (drop test with :data:`PREVIOUS_FLIGHT`, mu = 0.25)."""


@dataclass(frozen=True, slots=True)
class FlightCalibration:
    """Everything :func:`calibrate_flight` measured and fitted (figures only, no data rows)."""

    source: str
    """The data file read."""
    n_rallies: int
    """Rallies in the file."""
    n_flights: int
    """Flights with a measured landing or net touch."""
    flight_before: FlightModel
    """Reference flight model (before)."""
    fit: FlightFit
    """Flight model fitted on all flights, with the data's velocity lag."""
    table_before: TableBounceModel
    """Reference table model (before)."""
    table_after: TableBounceModel
    """Friction fitted on the bounces, restitution re-tuned to the drop test."""
    before: ReplaySummary
    """Reference models on the raw data (no lag): the figures measured before."""
    after: ReplaySummary
    """Fitted model with the velocity lag (in-sample)."""
    old_model_with_lag: ReplaySummary
    """Reference flight model with the lag correction only (attribution)."""
    new_model_without_lag: ReplaySummary
    """Fitted flight model on the raw data (attribution)."""
    shipped: ReplaySummary
    """The shipped defaults (:class:`FlightModel`, :class:`TableBounceModel`,
    :data:`VELOCITY_LAG`), not refitted: on a file they were not fitted on (another
    player's matches, your own recordings) this is their held-out validation."""
    player_cv: tuple[FoldResult, ...]
    """Leave-one-player-out folds."""
    player_cv_pooled: ReplaySummary | None
    """Pooled held-out figures of the player folds."""
    rally_cv: tuple[FoldResult, ...]
    """Folds of whole rallies."""
    rally_cv_pooled: ReplaySummary | None
    """Pooled held-out figures of the rally folds."""
    bounce_before: BounceCheck
    """Reference flight + table models, raw data."""
    bounce_after: BounceCheck
    """Fitted flight + table models, lag-corrected data."""
    drop_test_before: float
    """ITTF drop test rebound of the reference models [m]."""
    drop_test_after: float
    """ITTF drop test rebound of the fitted models [m]."""
    noise: NoiseLevel
    """The data's noise level."""


def _cv(flights: Flights, groups: Sequence[str]) -> tuple[tuple[FoldResult, ...], ReplaySummary]:
    """Cross-validate over ``groups`` and pool the held-out replays."""
    folds = cross_validate(flights, groups, reference=PREVIOUS_FLIGHT)
    return folds, summarize(flights, pooled_replay(flights, groups, folds))


def _round_fit(fit: FlightFit) -> FlightFit:
    """The fit with the parameters rounded as shipped (3 significant decimals, lag 0.1 ms)."""
    m = fit.model
    model = replace(
        m,
        drag_coefficient=round(m.drag_coefficient, 3),
        lift_a=round(m.lift_a, 3),
        lift_b=round(m.lift_b, 3),
        spin_decay=round(m.spin_decay, 4),
    )
    return replace(fit, model=model, velocity_lag=round(fit.velocity_lag, 4))


def _table_fit(flights: Flights, fit: FlightFit) -> tuple[TableBounceModel, float, float]:
    """Refitted table model and the drop test rebounds [m] before / after."""
    from studio.physics.ball_calibration import drop_test_rebound, tune_table_restitution

    rep = replay(flights, fit.model, velocity_lag=fit.velocity_lag)
    e0 = round(tune_table_restitution(fit.model, friction=PREVIOUS_TABLE.friction), 4)
    mu = round(fit_table_friction(flights, rep, e0), 3)
    e1 = round(tune_table_restitution(fit.model, friction=mu), 4)
    table = TableBounceModel(restitution=e1, friction=mu)
    return table, drop_test_rebound(PREVIOUS_TABLE, PREVIOUS_FLIGHT), drop_test_rebound(table, fit.model)


def calibrate_flight(
    path: str | os.PathLike[str] | None = None,
    *,
    folds: int = 5,
    seed: int = 0,
    player_cv: bool = True,
    rally_cv: bool = True,
) -> FlightCalibration:
    """Fit and check the flight and table models on the match data (see the module doc).

    Args:
        path: the match CSV (None: :data:`DEFAULT_MATCH_CSV`).
        folds: number of rally groups of the rally cross-validation.
        seed: seed of the rally grouping.
        player_cv, rally_cv: run the leave-one-player-out / rally cross-validations
            (each refits the model per fold, the slow part: ``docs/measured.md``).

    Raises:
        DataFileError: the file is missing or malformed.
    """
    rallies = load_match_events(path)
    flights = match_flights(rallies)
    fit = _round_fit(fit_flight_model(flights, initial=PREVIOUS_FLIGHT))
    table, drop0, drop1 = _table_fit(flights, fit)
    rep0 = replay(flights, PREVIOUS_FLIGHT, PREVIOUS_TABLE, velocity_lag=0.0)
    rep1 = replay(flights, fit.model, table, velocity_lag=fit.velocity_lag)
    pcv, pcv_pool = _cv(flights, flights.player) if player_cv else ((), None)
    rcv, rcv_pool = _cv(flights, rally_groups(flights, folds, seed)) if rally_cv else ((), None)
    return FlightCalibration(
        source=str(DEFAULT_MATCH_CSV if path is None else path),
        n_rallies=len(rallies),
        n_flights=len(flights),
        flight_before=PREVIOUS_FLIGHT,
        fit=fit,
        table_before=PREVIOUS_TABLE,
        table_after=table,
        before=summarize(flights, rep0),
        after=summarize(flights, rep1),
        old_model_with_lag=summarize(flights, replay(flights, PREVIOUS_FLIGHT, velocity_lag=fit.velocity_lag)),
        new_model_without_lag=summarize(flights, replay(flights, fit.model, velocity_lag=0.0)),
        shipped=summarize(flights, replay(flights, FlightModel(), TableBounceModel(), velocity_lag=VELOCITY_LAG)),
        player_cv=pcv,
        player_cv_pooled=pcv_pool,
        rally_cv=rcv,
        rally_cv_pooled=rcv_pool,
        bounce_before=bounce_check(flights, rep0, PREVIOUS_TABLE),
        bounce_after=bounce_check(flights, rep1, table),
        drop_test_before=drop0,
        drop_test_after=drop1,
        noise=noise_level(flights, fit.model, fit.velocity_lag),
    )


@dataclass(frozen=True, slots=True)
class CalibrationRow:
    """One row of the calibration table."""

    model: str
    """``flight``, ``table`` or ``data``."""
    data_set: str
    """Which flights/bounces (and how many)."""
    metric: str
    """What is measured, with its unit."""
    before: float
    """Reference model (before)."""
    after: float
    """Fitted model (after)."""
    noise: float
    """The data's noise level for scale (NaN if none)."""


def _summary_rows(label: str, n: ReplaySummary, b: ReplaySummary, floor: NoiseLevel | None) -> list[CalibrationRow]:
    """Rows of the landing figures of two summaries (before ``b``, after ``n``)."""
    nan = math.nan
    fl = floor or NoiseLevel(nan, nan, nan, nan, nan, nan, nan)
    rows = []
    for key, name, fnoise in (
        ("serve", "serve racket->1st bounce", fl.serve_floor),
        ("serve_bounce", "serve 1st->2nd bounce", fl.serve_bounce_floor),
        ("rally", "rally shot->bounce", fl.rally_floor),
    ):
        gb, ga = getattr(b, key), getattr(n, key)
        ds = f"{label}{name} ({ga.count})"
        rows += [
            CalibrationRow("flight", ds, "landing error median [mm]", 1e3 * gb.median, 1e3 * ga.median, 1e3 * fnoise),
            CalibrationRow("flight", ds, "landing error p90 [mm]", 1e3 * gb.p90, 1e3 * ga.p90, nan),
            CalibrationRow(
                "flight", ds, "time error median |dt| [ms]", 1e3 * gb.time_median_abs, 1e3 * ga.time_median_abs, nan
            ),
        ]
    rows.append(
        CalibrationRow(
            "flight",
            f"{label}landed flights",
            "predicted into the net [count]",
            b.false_net,
            n.false_net,
            fl.false_net_floor,
        )
    )
    rows.append(
        CalibrationRow(
            "flight",
            f"{label}measured net touches ({n.measured_net})",
            "predicted into the net [count]",
            b.measured_net_predicted,
            n.measured_net_predicted,
            nan,
        )
    )
    return rows


def _cv_rows(
    folds: Sequence[FoldResult], pooled: ReplaySummary | None, what: str, full_before: ReplaySummary
) -> list[CalibrationRow]:
    """Per-fold rally/serve medians and false nets of a cross-validation, then pooled
    (the reference model is not refitted: its pooled held-out figures are its full-data ones)."""
    nan = math.nan
    rows = []
    for f in folds:
        ds = f"{what} held out: {f.held_out}"
        for key, name in (("rally", "rally"), ("serve", "serve"), ("serve_bounce", "serve 2nd bounce")):
            gb, ga = getattr(f.before, key), getattr(f.after, key)
            rows.append(
                CalibrationRow("flight", ds, f"{name} median [mm] ({ga.count})", 1e3 * gb.median, 1e3 * ga.median, nan)
            )
        rows.append(
            CalibrationRow("flight", ds, "predicted into the net [count]", f.before.false_net, f.after.false_net, nan)
        )
    if pooled is not None and folds:
        b = full_before
        rows += [
            CalibrationRow(
                "flight", f"{what} pooled", "rally median [mm]", 1e3 * b.rally.median, 1e3 * pooled.rally.median, nan
            ),
            CalibrationRow(
                "flight", f"{what} pooled", "rally p90 [mm]", 1e3 * b.rally.p90, 1e3 * pooled.rally.p90, nan
            ),
            CalibrationRow(
                "flight", f"{what} pooled", "serve median [mm]", 1e3 * b.serve.median, 1e3 * pooled.serve.median, nan
            ),
            CalibrationRow(
                "flight",
                f"{what} pooled",
                "serve 2nd bounce median [mm]",
                1e3 * b.serve_bounce.median,
                1e3 * pooled.serve_bounce.median,
                nan,
            ),
            CalibrationRow(
                "flight", f"{what} pooled", "predicted into the net [count]", b.false_net, pooled.false_net, nan
            ),
        ]
    return rows


def _parameter_rows(res: FlightCalibration) -> list[CalibrationRow]:
    """Rows of the model parameters (before / after)."""
    nan = math.nan
    fb, fa, tb, ta = res.flight_before, res.fit.model, res.table_before, res.table_after
    return [
        CalibrationRow(
            "flight", "parameter", "drag coefficient C_D [-]", fb.drag_coefficient, fa.drag_coefficient, nan
        ),
        CalibrationRow("flight", "parameter", "lift_a [-] (C_L = S/(a + b S))", fb.lift_a, fa.lift_a, nan),
        CalibrationRow("flight", "parameter", "lift_b [-]", fb.lift_b, fa.lift_b, nan),
        CalibrationRow(
            "flight",
            "parameter",
            "C_L at S = 0.25 / 1 [-]",
            float(fb.lift_coefficient(0.25)),
            float(fa.lift_coefficient(0.25)),
            float(fa.lift_coefficient(1.0)),
        ),
        CalibrationRow(
            "flight", "parameter", "spin decay [1/m] (from w_z over bounces)", fb.spin_decay, fa.spin_decay, nan
        ),
        CalibrationRow("data", "parameter", "velocity lag of the data [ms]", 0.0, 1e3 * res.fit.velocity_lag, nan),
        CalibrationRow("table", "parameter", "friction mu [-]", tb.friction, ta.friction, nan),
        CalibrationRow("table", "parameter", "restitution e [-] (drop test)", tb.restitution, ta.restitution, nan),
    ]


def _bounce_rows_table(res: FlightCalibration) -> list[CalibrationRow]:
    """Rows of the table bounce check and the drop test."""
    b, a, nz, nan = res.bounce_before, res.bounce_after, res.noise, math.nan
    ds = f"bounces ({a.count})"
    return [
        CalibrationRow(
            "table",
            ds,
            "post-bounce velocity error RMS [m/s]",
            b.rms_velocity,
            a.rms_velocity,
            math.sqrt(3) * nz.velocity,
        ),
        CalibrationRow(
            "table", ds, "post-bounce velocity error median [m/s]", b.median_velocity, a.median_velocity, nan
        ),
        CalibrationRow(
            "table",
            ds,
            "horizontal velocity error RMS [m/s]",
            b.rms_tangential_velocity,
            a.rms_tangential_velocity,
            math.sqrt(2) * nz.velocity,
        ),
        CalibrationRow(
            "table", ds, "post-bounce spin error RMS [rad/s]", b.rms_spin, a.rms_spin, math.sqrt(3) * nz.spin
        ),
        CalibrationRow("table", ds, "post-bounce spin error median [rad/s]", b.median_spin, a.median_spin, nan),
        CalibrationRow("table", ds, "data: |v_z out| / |v_z in| median [-]", b.vz_ratio_data, a.vz_ratio_data, nan),
        CalibrationRow(
            "table", ds, "topspin gained per m/s of v_z, data [rad/s/(m/s)]", b.spin_gain_data, a.spin_gain_data, nan
        ),
        CalibrationRow(
            "table", ds, "topspin gained per m/s of v_z, model [rad/s/(m/s)]", b.spin_gain_model, a.spin_gain_model, nan
        ),
        CalibrationRow(
            "table", "ITTF drop test 30 cm", "rebound [cm]", 100 * res.drop_test_before, 100 * res.drop_test_after, nan
        ),
    ]


def calibration_rows(res: FlightCalibration) -> tuple[CalibrationRow, ...]:
    """The calibration table: parameters, landing figures (in-sample, attribution of the
    gain to the lag and to the model, cross-validated), table bounce check, noise."""
    nz = res.noise
    rows = _parameter_rows(res)
    rows += _summary_rows("", res.after, res.before, nz)
    rows += [
        CalibrationRow(
            "flight",
            "rally (old model + lag)",
            "landing error median [mm]",
            1e3 * res.before.rally.median,
            1e3 * res.old_model_with_lag.rally.median,
            math.nan,
        ),
        CalibrationRow(
            "flight",
            "rally (new model, no lag)",
            "landing error median [mm]",
            1e3 * res.before.rally.median,
            1e3 * res.new_model_without_lag.rally.median,
            math.nan,
        ),
        CalibrationRow(
            "flight",
            "landed (old model + lag)",
            "predicted into the net [count]",
            res.before.false_net,
            res.old_model_with_lag.false_net,
            math.nan,
        ),
        CalibrationRow(
            "flight",
            "landed (new model, no lag)",
            "predicted into the net [count]",
            res.before.false_net,
            res.new_model_without_lag.false_net,
            math.nan,
        ),
        CalibrationRow(
            "flight",
            "serve (shipped model, not refitted)",
            "landing error median [mm]",
            1e3 * res.before.serve.median,
            1e3 * res.shipped.serve.median,
            math.nan,
        ),
        CalibrationRow(
            "flight",
            "rally (shipped model, not refitted)",
            "landing error median [mm]",
            1e3 * res.before.rally.median,
            1e3 * res.shipped.rally.median,
            math.nan,
        ),
        CalibrationRow(
            "flight",
            "landed (shipped model, not refitted)",
            "predicted into the net [count]",
            res.before.false_net,
            res.shipped.false_net,
            math.nan,
        ),
    ]
    rows += _cv_rows(res.player_cv, res.player_cv_pooled, "player", res.before)
    rows += _cv_rows(res.rally_cv, res.rally_cv_pooled, "rally group", res.before)
    rows += _bounce_rows_table(res)
    rows += [
        CalibrationRow("data", "noise", "position (bounce height scatter) [mm]", math.nan, math.nan, 1e3 * nz.position),
        CalibrationRow("data", "noise", "velocity per component, upper bound [m/s]", math.nan, math.nan, nz.velocity),
        CalibrationRow("data", "noise", "spin per state (w_z over bounces) [rad/s]", math.nan, math.nan, nz.spin),
    ]
    return tuple(rows)


def _fmt(x: float) -> str:
    """A table cell: 4 significant digits, '-' for NaN."""
    if not math.isfinite(x):
        return "-"
    return f"{x:.0f}" if abs(x) >= 1000 or (x == int(x) and abs(x) < 1000 and abs(x) >= 10) else f"{x:.4g}"


def format_flight_table(res: FlightCalibration) -> str:
    """The calibration table as aligned text (model, data set, metric, before, after, noise)."""
    head = ("model", "data set", "metric", "before", "after", "noise")
    body = [
        (r.model, r.data_set, r.metric, _fmt(r.before), _fmt(r.after), _fmt(r.noise)) for r in calibration_rows(res)
    ]
    width = [max(len(row[i]) for row in [head, *body]) for i in range(6)]

    def line(row: tuple[str, ...]) -> str:
        return "  ".join(c.ljust(w) if i < 3 else c.rjust(w) for i, (c, w) in enumerate(zip(row, width, strict=True)))

    title = (
        f"Flight/table calibration on {res.source}: {res.n_rallies} rallies, {res.n_flights} flights. "
        f"Before: previous models on the raw data; after: fitted models, velocities lag-corrected by "
        f"{1e3 * res.fit.velocity_lag:.1f} ms; noise: the data's own scatter or what it alone explains."
    )
    return "\n".join([title, line(head), line(tuple("-" * w for w in width)), *(line(b) for b in body)])


# =====================================================================================
# Record and entry point
# =====================================================================================


def _json_number(x: float) -> float | None:
    """A finite float rounded to 6 significant digits, None for NaN."""
    return float(f"{x:.6g}") if math.isfinite(x) else None


def flight_record(res: FlightCalibration) -> dict[str, object]:
    """JSON-ready record of the fitted parameters and the calibration table (no data rows)."""
    m, t = res.fit.model, res.table_after
    return {
        "schema": 1,
        "source": SOURCE,
        "data_file": Path(res.source).name,
        "rallies": res.n_rallies,
        "flights": res.n_flights,
        "flight_model": {
            "drag_coefficient": m.drag_coefficient,
            "lift_a": m.lift_a,
            "lift_b": m.lift_b,
            "spin_decay": m.spin_decay,
        },
        "table_model": {"restitution": t.restitution, "friction": t.friction},
        "data_velocity_lag_s": res.fit.velocity_lag,
        "fit": {
            "loss": "soft_l1",
            "f_scale_m": FIT_SCALE,
            "time_weight_m_per_s": TIME_WEIGHT,
            "flight_kinds": list(FIT_KINDS),
            "cost": _json_number(res.fit.cost),
            "flights_fitted": res.fit.n_flights,
        },
        "player_cv_parameters": {
            f.held_out: {
                "drag_coefficient": _json_number(f.fit.model.drag_coefficient),
                "lift_a": _json_number(f.fit.model.lift_a),
                "lift_b": _json_number(f.fit.model.lift_b),
                "spin_decay": _json_number(f.fit.model.spin_decay),
                "velocity_lag_s": _json_number(f.fit.velocity_lag),
            }
            for f in res.player_cv
        },
        "table": [
            {
                "model": r.model,
                "data_set": r.data_set,
                "metric": r.metric,
                "before": _json_number(r.before),
                "after": _json_number(r.after),
                "noise": _json_number(r.noise),
            }
            for r in calibration_rows(res)
        ],
    }


def write_flight_json(res: FlightCalibration, path: Path = FLIGHT_MODEL_JSON) -> None:
    """Write :func:`flight_record` to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".json")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(flight_record(res), fh, indent=2)
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
