"""Reference serves for the dashboard: real players' and the Ace robot's serves at the net.

A match file in the Ace public format (``player_id, rally_id, type, timestamp, ball_pos,
ball_vel_out, ball_spin_out``; read with the project's loader,
:func:`studio.physics.flight_calibration.load_match_events`) holds for every rally its
first event, the serve: ``shot_p1`` a robot serve (from x < 0, towards +X, as the
studio's), ``shot_p2`` a human serve (from x > 0, towards -X), with the ball's measured
state just after the racket. Each serve is flown from that state to the net crossing with
the project's flight, table-bounce and net models (:func:`studio.physics.ball.simulate`,
the models every studio evaluation uses), its measured velocity lag-corrected as in the
flight calibration (:func:`~studio.physics.flight_calibration.corrected_velocity`,
:data:`~studio.physics.flight_calibration.VELOCITY_LAG`). The flight goes through the net
plane as if the net were not there (as the calibration's replay does): a low real serve
that the model sends into the net (about a quarter of the human serves of the
development file, whose real flights cleared it by 1-2 cm) keeps its state at the net
plane and is flagged ``touches_net`` (its clearance < 0). A human serve is first turned
by 180 degrees about the vertical axis (x, y -> -x, -y for position, velocity and spin):
the table is symmetric under that turn and the velocity-aligned spin components do not
change, so both kinds are compared with the library in the studio's frame.

The result is the same net-crossing state the library stores
(:class:`studio.library.selection.NetState`: horizontal speed [m/s], spin and its
components [rad/s], clearance [m]). The file is only read (it is not the project's to
ship); nothing derived from it is written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pandas as pd

from studio.library.selection import NetState, net_state
from studio.physics.ball import (
    DEFAULT_FLIGHT,
    DEFAULT_TABLE,
    BallState,
    FlightModel,
    TableBounceModel,
    simulate,
)
from studio.physics.court import DEFAULT_COURT
from studio.physics.flight_calibration import (
    VELOCITY_LAG,
    corrected_velocity,
    load_match_events,
)
from studio.serve.evaluate import ball_metrics

ROBOT, HUMAN = "robot", "human"
"""Who served: the Ace robot (``shot_p1``) or the human player (``shot_p2``)."""

SERVE_KINDS = {"shot_p1": ROBOT, "shot_p2": HUMAN}
"""A rally's first event kind -> who served."""

COLUMNS = ("who", "player", "rally", "speed_h", "spin", "topspin", "sidespin", "cork", "clearance", "touches_net")
"""Columns of :attr:`ReferenceServes.table` (speeds [m/s], spins [rad/s], clearance [m],
``touches_net``: the model's flight touches the net)."""

FLIGHT_TIME = 1.5
"""Longest flight followed from the racket [s] (a serve reaches the net in ~0.3-0.6 s)."""

NETLESS_COURT = replace(DEFAULT_COURT, net_height=1e-6)
"""The court with a 1 um net: the ball flies through the net plane (the real net's
clearance is still measured against :data:`DEFAULT_COURT`)."""

HALF_TURN = np.diag([-1.0, -1.0, 1.0])
"""180-degree turn about +Z: a human serve (towards -X) seen as the robot's (towards +X)."""


@dataclass(frozen=True)
class ReferenceServes:
    """The reference serves of one match file at the net crossing."""

    path: Path
    """The match file read."""
    table: pd.DataFrame
    """One row per serve that crosses the net in the model (columns :data:`COLUMNS`)."""
    serves: dict[str, int]
    """Serves found per :data:`ROBOT` / :data:`HUMAN` (crossing the net or not)."""
    no_crossing: dict[str, int]
    """Serves per who that do not reach the net plane in the model (not drawn)."""

    def of(self, who: str) -> pd.DataFrame:
        """The rows of :data:`ROBOT` or :data:`HUMAN`."""
        return self.table[self.table["who"] == who].reset_index(drop=True)

    def summary(self) -> str:
        """One Markdown sentence: how many of each, and how many did not cross."""
        parts = []
        for who in (ROBOT, HUMAN):
            n, miss = self.serves.get(who, 0), self.no_crossing.get(who, 0)
            touch = int(self.of(who)["touches_net"].sum()) if len(self.table) else 0
            notes = [
                f"{touch} touch the net in the model" if touch else "",
                f"{miss} never reach the net plane (not drawn)" if miss else "",
            ]
            notes = [x for x in notes if x]
            parts.append(f"{n} {who} serves" + (f" ({'; '.join(notes)})" if notes else ""))
        return (
            f"Reference: {' and '.join(parts)} from `{self.path.name}` (Ace public match format), "
            "each flown from its measured state after the racket to the net plane with the project's flight model."
        )


