"""ITTF service legality chain (Law 2.6) with the paper's penalties.

The paper ("Optimizing serve parameters") checks a simulated serve with a sequential
chain, each check more restrictive than the one before, and assigns the shaping term
``s_leg`` of the first failing check: non-racket robot contact (-5), more than one racket
contact (-4), fewer than two table bounces (-3), first bounce on the wrong side (-2.5),
net collision (-2), second bounce on the wrong side (-1.5), bounce too close to an edge
(-0.5), insufficient net clearance (-0.3) and, optionally, the robot not at rest by the
opponent-side bounce (-0.1).

On top of the paper's chain this module checks the toss conditions of ITTF Law 2.6,
placed right after the robot-contact check (they concern what happens before the
strike, and their penalties keep the chain's order of severity):

- ``missed``: the racket never touches the ball (-4.6; added here: without it, a missed
  ball falling twice on the server's side would only cost -1.5);
- ``toss_rise``: the ball rises at least 16 cm after leaving the cup (2.6.2, -4.5);
- ``touched_before_strike``: it touches nothing before it is struck (2.6.2, -4.4);
- ``struck_rising``: it is struck while falling (2.6.3, -4.3);
- ``behind_end_line`` / ``above_surface``: from release until struck it stays behind the
  server's end line and above the level of the playing surface (2.6.4, -4.2 / -4.1).

Every check is evaluated (so a GUI can show the full checklist); the verdict is the first
failing one in chain order. Thresholds are documented fields of :class:`RuleParams`.
World frame of ``DESIGN.md``: the server (robot) plays from x < 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.physics.court import DEFAULT_COURT, Court

ContactKind = Literal["racket", "robot", "table", "net", "post", "floor"]


class ContactLike(Protocol):
    """Any ball contact record: :class:`studio.physics.ball.Event` and rollout contacts qualify."""

    @property
    def kind(self) -> str: ...

    @property
    def t(self) -> float: ...

    @property
    def p(self) -> npt.NDArray[np.float64]: ...


@dataclass(frozen=True, slots=True)
class RuleParams:
    """Thresholds of the legality chain."""

    edge_margin: float = 0.03
    """Minimal distance [m] of a bounce point from the nearest table edge (end or side
    line). The paper names the check but not the value; 3 cm keeps serves robust to the
    toss spread (~1 cm) and the impact model error."""
    min_net_clearance: float = 0.02
    """Minimal gap [m] between the ball's bottom and the net top when the ball crosses the
    net plane. The paper names the check but not the value."""
    min_toss_rise: float = C.TOSS_MIN_RISE
    """Minimal rise of the ball above the release point [m]: ITTF Law 2.6.2 (16 cm)."""
    check_robot_rest: bool = False
    """Enable the paper's optional check that the robot is at rest by the time of the
    opponent-side bounce."""


@dataclass(frozen=True, slots=True)
class Check:
    """One check of the chain, evaluated."""

    name: str
    """Stable identifier (used in JSON output and tests)."""
    label: str
    """Human-readable description for checklists."""
    penalty: float
    """Shaping term s_leg if this is the first failing check (negative)."""
    passed: bool
    """Whether the serve passes this check."""
    detail: str
    """Measured value behind the verdict, for display."""


@dataclass(frozen=True, slots=True)
class LegalityReport:
    """All checks in chain order and the verdict."""

    checks: tuple[Check, ...]
    """Every check of the chain, in order."""

    @property
    def first_failure(self) -> Check | None:
        """The first failing check in chain order, or None if the serve is legal."""
        return next((c for c in self.checks if not c.passed), None)

    @property
    def legal(self) -> bool:
        """True when every check passes."""
        return self.first_failure is None

    @property
    def penalty(self) -> float:
        """The shaping term s_leg: the first failure's penalty, 0 when legal."""
        failure = self.first_failure
        return 0.0 if failure is None else failure.penalty


