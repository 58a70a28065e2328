"""Serve parameters: genome round trips, normal convention, serve JSON validation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from studio.errors import DataFileError, InvalidInputError
from studio.serve.params import (
    GenomeBounds,
    HandServe,
    LimitScale,
    ServeParams,
    load_serve,
    racket_normal,
    save_serve,
    serve_from_json,
    yaw_roll_from_normal,
)


def test_normal_convention() -> None:
    np.testing.assert_allclose(racket_normal(math.pi / 2, 0.0), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(racket_normal(math.pi, 0.0), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(racket_normal(math.pi / 2, math.pi / 2), [0, 0, 1], atol=1e-15)
    # positive roll opens the face (normal tilts up)
    assert racket_normal(math.pi / 2, 0.3)[2] > 0


def test_yaw_roll_inverse() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        yaw = rng.uniform(-math.pi / 2, 3 * math.pi / 2)
        roll = rng.uniform(-math.pi / 2 + 1e-6, math.pi / 2 - 1e-6)
        y2, r2 = yaw_roll_from_normal(racket_normal(yaw, roll))
        assert y2 == pytest.approx(yaw, abs=1e-9) and r2 == pytest.approx(roll, abs=1e-9)


def test_genome_round_trip_exact() -> None:
    bounds = GenomeBounds()
    rng = np.random.default_rng(1)
    for _ in range(100):
        z = rng.uniform(0, 1, 10)
        p = ServeParams.denormalize(z, bounds)
        np.testing.assert_allclose(p.normalize(bounds), z, atol=1e-12)
        assert ServeParams.from_vector(p.to_vector()) == p
    mid = ServeParams.denormalize(np.full(10, 0.5), bounds)
    assert mid.velocity == (0.0, 0.0, 0.0) and mid.offset == (0.0, 0.0, 0.0)
    assert mid.yaw == pytest.approx(math.pi / 2)
    # the 7-gene form keeps offsets at zero
    assert ServeParams.denormalize(np.full(7, 0.5), bounds).offset == (0.0, 0.0, 0.0)


def test_paper_bounds() -> None:
    low, high = GenomeBounds().lows_highs()
    np.testing.assert_allclose(high[1:4], [10, 5, 5])
    np.testing.assert_allclose(high[7:], [0.07] * 3)
    assert high[4] - low[4] == pytest.approx(2 * math.pi)


@pytest.mark.parametrize("field,value", [("tau", float("nan")), ("yaw", float("inf")), ("t_return", -0.1)])
def test_bad_params_rejected(field: str, value: float) -> None:
    kwargs = dict(tau=0.8, velocity=(3.0, 0.0, 1.0), yaw=1.5, roll=0.1, t_return=0.7)
    kwargs[field] = value
    with pytest.raises(InvalidInputError, match=field):
        ServeParams(**kwargs)  # type: ignore[arg-type]


def test_serve_file_round_trip(tmp_path: Path) -> None:
    serve = HandServe(
        name="fast topspin",
        side="left",
        params=ServeParams(tau=0.81, velocity=(6.0, -0.5, 1.5), yaw=1.6, roll=-0.2, offset=(0.01, 0, 0)),
        notes="demo",
        extra={"x_author": "me", "spin": "topspin"},
    )
    path = save_serve(tmp_path / "s.json", serve)
    assert load_serve(path) == serve


@pytest.mark.parametrize(
    "mutate,field",
    [
        (lambda d: d.pop("name"), "name"),
        (lambda d: d.__setitem__("side", "middle"), "side"),
        (lambda d: d["params"].__setitem__("velocity", [1, 2]), "params.velocity"),
        (lambda d: d["params"].__setitem__("tau", "soon"), "params.tau"),
        (lambda d: d["params"].__setitem__("spin", 3), "params"),
        (lambda d: d["params"].pop("roll"), "params.roll"),
        (lambda d: d.__setitem__("schema", "other@9"), "schema"),
        (lambda d: d.__setitem__("limit_scale", 1.3), "limit_scale"),
        (lambda d: d.__setitem__("limit_scale", {"jerk": math.nan}), "limit_scale': LimitScale.jerk"),
        (lambda d: d.__setitem__("limit_scale", {"acceleration": 40}), "limit_scale': LimitScale.acceleration"),
        (lambda d: d.__setitem__("limit_scale", {"torque": 1.2}), "limit_scale': unknown keys"),
        (lambda d: d.__setitem__("limit_scales", {"acceleration": 1.5}), "unknown fields \\['limit_scales'\\]"),
        (lambda d: d.__setitem__("spin", 3), "field 'spin'"),
        (lambda d: d.__setitem__("name", "\ud800"), "field 'name': not valid Unicode"),
        (lambda d: d.__setitem__("name", "n" * 500), "field 'name'"),
        (lambda d: d["params"].__setitem__("t_return", 1e6), "t_return = 1e\\+06 is outside the allowed range \\[0.1, 5\\]"),
        (lambda d: d["params"].__setitem__("velocity", [1e300, 0, 0]), "velocity = 1e\\+300 is outside the allowed range"),
        (lambda d: d["params"].__setitem__("tau", 50.0), "tau = 50 is outside"),
    ],
)
def test_bad_serve_json_names_field(mutate, field: str) -> None:  # type: ignore[no-untyped-def]
    doc = {
        "schema": "serve-studio/serve@1",
        "name": "x",
        "side": "right",
        "params": {"tau": 0.8, "velocity": [3, 0, 1], "yaw": 1.57, "roll": 0.0},
    }
    mutate(doc)
    with pytest.raises(DataFileError, match=f"my.json: .*{field.replace('.', '[.]')}"):
        serve_from_json(doc, source="my.json")


def test_corrupt_file_rejected(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text("{not json")
    with pytest.raises(DataFileError, match="bad.json.*not valid JSON"):
        load_serve(path)
    with pytest.raises(DataFileError, match="cannot read"):
        load_serve(tmp_path / "missing.json")


def test_limit_scale_in_serve_files() -> None:
    """A serve carries its dynamic limit expansion; files without it plan with the robot's limits."""
    doc = {"name": "x", "side": "right", "params": {"tau": 0.8, "velocity": [3, 0, 1], "yaw": 1.57, "roll": 0.0}}
    plain = serve_from_json(doc)
    assert plain.limit_scale == LimitScale() and plain.limit_scale.is_identity
    assert "limit_scale" not in plain.to_json()  # files of the robot's own limits stay as they were
    fast = serve_from_json({**doc, "limit_scale": {"acceleration": 1.5, "jerk": 1.25}})
    assert fast.limit_scale == LimitScale(velocity=1.0, acceleration=1.5, jerk=1.25)
    assert serve_from_json(fast.to_json()) == fast
    assert fast.to_json()["limit_scale"] == {"velocity": 1.0, "acceleration": 1.5, "jerk": 1.25}


