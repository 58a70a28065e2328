"""Legality chain: each check fires, in order, on crafted ball trajectories."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import pytest

from studio.serve.rules import LABELS, RuleParams, ServeOutcome, check_serve, net_crossing, serve_net_clearance


@dataclass(frozen=True)
class C:
    kind: str
    t: float
    p: npt.NDArray[np.float64]
    v_before: npt.NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    part: str = "top"


def path(points: list[tuple[float, float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-linear ball path through (t, x, y, z) knots, sampled at 1 ms."""
    k = np.array(points)
    t = np.arange(k[0, 0], k[-1, 0] + 1e-9, 1e-3)
    p = np.stack([np.interp(t, k[:, 0], k[:, i]) for i in (1, 2, 3)], axis=1)
    return t, p


def good() -> tuple[ServeOutcome, dict]:
    knots = [
        (0.00, -1.60, 0.0, 0.10),  # release
        (0.30, -1.60, 0.0, 0.45),  # apex 35 cm above release
        (0.60, -1.60, 0.0, 0.25),  # strike (falling)
        (0.80, -0.60, 0.1, 0.02),  # first bounce, server side
        (1.00, 0.00, 0.2, 0.22),  # over the net: 22 cm - 2 cm radius = 5 cm above the net top
        (1.20, 0.80, 0.3, 0.02),  # second bounce, receiver side
        (1.40, 1.50, 0.3, 0.20),
    ]
    t, p = path(knots)
    contacts = [
        C("racket", 0.60, np.array([-1.60, 0.0, 0.25])),
        C("table", 0.80, np.array([-0.60, 0.1, 0.02])),
        C("table", 1.20, np.array([0.80, 0.3, 0.02])),
    ]
    return ServeOutcome(t=t, p=p, contacts=tuple(contacts), release_t=0.0, release_z=0.10), {"knots": knots}


def with_contacts(o: ServeOutcome, contacts: list[C], **kw) -> ServeOutcome:  # type: ignore[no-untyped-def]
    return ServeOutcome(t=kw.get("t", o.t), p=kw.get("p", o.p), contacts=tuple(contacts), release_t=o.release_t, release_z=kw.get("release_z", o.release_z))


def test_good_serve_is_legal() -> None:
    o, _ = good()
    report = check_serve(o)
    assert report.legal and report.penalty == 0.0
    assert all(type(c.passed) is bool for c in report.checks)  # JSON-serializable verdicts
    assert [c.name for c in report.checks] == [n for n in LABELS if n != "robot_rest"]
    assert serve_net_clearance(o.t, o.p) == pytest.approx(0.22 - 0.02 - 0.1525, abs=1e-3)


def test_penalties_follow_the_paper_and_decrease() -> None:
    penalties = [pen for _, pen in LABELS.values()]
    assert penalties == sorted(penalties)  # each check is milder than the one before
    assert LABELS["robot_contact"][1] == -5 and LABELS["multiple_racket_contacts"][1] == -4
    assert LABELS["two_bounces"][1] == -3 and LABELS["first_bounce_side"][1] == -2.5
    assert LABELS["net"][1] == -2 and LABELS["second_bounce_side"][1] == -1.5
    assert LABELS["edge_margin"][1] == -0.5 and LABELS["net_clearance"][1] == -0.3
    assert LABELS["robot_rest"][1] == -0.1


def _fails(o: ServeOutcome, name: str, **kw) -> None:  # type: ignore[no-untyped-def]
    report = check_serve(o, **kw)
    assert report.first_failure is not None and report.first_failure.name == name, report.first_failure
    assert report.penalty == LABELS[name][1]


def test_each_check_fires() -> None:
    o, _ = good()
    r, b1, b2 = o.contacts
    _fails(with_contacts(o, [C("robot", 0.59, np.array([-1.6, 0, 0.3])), r, b1, b2]), "robot_contact")
    _fails(with_contacts(o, [b1, b2]), "missed")
    _fails(with_contacts(o, list(o.contacts), release_z=0.35), "toss_rise")
    _fails(with_contacts(o, [C("table", 0.5, np.array([-1.3, 0, 0.02])), r, b1, b2]), "touched_before_strike")
    rising = C("racket", 0.60, r.p, v_before=np.array([0.0, 0.0, 0.5]))
    _fails(with_contacts(o, [rising, b1, b2]), "struck_rising")
    t, p = path([(0, -1.6, 0, 0.1), (0.3, -1.2, 0, 0.45), (0.6, -1.3, 0, 0.25), (1.4, 1.5, 0.3, 0.2)])
    _fails(with_contacts(o, list(o.contacts), t=t, p=p), "behind_end_line")
    t, p = path([(0, -1.6, 0, 0.1), (0.3, -1.6, 0, 0.45), (0.55, -1.6, 0, 0.01), (0.6, -1.6, 0, 0.25), (1.4, 1.5, 0.3, 0.2)])
    _fails(with_contacts(o, list(o.contacts), t=t, p=p), "above_surface")
    _fails(with_contacts(o, [r, C("racket", 0.62, r.p), b1, b2]), "multiple_racket_contacts")
    _fails(with_contacts(o, [r, b1]), "two_bounces")
    # a hit on the vertical side of the table top is not a bounce on the playing surface
    _fails(with_contacts(o, [r, b1, C("table", 1.2, np.array([1.38, 0.3, -0.01]), part="side")]), "two_bounces")
    _fails(with_contacts(o, [r, C("table", 0.8, np.array([0.5, 0, 0.02])), b2]), "first_bounce_side")
    _fails(with_contacts(o, [r, b1, C("net", 1.0, np.array([0, 0.2, 0.1])), b2]), "net")
    _fails(with_contacts(o, [r, b1, C("table", 1.2, np.array([-0.2, 0.3, 0.02]))]), "second_bounce_side")
    _fails(with_contacts(o, [r, b1, C("table", 1.2, np.array([1.36, 0.3, 0.02]))]), "edge_margin")
    t, p = path([(0, -1.6, 0, 0.1), (0.3, -1.6, 0, 0.45), (0.6, -1.6, 0, 0.25), (1.0, 0.0, 0.2, 0.18), (1.4, 1.5, 0.3, 0.2)])
    _fails(with_contacts(o, list(o.contacts), t=t, p=p), "net_clearance")
    # optional rest check only when enabled
    assert check_serve(o).legal
    _fails(o, "robot_rest", params=RuleParams(check_robot_rest=True))


def test_chain_order_first_failure_wins() -> None:
    o, _ = good()
    r, b1, _ = o.contacts
    # both a robot contact and a missing second bounce: robot contact is reported
    bad = with_contacts(o, [C("robot", 0.5, r.p), r, b1])
    report = check_serve(bad)
    assert report.first_failure is not None and report.first_failure.name == "robot_contact"
    failing = [c.name for c in report.checks if not c.passed]
    assert failing[:2] == ["robot_contact", "touched_before_strike"] and "two_bounces" in failing


def test_net_crossing_interpolates() -> None:
    t = np.array([0.0, 1.0])
    p = np.array([[-1.0, 0.0, 0.3], [1.0, 0.0, 0.1]])
    tc, pc = net_crossing(t, p)  # type: ignore[misc]
    assert tc == pytest.approx(0.5) and pc[2] == pytest.approx(0.2)
    assert net_crossing(t, p[::-1]) is None