def serve_state(
    who: str,
    p: npt.ArrayLike,
    v: npt.ArrayLike,
    w: npt.ArrayLike,
    *,
    flight: FlightModel = DEFAULT_FLIGHT,
    lag: float = VELOCITY_LAG,
) -> BallState:
    """The ball just after the racket in the studio's frame: velocity lag-corrected,
    a human serve turned by 180 degrees about +Z (position [m], velocity [m/s], spin [rad/s])."""
    pos: npt.NDArray[np.float64] = np.asarray(p, dtype=float)
    spin: npt.NDArray[np.float64] = np.asarray(w, dtype=float)
    vel = corrected_velocity(flight, np.asarray(v, dtype=float), spin, lag)
    if who == HUMAN:
        pos, vel, spin = HALF_TURN @ pos, HALF_TURN @ vel, HALF_TURN @ spin
    return BallState(pos, vel, spin)


def fly_to_net(
    state: BallState, *, flight: FlightModel = DEFAULT_FLIGHT, table: TableBounceModel = DEFAULT_TABLE
) -> NetState | None:
    """The ball at its first crossing of the net plane towards +X (through the net, see
    :data:`NETLESS_COURT`), None if it never gets there."""
    traj = simulate(state, FLIGHT_TIME, flight=flight, table=table, court=NETLESS_COURT, max_table_bounces=2)
    m = ball_metrics(traj, strike_t=-1.0)  # every contact is after the start
    return net_state({"net": m.net}) if m.net is not None else None


def reference_serves(path: str | os.PathLike[str], *, flight: FlightModel = DEFAULT_FLIGHT) -> ReferenceServes:
    """Every serve of a match file at the net crossing (DataFileError names a bad line)."""
    path = Path(path)
    rows: list[dict[str, object]] = []
    serves = {ROBOT: 0, HUMAN: 0}
    missed = {ROBOT: 0, HUMAN: 0}
    for rally in load_match_events(path):
        first = rally.events[0]
        who = SERVE_KINDS.get(first.kind)
        if who is None:
            continue
        serves[who] += 1
        net = fly_to_net(serve_state(who, first.p, first.v, first.w, flight=flight), flight=flight)
        if net is None:
            missed[who] += 1
            continue
        rows.append({"who": who, "player": rally.player, "rally": rally.rally_id, "speed_h": net.speed_h, "spin": net.spin,
                     "topspin": net.topspin, "sidespin": net.sidespin, "cork": net.cork, "clearance": net.clearance,
                     "touches_net": bool(net.clearance < 0.0)})  # fmt: skip
    return ReferenceServes(
        path=path, table=pd.DataFrame(rows, columns=list(COLUMNS)), serves=serves, no_crossing=missed
    )


_CACHE: dict[tuple[str, int, int], ReferenceServes] = {}


def cached_reference_serves(path: str | os.PathLike[str]) -> ReferenceServes:
    """:func:`reference_serves` of ``path``, computed once per file version (path, size,
    modification time): each dashboard session reuses it."""
    p = Path(path).resolve()
    st = p.stat()
    key = (str(p), st.st_size, st.st_mtime_ns)
    if key not in _CACHE:
        _CACHE[key] = reference_serves(p)
    return _CACHE[key]
