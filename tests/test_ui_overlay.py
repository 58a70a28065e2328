"""The overlay's numbers (studio.ui.overlay) are the evaluation's, legal or not, beside the pin."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import pytest

from studio.paths import example_serves_dir
from studio.serve.efforts import effort_report
from studio.serve.evaluate import EvaluationContext, evaluate_serve
from studio.serve.params import load_serve
from studio.ui.overlay import (
    overlay_markdown,
    serve_numbers,
    sidespin_text,
    topspin_text,
)


@pytest.fixture(scope="module")
def context() -> EvaluationContext:
    return EvaluationContext.default()


def _row(table: str, label: str) -> list[str]:
    line = next(x for x in table.splitlines() if x.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split("|")][1:]


def test_numbers_of_a_legal_serve_are_the_evaluations(context: EvaluationContext) -> None:
    ev = evaluate_serve(load_serve(example_serves_dir() / "topspin_right.json"), context)
    efforts = effort_report(ev.motion, context.robot)
    n = serve_numbers(ev, efforts)
    m = ev.metrics
    assert ev.legal and n.verdict == "LEGAL" and n.failing is None
    assert n.reward == ev.reward.total
    assert (n.net_speed, n.net_topspin, n.net_sidespin) == (m.net["speed"], m.net["topspin"], m.net["sidespin"])
    assert (n.bounce2_topspin, n.bounce2_sidespin) == (m.second_bounce["topspin"], m.second_bounce["sidespin"])
    assert n.clearance == m.net_clearance
    table = overlay_markdown(n)
    assert _row(table, "verdict") == ["**LEGAL**"] and _row(table, "first failing check") == ["none"]
    assert _row(table, "reward F") == [f"{ev.reward.total:+.3f}"]
    assert _row(table, "net: speed") == [f"{m.net['speed']:.2f} m/s"]
    assert _row(table, "net: top/back") == [f"topspin {m.net['topspin']:.0f} rad/s"] and m.net["topspin"] > 50  # the example's topspin
    assert _row(table, "net: side") == [f"{m.net['sidespin']:+.0f} rad/s"]
    assert _row(table, "2nd bounce: top/back") == [topspin_text(m.second_bounce["topspin"])]
    assert _row(table, "2nd bounce: side") == [sidespin_text(m.second_bounce["sidespin"])]
    assert _row(table, "net clearance") == [f"{100 * m.net_clearance:.1f} cm"]
    assert _row(table, "joint efforts")[0].startswith("within" if efforts.within else "EXCEED")


def test_an_illegal_serve_names_its_first_failing_check_beside_the_pinned_legal_one(context: EvaluationContext) -> None:
    legal = evaluate_serve(load_serve(example_serves_dir() / "topspin_right.json"), context)
    serve = legal.serve
    broken = replace(serve, params=replace(serve.params, velocity=(serve.params.velocity[0], serve.params.velocity[1], 4.5), roll=math.radians(60.0)))
    ev = evaluate_serve(broken, context)
    assert not ev.legal
    n = serve_numbers(ev)
    failure = ev.legality.first_failure if ev.legality is not None else None
    if failure is not None:
        assert n.verdict == "ILLEGAL" and n.failing.startswith(failure.label)
    else:  # no ball simulated: the planner or the collision check stopped it
        assert n.verdict in ("NO PLAN", "COLLISION") and n.failing
    table = overlay_markdown(n, serve_numbers(legal))
    assert table.splitlines()[0] == "| | now | pinned A |"
    verdicts = _row(table, "verdict")
    assert verdicts[0] == f"**{n.verdict}**" and verdicts[1] == "**LEGAL**"
    assert _row(table, "net: speed")[1] == f"{legal.metrics.net['speed']:.2f} m/s"
    assert _row(table, "reward F") == [f"{ev.reward.total:+.3f}", f"{legal.reward.total:+.3f}"]
    assert re.search(r"\| first failing check \| .+ \| none \|", table)


def test_spin_words() -> None:
    assert topspin_text(117.6) == "topspin 118 rad/s" and topspin_text(-264.4) == "backspin 264 rad/s" and topspin_text(None) == "-"
    assert sidespin_text(-75.5) == "-76 rad/s" and sidespin_text(None) == "-"
