"""Collision checker (studio.robot.collision): robot vs itself, table, net, posts, legs, floor."""

from __future__ import annotations

import numpy as np
import pytest

from studio.robot.collision import CollisionChecker
from studio.errors import InvalidInputError
from studio.planning.planner import StrikePlanner
from studio.planning.strike import StrikeStart, StrikeTarget
from studio.robot.model import load_robot


@pytest.fixture(scope="module")
def robot():  # type: ignore[no-untyped-def]
    return load_robot()


@pytest.fixture(scope="module")
def checker(robot):  # type: ignore[no-untyped-def]
    return CollisionChecker(robot)


def test_named_poses_are_collision_free(robot, checker) -> None:  # type: ignore[no-untyped-def]
    for q in (robot.q_rest, robot.q_flat):
        assert checker.colliding_pairs(q) == ()
        assert checker.min_distance(q) > 0.0
    t = np.arange(50) * 1e-3
    rep = checker.check(t, np.linspace(robot.q_rest, robot.q_flat, 50))
    assert not rep.collides and rep.samples_checked == 50 and "collision-free" in rep.describe()


def test_pairs_skip_adjacent_links_and_static_parts(checker) -> None:  # type: ignore[no-untyped-def]
    names = set(checker.names)
    assert {"table_top", "net", "net_post_left", "floor", "table_leg_0"} <= names
    pairs = {(checker.names[i], checker.names[j]) for i, j in checker._pairs}
    assert ("link_1_0", "link_2_0") not in pairs  # a2 joins link_1 and link_2
    assert ("gantry_base_0", "floor") not in pairs  # rails on the floor: both static
    assert any(a.startswith("racket") and b == "table_top" for a, b in pairs)
    assert any(a.startswith("racket") and b.startswith("link_4") for a, b in pairs) or any(
        b.startswith("racket") and a.startswith("link_4") for a, b in pairs
    )


def test_plan_into_the_table_is_caught(robot, checker) -> None:  # type: ignore[no-untyped-def]
    planner = StrikePlanner(robot)
    start = StrikeStart.at_rest(robot.q_flat)
    # Racket centre 3 cm below the playing surface, 17 cm inside the end line.
    into = StrikeTarget(tau=0.4, position=[-1.2, 0.0, -0.03], normal=[0, 0, 1], velocity=[0, 0, 0], tau_f=1.0)
    plan = planner.plan(start, into)
    assert plan.ok  # the planner itself does not know the table
    rep = checker.check(plan.t, plan.q)
    assert rep.collides and rep.time is not None and 0.0 < rep.time <= 0.4 + 1e-9
    assert any("table_top" in pair for pair in rep.pairs) and "table_top" in rep.describe()
    # The same motion lifted well above the table is free.
    above = StrikeTarget(tau=0.4, position=robot.fk(robot.q_flat).position + [0.0, 0.0, 0.2], normal=[0, 0, 1],
                         velocity=[1.0, 0, 0], tau_f=1.0)
    plan = planner.plan(start, above)
    assert plan.ok and not checker.check(plan.t, plan.q).collides


def test_broad_phase_agrees_with_pairwise_checks(robot, checker) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(11)
    L = robot.limits
    qs = rng.uniform(L.lower, L.upper, size=(150, 8))
    for q in qs:
        pairwise = bool(checker.colliding_pairs(q))
        rep = checker.check(np.zeros(1), q[None])
        assert rep.collides == pairwise
    assert any(bool(checker.colliding_pairs(q)) for q in qs)  # random poses do collide


def test_bad_inputs_raise(checker) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInputError, match="q is not finite"):
        checker.check(np.zeros(2), np.full((2, 8), np.nan))
    with pytest.raises(InvalidInputError, match="need t"):
        checker.check(np.zeros(3), np.zeros((2, 8)))