def test_limit_scale_parse_apply_and_reject() -> None:
    from studio.robot.model import load_robot

    assert LimitScale.parse("1.3") == LimitScale(acceleration=1.3, jerk=1.3)  # the paper's expansion
    assert LimitScale.parse(" velocity=1.1, jerk=2 ") == LimitScale(velocity=1.1, jerk=2.0)
    for bad, what in (("fast", "part 'fast'"), ("jerk=x", "jerk must be a number"), ("torque=2", "torque"), ("nan", "acceleration"), ("0", r"\[0.25, 4.0\]")):
        with pytest.raises(InvalidInputError, match=what):
            LimitScale.parse(bad)
    with pytest.raises(InvalidInputError, match="jerk given twice"):
        LimitScale.parse("jerk=1.2,jerk=2")
    with pytest.raises(InvalidInputError, match="LimitScale.velocity"):
        LimitScale(velocity=True)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="LimitScale.jerk"):
        LimitScale(jerk=10**400)  # beyond float range: an error, not an OverflowError
    assert LimitScale(acceleration=1.1500000000000001) == LimitScale(acceleration=1.15)  # slider steps
    base = load_robot().limits
    out = LimitScale(velocity=1.2, acceleration=1.5, jerk=2.0).apply(base)
    np.testing.assert_allclose(out.velocity, 1.2 * base.velocity)
    np.testing.assert_allclose(out.acceleration, 1.5 * base.acceleration)
    np.testing.assert_allclose(out.jerk, 2.0 * base.jerk)
    np.testing.assert_array_equal(out.lower, base.lower)
    np.testing.assert_array_equal(out.upper, base.upper)
    assert LimitScale().apply(base) is base


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{}".encode("utf-16"), "not UTF-8 text"),
        (b"[" * 5000 + b"]" * 5000, "nested 5000 levels deep"),
        (b'{"name": NaN}', "field 'name': must be a finite number"),
        (b'{"n": ' + b"9" * 5000 + b"}", "an integer of 5000 digits"),
        (b'{"n": 1e400}', "field 'n': must be a finite number"),
        (b'{"name": "\\ud800"}', "field 'name' is not valid Unicode"),
        (b"", "not valid JSON"),
    ],
    ids=["utf16", "deep", "nan", "huge-int", "huge-float", "surrogate", "empty"],
)
def test_corrupt_serve_files_name_the_file_and_problem(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.json"
    path.write_bytes(content)
    with pytest.raises(DataFileError, match=f"bad.json: .*{message}"):
        load_serve(path)


def test_a_fifo_or_huge_file_is_refused_without_reading_it(tmp_path: Path) -> None:
    import os

    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    with pytest.raises(DataFileError, match="pipe.json: not a regular file"):
        load_serve(fifo)  # returns at once: opened non-blocking, refused by type
    big = tmp_path / "big.json"
    big.write_bytes(b" " * 1_000_001)
    with pytest.raises(DataFileError, match="big.json: 1000001 bytes, more than the 1000000 bytes allowed"):
        load_serve(big)