@dataclass(frozen=True, slots=True)
class ServeOutcome:
    """What the rules need to know about one simulated serve (world frame, SI units)."""

    t: npt.NDArray[np.float64]
    """Ball path times (N,) [s], from toss release (or earlier) to the end of the serve."""
    p: npt.NDArray[np.float64]
    """Ball centre positions (N, 3) [m]."""
    contacts: tuple[ContactLike, ...]
    """Ball contacts in time order (racket, robot, table, net, post, floor)."""
    release_t: float
    """Time the ball left the cup [s]."""
    release_z: float
    """Ball centre height at release [m]."""
    robot_rest_t: float | None = None
    """Time the robot is back at rest [s], if known (for the optional rest check)."""


def net_crossing(
    t: npt.NDArray[np.float64], p: npt.NDArray[np.float64]
) -> tuple[float, npt.NDArray[np.float64]] | None:
    """First crossing of the net plane x = 0 from the server's side: (time [s], position (3,)).

    Linear interpolation between samples; None if the ball never crosses.
    """
    x = p[:, 0]
    idx = np.nonzero((x[:-1] < 0.0) & (x[1:] >= 0.0))[0]
    if idx.size == 0:
        return None
    i = int(idx[0])
    a = -x[i] / (x[i + 1] - x[i])
    return float(t[i] + a * (t[i + 1] - t[i])), p[i] + a * (p[i + 1] - p[i])


LABELS: dict[str, tuple[str, float]] = {
    "robot_contact": ("no robot body other than the racket touches the ball", -5.0),
    "missed": ("the racket strikes the ball", -4.6),
    "toss_rise": ("toss rises at least 16 cm (2.6.2)", -4.5),
    "touched_before_strike": ("ball touches nothing before it is struck (2.6.2)", -4.4),
    "struck_rising": ("ball is struck while falling (2.6.3)", -4.3),
    "behind_end_line": ("ball stays behind the end line until struck (2.6.4)", -4.2),
    "above_surface": ("ball stays above the playing surface until struck (2.6.4)", -4.1),
    "multiple_racket_contacts": ("only one racket contact", -4.0),
    "two_bounces": ("at least two table bounces", -3.0),
    "first_bounce_side": ("first bounce on the server's court (2.6.3)", -2.5),
    "net": ("ball does not touch the net assembly", -2.0),
    "second_bounce_side": ("second bounce on the receiver's court (2.6.3)", -1.5),
    "edge_margin": ("bounces not too close to an edge", -0.5),
    "net_clearance": ("sufficient net clearance", -0.3),
    "robot_rest": ("robot at rest by the opponent-side bounce", -0.1),
}
"""Check name -> (label, penalty), in chain order."""