def _min_jerk(q0: np.ndarray, q1: np.ndarray, n: int) -> np.ndarray:
    """(n, 8) minimum-jerk joint path from q0 to q1."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    return q0 + (q1 - q0) * (10 * s**3 - 15 * s**4 + 6 * s**5)


def test_fast_check_equals_exhaustive_on_random_motions(robot, checker) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(5)
    L = robot.limits
    lo, hi = np.asarray(L.lower), np.asarray(L.upper)
    reports = []
    for _ in range(30):
        q0 = robot.q_flat + rng.uniform(-0.3, 0.3, 8) * (hi - lo)
        q1 = q0 + rng.uniform(-0.25, 0.25, 8) * (hi - lo)
        n = int(rng.integers(150, 400))
        qq = _min_jerk(np.clip(q0, lo, hi), np.clip(q1, lo, hi), n)
        t = 0.3 + np.arange(n) * 1e-3
        fast, ref = checker.check(t, qq), checker.check(t, qq, exhaustive=True)
        assert fast == ref
        reports.append(ref)
    hits = [r for r in reports if r.collides]
    assert 5 <= len(hits) <= 25  # both outcomes exercised
    assert any(r.index is not None and r.index > 0 for r in hits)  # not only collisions at the first sample


def test_fast_check_equals_exhaustive_on_planned_and_perturbed_serves(robot) -> None:  # type: ignore[no-untyped-def]
    import dataclasses
    from pathlib import Path

    from studio.serve.evaluate import EvaluationContext, plan_motion
    from studio.serve.params import load_serve

    ctx = EvaluationContext.default()
    checker = ctx.collision
    serves = [load_serve(p) for p in sorted((Path(__file__).resolve().parent.parent / "examples" / "serves").glob("*.json"))]
    rng = np.random.default_rng(2)
    variants = list(serves)
    for k in range(12):  # racket driven downwards hard, short returns: many collide with the table
        p = serves[k % len(serves)].params
        v = np.asarray(p.velocity) + rng.normal(0.0, 1.0, 3) - [0.0, 0.0, rng.uniform(1.0, 5.0)]
        p2 = dataclasses.replace(p, velocity=tuple(v), t_return=float(rng.uniform(0.3, 0.6)), offset=tuple(rng.normal(0, 0.05, 3)))
        variants.append(dataclasses.replace(serves[k % len(serves)], params=p2))
    outcomes = []
    for s in variants:
        m = plan_motion(s, ctx)
        if m.q is None:
            continue
        fast, ref = checker.check(m.t, m.q), checker.check(m.t, m.q, exhaustive=True)
        assert fast == ref
        outcomes.append(ref.collides)
    assert len(outcomes) >= 12 and any(outcomes) and not all(outcomes)
    assert not any(outcomes[: len(serves)])  # the example serves are collision-free


def test_motion_bound_is_sound(robot, checker) -> None:  # type: ignore[no-untyped-def]
    """d(s) + B(s) never decreases (up to coal's distance tolerance): the bound covers every
    sample-to-sample distance change of every pair."""
    import pinocchio as pin

    rng = np.random.default_rng(8)
    L = robot.limits
    lo, hi = np.asarray(L.lower), np.asarray(L.upper)
    qq = np.vstack([
        _min_jerk(robot.q_flat, np.clip(robot.q_flat + rng.uniform(-0.3, 0.3, 8) * (hi - lo), lo, hi), 120),
        _min_jerk(robot.q_rest, robot.q_flat, 80),
    ])
    steps, lever, view = checker._motion_bounds(qq)
    gm, gd = checker.geom_model, checker.geom_data
    d = np.empty((qq.shape[0], checker.n_pairs))
    for s, q in enumerate(qq):
        pin.computeDistances(robot.model, checker.data, gm, gd, q)
        d[s] = [r.min_distance for r in gd.distanceResults]
    both_free = (d[1:] > 0) & (d[:-1] > 0)
    moved = np.abs(np.diff(d, axis=0))[both_free]
    assert moved.max() > 1e-3  # the pairs did move: the bound is exercised
    B = (steps @ lever)[:, view]  # (S, P)
    slack = np.diff(d + B, axis=0)[both_free]
    # Only coal's GJK distance tolerance (1e-6 m) shows, ten times below the skipping margin.
    assert slack.size > 10_000 and slack.min() > -1e-5
    tight = np.diff(B, axis=0)[both_free] / np.maximum(moved, 1e-6)
    assert np.median(tight[moved > 1e-4]) < 10.0  # and the bound is not absurdly loose


def test_stride_fast_equals_exhaustive(robot) -> None:  # type: ignore[no-untyped-def]
    planner = StrikePlanner(robot)
    start = StrikeStart.at_rest(robot.q_flat)
    into = StrikeTarget(tau=0.4, position=[-1.2, 0.0, -0.03], normal=[0, 0, 1], velocity=[0, 0, 0], tau_f=1.0)
    plan = planner.plan(start, into)
    strided = CollisionChecker(robot, stride=4)
    fast, ref = strided.check(plan.t, plan.q), strided.check(plan.t, plan.q, exhaustive=True)
    assert fast == ref and fast.collides and fast.index is not None and fast.index % 4 == 0
    assert fast.samples_checked == len(range(0, len(plan.t), 4)) + (0 if (len(plan.t) - 1) % 4 == 0 else 1)


def test_penetrating_cylinders_are_collisions(robot, checker) -> None:  # type: ignore[no-untyped-def]
    """coal 3.0.3 with pinocchio's default requests (no contacts) called this pose free."""
    import pinocchio as pin

    q = np.array([-0.7701076773993427, 0.2906404810342453, 1.2621156368903441, -0.5480521407305974,
                  -0.39285006700305647, 1.3723268456976874, -1.8995846259183682, 1.5097842289137282])
    fresh = CollisionChecker(robot)  # coal's answer depended on its cached GJK guesses
    assert ("link_4_0", "link_6_0") in fresh.colliding_pairs(q)
    assert checker.min_distance(q) < -5e-4  # link_4_0 and link_6_0 overlap by 0.8 mm
    rep = checker.check(np.zeros(1), q[None])
    assert rep == checker.check(np.zeros(1), q[None], exhaustive=True) and rep.pairs == (("link_4_0", "link_6_0"),)
    # Every pair coal measures as penetrating (signed distance < -0.1 mm) is a collision.
    rng = np.random.default_rng(0)
    gm, gd = checker.geom_model, checker.geom_data
    n_pen = 0
    for qr in rng.uniform(robot.limits.lower, robot.limits.upper, size=(300, 8)):
        pin.computeDistances(robot.model, checker.data, gm, gd, qr)
        pen = {k for k, r in enumerate(gd.distanceResults) if r.min_distance < -1e-4}
        hits = {(checker.names[i], checker.names[j]) for i, j in checker._colliding_pairs(qr)}
        assert {(checker.names[checker._pairs[k][0]], checker.names[checker._pairs[k][1]]) for k in pen} <= hits
        n_pen += len(pen)
    assert n_pen > 100


def test_bounding_volume_bounds_are_below_coal_distances(robot, checker) -> None:  # type: ignore[no-untyped-def]
    """The pre-filter's lower bounds never exceed coal's distance (else it could skip a
    contact), and they are useful: most pairs are far from touching in random poses."""
    import pinocchio as pin

    rng = np.random.default_rng(3)
    qs = rng.uniform(robot.limits.lower, robot.limits.upper, size=(200, 8))
    low = checker._sphere_bounds(qs)  # (P, S)
    gm, gd = checker.geom_model, checker.geom_data
    d = np.empty_like(low)
    for s, q in enumerate(qs):
        pin.computeDistances(robot.model, checker.data, gm, gd, q)
        d[:, s] = [r.min_distance for r in gd.distanceResults]
    free = d > 0
    assert np.all(low[free] <= d[free] + 1e-9)
    assert np.all(low[~free] <= 1e-9)  # touching or penetrating pairs: volumes overlap
    assert np.mean(low > 1e-4) > 0.95
    assert np.median((d - low)[free]) < 0.05  # not absurdly loose


@pytest.mark.parametrize(("window", "stride"), [(1, 1), (2, 3), (5, 1), (1000, 1), (32, 3)])
def test_fast_check_equals_exhaustive_for_any_window_and_stride(robot, window: int, stride: int) -> None:  # type: ignore[no-untyped-def]
    """The pre-filter's window is a speed knob only: the report never depends on it."""
    chk = CollisionChecker(robot, window=window, stride=stride)
    rng = np.random.default_rng(11)
    L = robot.limits
    lo, hi = np.asarray(L.lower), np.asarray(L.upper)
    hits = 0
    for _ in range(12):
        q0 = np.clip(robot.q_flat + rng.uniform(-0.3, 0.3, 8) * (hi - lo), lo, hi)
        q1 = np.clip(q0 + rng.uniform(-0.25, 0.25, 8) * (hi - lo), lo, hi)
        n = int(rng.integers(1, 300))
        qq = _min_jerk(q0, q1, n)
        t = np.arange(n) * 1e-3
        fast, ref = chk.check(t, qq), chk.check(t, qq, exhaustive=True)
        assert fast == ref
        hits += ref.collides
    assert 0 < hits < 12


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "4"])
def test_bad_window_or_stride_rejected(robot, bad) -> None:  # type: ignore[no-untyped-def]
    for kw in ("window", "stride"):
        with pytest.raises(InvalidInputError, match=kw):
            CollisionChecker(robot, **{kw: bad})
