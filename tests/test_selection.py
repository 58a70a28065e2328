"""Serve selection: spin clusters (direction / magnitude band) and the next-serve rule."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from studio.errors import InvalidInputError
from studio.library.store import INDEX_NAME, LIBRARY_SCHEMA, ServeLibrary
from studio.library.selection import HEAVY_SPIN, SelectionParams, select_next, serve_cluster

PARAMS = {"tau": 0.854, "velocity": [2.62, 1.3, -2.08], "yaw": 1.919, "roll": 0.2, "t_return": 0.7, "offset": [0.0, 0.0, 0.0]}


def _net(topspin: float, sidespin: float, cork: float = 0.0) -> dict[str, Any]:
    # velocity along +x: topspin is +w_y, sidespin +w_z, cork +w_x (values only need to be consistent)
    return {"p": [0.0, 0.0, 0.2], "v": [5.0, 0.0, 0.0], "w": [cork, topspin, sidespin], "topspin": topspin, "sidespin": sidespin, "cork": cork, "clearance": 0.05}


def make_library(folder: Path, serves: list[tuple[str, tuple[float, float] | None, bool, float, int]]) -> ServeLibrary:
    """A library of (id, (topspin, sidespin) at the net or None, legal, reward, used) with tiny NPZs."""
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for sid, spin, legal, reward, used in serves:
        np.savez(folder / f"{sid}.npz", t=np.arange(3) * 1e-3, u=np.zeros((3, 8)), q=np.zeros((3, 8)), ball_t=np.zeros(2), ball_p=np.zeros((2, 3)), joint_names=np.array([f"j{i}" for i in range(8)]))
        entries.append(
            {
                "id": sid,
                "name": sid.replace("-", " "),
                "side": "right" if len(entries) % 2 == 0 else "left",
                "task": "topspin_velocity",
                "params": PARAMS,
                "net": None if spin is None else _net(*spin),
                "second_bounce": None,
                "legal": legal,
                "reward": reward,
                "terms": {},
                "provenance": {"kind": "test"},
                "created": "2026-01-01T00:00:00+00:00",
                "usage": {"used": used, "won": 0, "lost": 0, "aces": 0},
                "arrays": f"{sid}.npz",
            }
        )
    (folder / INDEX_NAME).write_text(json.dumps({"schema": LIBRARY_SCHEMA, "serves": entries}))
    return ServeLibrary(folder)


def test_clusters_by_direction_and_magnitude(tmp_path: Path) -> None:
    lib = make_library(
        tmp_path,
        [
            ("top-heavy", (200.0, 20.0), True, 0.0, 0),
            ("top-light", (100.0, -10.0), True, 0.0, 0),
            ("back-light", (-80.0, 5.0), True, 0.0, 0),
            ("side-heavy", (30.0, -170.0), True, 0.0, 0),
            ("mixed-heavy", (150.0, -150.0), True, 0.0, 0),
            ("flat", (5.0, 3.0), True, 0.0, 0),
            ("no-net", None, True, 0.0, 0),
            ("edge", (HEAVY_SPIN, 0.0), True, 0.0, 0),
        ],
    )
    got = {e.id: serve_cluster(e) for e in lib.entries()}
    assert got == {
        "top-heavy": "topspin/heavy",
        "top-light": "topspin/light",
        "back-light": "backspin/light",
        "side-heavy": "sidespin/heavy",
        "mixed-heavy": "mixed/heavy",  # 150/212 = 0.71 < 0.8 dominance
        "flat": "no spin",
        "no-net": "no net crossing",
        "edge": "topspin/heavy",  # the threshold itself is heavy
    }
    # the magnitude band moves with its threshold
    assert serve_cluster(lib.get("top-heavy"), params=SelectionParams(heavy_spin=250.0)) == "topspin/light"


def test_200_selections_never_repeat_a_cluster_and_balance_usage(tmp_path: Path) -> None:
    lib = make_library(
        tmp_path,
        [
            ("t1", (220.0, 0.0), True, 0.5, 0),
            ("t2", (240.0, 10.0), True, 0.4, 0),
            ("t3", (300.0, -20.0), True, 0.3, 0),
            ("tl", (90.0, 0.0), True, 0.2, 0),
            ("b1", (-120.0, 0.0), True, 0.1, 0),
            ("b2", (-100.0, 5.0), True, 0.0, 0),
            ("s1", (20.0, 180.0), True, 0.0, 0),
            ("bad", (-200.0, 0.0), False, 1.0, 0),  # illegal: a cluster of its own, never served
        ],
    )
    entries = lib.entries()
    cluster = {e.id: serve_cluster(e) for e in entries}
    usage: Counter[str] = Counter()
    previous: str | None = None
    sequence = []
    for _ in range(200):
        e = select_next(entries, previous, usage=usage)
        sequence.append(e.id)
        usage[e.id] += 1
        previous = e.id
    assert "bad" not in usage
    assert all(cluster[a] != cluster[b] for a, b in zip(sequence, sequence[1:], strict=False))
    # least-used first: every legal serve is used, counts stay within one of each other
    assert set(usage) == {"t1", "t2", "t3", "tl", "b1", "b2", "s1"}
    assert max(usage.values()) - min(usage.values()) <= 1
    # the same with random tie-breaking
    rng = np.random.default_rng(3)
    previous, seq2 = None, []
    usage2: Counter[str] = Counter()
    for _ in range(200):
        e = select_next(entries, previous, usage=usage2, rng=rng)
        seq2.append(e.id)
        usage2[e.id] += 1
        previous = e.id
    assert all(cluster[a] != cluster[b] for a, b in zip(seq2, seq2[1:], strict=False))
    assert max(usage2.values()) - min(usage2.values()) <= 1
    assert seq2 != sequence  # the rng did break ties differently


def test_least_used_serve_of_another_cluster_is_preferred(tmp_path: Path) -> None:
    lib = make_library(
        tmp_path,
        [
            ("top-a", (250.0, 0.0), True, 0.9, 0),
            ("top-b", (260.0, 0.0), True, 0.8, 0),
            ("back-a", (-90.0, 0.0), True, 0.1, 7),
            ("back-b", (-95.0, 0.0), True, 0.2, 3),
            ("side-a", (0.0, 90.0), True, 0.3, 4),
        ],
    )
    entries = lib.entries()
    # counters from the index: top-b is unused but in the previous serve's cluster
    assert select_next(entries, "top-a").id == "back-b"
    # at the start of a match (no previous serve) the least used overall; tie -> higher reward
    assert select_next(entries, None).id == "top-a"
    # an explicit usage mapping overrides the counters (absent ids count 0)
    assert select_next(entries, "back-b", usage={"top-a": 5, "top-b": 5, "back-a": 0}).id == "side-a"
    assert select_next(entries, "side-a", usage={"top-a": 5, "top-b": 2, "back-a": 9, "back-b": 9}).id == "top-b"
    with pytest.raises(InvalidInputError, match="not in the library"):
        select_next(entries, "nope")


def test_single_cluster_falls_back_to_the_least_used_other_serve(tmp_path: Path) -> None:
    lib = make_library(
        tmp_path,
        [
            ("a", (250.0, 0.0), True, 0.0, 0),
            ("b", (260.0, 0.0), True, 0.0, 6),
            ("c", (270.0, 0.0), True, 0.0, 2),
            ("x", (-200.0, 0.0), False, 0.0, 0),  # other cluster, but illegal
        ],
    )
    entries = lib.entries()
    assert select_next(entries, "a").id == "c"  # a itself is least used but was just served
    assert select_next(entries, "c").id == "a"
    assert select_next(entries, "x").id == "a"  # previous may be any library serve
    only = make_library(tmp_path / "one", [("solo", (250.0, 0.0), True, 0.0, 3), ("off", (0.0, 200.0), False, 0.0, 0)])
    assert select_next(only.entries(), "solo").id == "solo"  # a single legal serve is repeated
    none = make_library(tmp_path / "none", [("off", (0.0, 200.0), False, 0.0, 0)])
    with pytest.raises(InvalidInputError, match="no legal serve"):
        select_next(none.entries(), None)


def test_rng_tie_break_reaches_every_tied_serve(tmp_path: Path) -> None:
    lib = make_library(tmp_path, [("p", (250.0, 0.0), True, 0.0, 0), ("q", (-120.0, 0.0), True, 0.0, 1), ("r", (-130.0, 0.0), True, 0.0, 1), ("s", (0.0, 160.0), True, 0.0, 1)])
    entries = lib.entries()
    picks = {select_next(entries, "p", rng=np.random.default_rng(seed)).id for seed in range(40)}
    assert picks == {"q", "r", "s"}
    assert select_next(entries, "p").id == "q"  # deterministic: equal rewards -> smaller id