def check_serve(
    outcome: ServeOutcome, *, params: RuleParams = RuleParams(), court: Court = DEFAULT_COURT
) -> LegalityReport:
    """Evaluate the whole legality chain on one simulated serve."""
    t, p = np.asarray(outcome.t, dtype=float), np.asarray(outcome.p, dtype=float)
    contacts = tuple(sorted(outcome.contacts, key=lambda c: c.t))
    racket = [c for c in contacts if c.kind == "racket"]
    strike_t = racket[0].t if racket else None
    results: dict[str, tuple[bool, str]] = {}

    robot = [c for c in contacts if c.kind == "robot"]
    results["robot_contact"] = (not robot, f"robot contact at t={robot[0].t:.3f} s" if robot else "none")
    results["missed"] = (bool(racket), f"struck at t={strike_t:.3f} s" if strike_t is not None else "no racket contact")

    # Toss phase: from release to the strike (or to the end if never struck).
    t_end = strike_t if strike_t is not None else float(t[-1])
    toss = (t >= outcome.release_t) & (t <= t_end)
    z_toss = p[toss, 2] if np.any(toss) else np.array([outcome.release_z])
    rise = float(np.max(z_toss) - outcome.release_z)
    results["toss_rise"] = (rise >= params.min_toss_rise - 1e-9, f"rise {100 * rise:.1f} cm")
    before = [c for c in contacts if c.kind != "racket" and c.t < t_end and c.t >= outcome.release_t]
    results["touched_before_strike"] = (
        not before,
        f"{before[0].kind} at t={before[0].t:.3f} s" if before else "nothing",
    )
    if strike_t is not None:
        v_before = getattr(racket[0], "v_before", None)
        vz = float(v_before[2]) if v_before is not None else _velocity_z_at(t, p, strike_t)
        results["struck_rising"] = (vz <= 0.0, f"v_z at strike {vz:+.2f} m/s")
    else:
        results["struck_rising"] = (True, "not struck")
    x_max = float(np.max(p[toss, 0])) if np.any(toss) else float("-inf")
    results["behind_end_line"] = (
        x_max + C.BALL_RADIUS <= court.server_end_line_x,
        f"front of ball at x={x_max + C.BALL_RADIUS:+.3f} m (end line {court.server_end_line_x:+.3f})",
    )
    z_min = float(np.min(z_toss)) - C.BALL_RADIUS
    results["above_surface"] = (z_min >= 0.0, f"lowest ball point z={z_min:+.3f} m")

    results["multiple_racket_contacts"] = (len(racket) <= 1, f"{len(racket)} racket contact(s)")

    after = [c for c in contacts if strike_t is not None and c.t > strike_t]
    # A hit on the vertical side of the table top ("side") is not on the playing surface.
    bounces = [c for c in after if c.kind == "table" and getattr(c, "part", "top") != "side"]
    results["two_bounces"] = (len(bounces) >= 2, f"{len(bounces)} table bounce(s) after the strike")
    b1 = bounces[0] if bounces else None
    results["first_bounce_side"] = (
        b1 is not None and b1.p[0] < 0.0,
        f"x={b1.p[0]:+.3f} m" if b1 is not None else "no bounce",
    )
    net_hits = [c for c in after if c.kind in ("net", "post")]
    results["net"] = (
        not net_hits,
        f"{getattr(net_hits[0], 'part', net_hits[0].kind)} at t={net_hits[0].t:.3f} s" if net_hits else "clear",
    )
    b2 = bounces[1] if len(bounces) > 1 else None
    results["second_bounce_side"] = (
        b2 is not None and b2.p[0] > 0.0,
        f"x={b2.p[0]:+.3f} m" if b2 is not None else "no second bounce",
    )
    margins = [float(court.edge_distance(c.p[:2])) for c in bounces[:2]]
    results["edge_margin"] = (
        bool(margins) and min(margins) >= params.edge_margin,
        f"closest {100 * min(margins):.1f} cm from an edge" if margins else "no bounce",
    )
    clearance = serve_net_clearance(t, p, after_t=strike_t, court=court)
    results["net_clearance"] = (
        clearance is not None and clearance >= params.min_net_clearance,
        f"{100 * clearance:.1f} cm" if clearance is not None else "never crosses the net",
    )
    if params.check_robot_rest:
        rest_ok = outcome.robot_rest_t is not None and b2 is not None and outcome.robot_rest_t <= b2.t
        results["robot_rest"] = (rest_ok, f"rest at {outcome.robot_rest_t}")

    checks = tuple(
        Check(name, LABELS[name][0], LABELS[name][1], bool(results[name][0]), results[name][1])
        for name in LABELS
        if name in results
    )
    return LegalityReport(checks)


def serve_net_clearance(
    t: npt.NDArray[np.float64],
    p: npt.NDArray[np.float64],
    *,
    after_t: float | None = None,
    court: Court = DEFAULT_COURT,
) -> float | None:
    """Gap [m] between the ball's bottom and the net top at the first net-plane crossing
    after ``after_t``; negative if the ball passes below the net top. None if no crossing."""
    mask = np.ones(len(t), bool) if after_t is None else np.asarray(t) >= after_t
    crossing = net_crossing(np.asarray(t)[mask], np.asarray(p)[mask])
    if crossing is None:
        return None
    return float(crossing[1][2] - C.BALL_RADIUS - court.net_height)


def _velocity_z_at(t: npt.NDArray[np.float64], p: npt.NDArray[np.float64], t_query: float) -> float:
    """Ball vertical velocity just before ``t_query`` from the sampled path [m/s]."""
    i = int(np.searchsorted(t, t_query)) - 1
    i = max(1, min(i, len(t) - 1))
    return float((p[i, 2] - p[i - 1, 2]) / (t[i] - t[i - 1]))


def contacts_of_kind(contacts: Sequence[ContactLike], kind: str) -> list[ContactLike]:
    """The contacts of one kind, in time order."""
    return sorted((c for c in contacts if c.kind == kind), key=lambda c: c.t)
