"""Collision checker (studio.collision): robot vs itself, table, net, posts, legs, floor."""

from __future__ import annotations

import numpy as np
import pytest

from studio.collision import CollisionChecker
from studio.errors import InvalidInputError
from studio.planner import StrikePlanner, StrikeStart, StrikeTarget
from studio.robot import load_robot


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
