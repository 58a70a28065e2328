"""Match log, Wilson intervals, Table I statistics, usage counters, pruning and the library CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from studio.cli import main
from studio.errors import DataFileError, InvalidInputError
from studio.library.store import INDEX_NAME, LIBRARY_SCHEMA, ServeLibrary
from studio.library.match import (
    MATCH_LOG,
    PRUNED_DIR,
    Z95,
    Point,
    append_point,
    load_points,
    match_stats,
    prune,
    prune_candidates,
    serve_records,
    sync_usage,
    wilson_interval,
)

PARAMS = {"tau": 0.854, "velocity": [2.62, 1.3, -2.08], "yaw": 1.919, "roll": 0.2, "t_return": 0.7, "offset": [0.0, 0.0, 0.0]}
T0 = "2026-04-12T10:00:00+00:00"


def make_library(folder: Path, serves: list[tuple[str, float, float]]) -> ServeLibrary:
    """Legal serves (id, topspin, sidespin at the net [rad/s]) with tiny NPZs, index written directly."""
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, (sid, top, side) in enumerate(serves):
        np.savez(folder / f"{sid}.npz", t=np.arange(3) * 1e-3, u=np.zeros((3, 8)), q=np.zeros((3, 8)), ball_t=np.zeros(2), ball_p=np.zeros((2, 3)), joint_names=np.array([f"j{k}" for k in range(8)]))
        net = {"p": [0.0, 0.0, 0.2], "v": [5.0, 0.0, 0.0], "w": [0.0, top, side], "topspin": top, "sidespin": side, "cork": 0.0, "clearance": 0.05}
        entries.append(
            {
                "id": sid, "name": sid, "side": "right" if i % 3 else "left", "task": "topspin_velocity", "params": PARAMS, "net": net,
                "second_bounce": None, "legal": True, "reward": 0.1 * i, "terms": {}, "provenance": {"kind": "test"},
                "created": T0, "usage": {"used": 0, "won": 0, "lost": 0, "aces": 0}, "arrays": f"{sid}.npz",
            }
        )  # fmt: skip
    (folder / INDEX_NAME).write_text(json.dumps({"schema": LIBRARY_SCHEMA, "serves": entries}))
    return ServeLibrary(folder)


def robot(serve: str, winner: str, ace: bool = False) -> Point:
    return Point(time=T0, server="robot", serve=serve, winner=winner, ace=ace, opponent="A. Player")


def receive(winner: str) -> Point:
    return Point(time=T0, server="opponent", serve=None, winner=winner, ace=False)


# --- Wilson score interval -------------------------------------------------------------


def test_wilson_known_values_and_edges() -> None:
    lo, hi = wilson_interval(20, 40)
    assert (round(lo, 4), round(hi, 4)) == (0.3520, 0.6480)
    # the paper's Table I, April 2025: 177 robot serves, serving interval 40.8-55.3 % (85 won)
    lo, hi = wilson_interval(85, 177)
    assert (round(100 * lo, 1), round(100 * hi, 1)) == (40.8, 55.3)
    # 0/n and n/n: closed forms z²/(n+z²) and n/(n+z²)
    for n in (1, 5, 30, 1000):
        z2 = Z95**2
        assert wilson_interval(0, n) == (0.0, pytest.approx(z2 / (n + z2), rel=1e-12))
        lo, hi = wilson_interval(n, n)
        assert lo == pytest.approx(n / (n + z2), rel=1e-12) and hi == 1.0
    assert wilson_interval(0, 0) == (0.0, 1.0)
    # the bounds are the roots of the score test (p̂ - p)² = z² p (1 - p) / n
    for k, n in ((3, 17), (50, 60), (1, 2)):
        p_hat = k / n
        for p in wilson_interval(k, n):
            assert (p_hat - p) ** 2 == pytest.approx(Z95**2 * p * (1 - p) / n, rel=1e-9)
    for bad in ((5, 4), (-1, 3), (0, -1)):
        with pytest.raises(InvalidInputError):
            wilson_interval(*bad)


# --- match log ----------------------------------------------------------------------------


def test_log_round_trip_and_statistics(tmp_path: Path) -> None:
    log = tmp_path / MATCH_LOG
    points = [robot("a", "robot", ace=True), robot("a", "opponent"), robot("b", "robot"), receive("robot"), receive("opponent"), receive("opponent")]
    for p in points:
        append_point(log, p)
    again = load_points(log)
    assert again == points
    s = match_stats(again)
    assert (s.serving.won, s.serving.n, s.receiving.won, s.receiving.n, s.aces) == (2, 3, 1, 3, 1)
    assert s.ace_fraction == pytest.approx(1 / 3) and s.opponents == ("A. Player",)
    assert s.serving.interval == wilson_interval(2, 3)
    rec = serve_records(again, ["a", "b", "c"])
    assert rec["a"].usage() == {"used": 2, "won": 1, "lost": 1, "aces": 1}
    assert rec["c"].used == 0 and math.isnan(rec["c"].win.rate)
    assert set(serve_records(again)) == {"a", "b"}


@pytest.mark.parametrize(
    ("record", "field"),
    [
        ({"time": T0, "server": "robot", "serve": "a", "winner": "robot"}, "missing field"),
        ({"time": "yesterday", "server": "robot", "serve": "a", "winner": "robot", "ace": False}, "'time'"),
        ({"time": "2026-04-12T10:00:00", "server": "robot", "serve": "a", "winner": "robot", "ace": False}, "'time'"),  # no offset
        ({"time": T0, "server": "umpire", "serve": "a", "winner": "robot", "ace": False}, "'server'"),
        ({"time": T0, "server": "robot", "serve": "a", "winner": "both", "ace": False}, "'winner'"),
        ({"time": T0, "server": "robot", "serve": None, "winner": "robot", "ace": False}, "'serve'"),
        ({"time": T0, "server": "opponent", "serve": "a", "winner": "robot", "ace": False}, "'serve'"),
        ({"time": T0, "server": "robot", "serve": "a", "winner": "robot", "ace": 1}, "'ace'"),
        ({"time": T0, "server": "robot", "serve": "a", "winner": "opponent", "ace": True}, "'ace'"),
        ({"time": T0, "server": "robot", "serve": "a", "winner": "robot", "ace": False, "score": 3}, "unknown field"),
    ],
)
def test_corrupt_log_lines_name_file_line_and_field(tmp_path: Path, record: dict[str, Any], field: str) -> None:
    log = tmp_path / MATCH_LOG
    append_point(log, robot("a", "robot"))
    append_point(log, receive("opponent"))
    with open(log, "a") as fh:
        fh.write(json.dumps(record) + "\n")
    with pytest.raises(DataFileError, match=rf"{MATCH_LOG}: line 3: .*{field}"):
        load_points(log)


def test_truncated_last_line_is_reported(tmp_path: Path) -> None:
    log = tmp_path / MATCH_LOG
    append_point(log, robot("a", "robot"))
    with open(log, "a") as fh:
        fh.write('{"time": "2026-04-12T10:0')
    with pytest.raises(DataFileError, match="line 2: not valid JSON"):
        load_points(log)
    with pytest.raises(InvalidInputError, match="'serve'"):
        append_point(tmp_path / "other.jsonl", Point(time=T0, server="robot", serve=None, winner="robot", ace=False))
    assert not (tmp_path / "other.jsonl").exists()


# --- usage counters and pruning ------------------------------------------------------------


def _season() -> list[Point]:
    """good: 14/20 won; ok: 11/20; bad: 3/20 (Wilson upper 36.0 %); new: 0/3 (too few uses)."""
    pts: list[Point] = []
    for sid, won, n in (("good", 14, 20), ("ok", 11, 20), ("bad", 3, 20), ("new", 0, 3)):
        pts += [robot(sid, "robot", ace=(sid == "good" and i < 4)) for i in range(won)] + [robot(sid, "opponent") for _ in range(n - won)]
    return pts


def test_prune_rule_and_prune_keeps_the_arrays(tmp_path: Path) -> None:
    lib = make_library(tmp_path / "lib", [("good", 250.0, 0.0), ("ok", -120.0, 0.0), ("bad", 0.0, 180.0), ("new", 90.0, 0.0)])
    records = serve_records(_season(), [e.id for e in lib.entries()])
    candidates, total = prune_candidates(records, min_uses=10)
    assert (total.won, total.n) == (28, 63)
    assert [c.record.id for c in candidates] == ["bad"]
    assert candidates[0].upper == pytest.approx(wilson_interval(3, 20)[1]) and candidates[0].upper < 28 / 63
    # 0/3 has upper bound 0.5615 > 28/63 = 0.444: even with min_uses=3 only 'bad' qualifies
    assert [c.record.id for c in prune_candidates(records, min_uses=3)[0]] == ["bad"]
    assert prune_candidates(records, min_uses=21)[0] == []
    assert prune(lib, ["bad"]) == ["bad"]
    assert [e.id for e in lib.entries()] == ["good", "ok", "new"]
    assert not (tmp_path / "lib" / "bad.npz").exists()
    pruned = ServeLibrary(tmp_path / "lib" / PRUNED_DIR)
    assert [e.id for e in pruned.entries()] == ["bad"]
    assert pruned.get("bad").arrays()["u"].shape == (3, 8)
    with pytest.raises(InvalidInputError, match="not in library"):
        prune(lib, ["bad"])


def test_sync_usage_rewrites_counters_atomically_with_validation(tmp_path: Path) -> None:
    lib = make_library(tmp_path, [("good", 250.0, 0.0), ("ok", -120.0, 0.0), ("idle", 0.0, 180.0)])
    sync_usage(lib, _season())  # 'bad' and 'new' are not in this library: ignored
    usage = {e.id: e.data["usage"] for e in lib.entries()}
    assert usage == {"good": {"used": 20, "won": 14, "lost": 6, "aces": 4}, "ok": {"used": 20, "won": 11, "lost": 9, "aces": 0}, "idle": {"used": 0, "won": 0, "lost": 0, "aces": 0}}
    assert not list(tmp_path.glob(".*tmp"))
    bad = [dict(e.data) for e in lib.entries()]
    bad[1]["usage"] = {"used": -1}
    with pytest.raises(DataFileError, match=r"serves\[1\]\.usage\.used"):
        lib.replace_entries(bad)
    assert lib.get("ok").data["usage"]["used"] == 20  # the index was not touched


# --- CLI -------------------------------------------------------------------------------------


def test_library_cli_session(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "lib"
    make_library(folder, [("top", 250.0, 0.0), ("back", -120.0, 0.0), ("side", 0.0, 180.0)])
    d = str(folder)
    assert main(["library", "list", d]) == 0
    out = capsys.readouterr().out
    assert "3 serves" in out and "| top | top | left | topspin_velocity | topspin/heavy |" in out and "backspin/light" in out
    assert main(["library", "show", d, "side"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("cluster: sidespin/heavy") and json.loads(out.split("\n", 1)[1])["id"] == "side"
    assert main(["library", "validate", d]) == 0
    assert "valid (3 serves" in capsys.readouterr().out

    # select -> record, 9 serves: every serve used 3 times, never the same cluster twice in a row
    previous = None
    served = []
    for i in range(9):
        argv = ["library", "select", d] + (["--previous", previous] if previous else [])
        assert main(argv) == 0
        previous = capsys.readouterr().out.split("\t")[0]
        served.append(previous)
        assert main(["library", "record", d, "--serve", previous, "--winner", "robot" if i % 3 else "opponent", "--opponent", "M. Test"] + (["--ace"] if i == 1 else [])) == 0
        assert "recorded point" in capsys.readouterr().out
    assert all(a != b for a, b in zip(served, served[1:], strict=False))
    assert sorted(served) == sorted(["top", "back", "side"] * 3)
    assert main(["library", "record", d, "--server", "opponent", "--winner", "robot"]) == 0
    assert sum(e.data["usage"]["used"] for e in ServeLibrary(folder).entries()) == 9
    assert sum(e.data["usage"]["aces"] for e in ServeLibrary(folder).entries()) == 1
    capsys.readouterr()

    assert main(["library", "stats", d]) == 0
    out = capsys.readouterr().out
    lo, hi = wilson_interval(6, 9)
    assert f"| 3 (2, 1) | 9 | 100.0 (" in out and f"| 66.7 ({100 * lo:.1f}–{100 * hi:.1f}) | 1 (11.1 %) | M. Test |" in out
    assert "| top | top | topspin/heavy | 3 |" in out

    # errors: unknown serve, missing --serve, receiving with a serve id: exit 2, log untouched
    lines = (folder / MATCH_LOG).read_text().count("\n")
    assert main(["library", "record", d, "--serve", "nope", "--winner", "robot"]) == 2
    assert main(["library", "record", d, "--winner", "robot"]) == 2
    assert main(["library", "record", d, "--server", "opponent", "--serve", "top", "--winner", "robot"]) == 2
    assert "--serve" in capsys.readouterr().err
    assert (folder / MATCH_LOG).read_text().count("\n") == lines == 10


def test_cli_prune_and_validate_failures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "lib"
    lib = make_library(folder, [("good", 250.0, 0.0), ("ok", -120.0, 0.0), ("bad", 0.0, 180.0), ("new", 90.0, 0.0)])
    for p in _season():
        append_point(folder / MATCH_LOG, p)
    d = str(folder)
    assert main(["library", "prune", d, "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "bad: 3/20 won, upper bound 36.0 %" in out and "would be pruned" in out
    assert len(lib.entries()) == 4
    assert main(["library", "prune", d, "--min-uses", "25"]) == 0
    assert "nothing to prune" in capsys.readouterr().out
    assert main(["library", "prune", d]) == 0
    assert "pruned 1 serve(s)" in capsys.readouterr().out
    assert [e.id for e in lib.entries()] == ["good", "ok", "new"]
    assert main(["library", "validate", d]) == 0
    assert main(["library", "validate", str(folder / PRUNED_DIR)]) == 0
    capsys.readouterr()
    # a corrupt NPZ, then a corrupt log line: exit 1 with the file (and field) named
    (folder / "ok.npz").write_bytes(b"not a zip")
    assert main(["library", "validate", d]) == 1
    assert "ok.npz: cannot read arrays" in capsys.readouterr().err
    np.savez(folder / "ok.npz", t=np.arange(3) * 1e-3, u=np.zeros((3, 8)), q=np.zeros((3, 8)), ball_t=np.zeros(2), ball_p=np.zeros((2, 3)))
    with open(folder / MATCH_LOG, "a") as fh:
        fh.write(json.dumps({"time": T0, "server": "robot", "serve": "good", "winner": "nobody", "ace": False}) + "\n")
    assert main(["library", "validate", d]) == 1
    assert "matches.jsonl: line 64: field 'winner'" in capsys.readouterr().err
    assert main(["library", "validate", str(tmp_path / "empty")]) == 1
    assert "index.json: missing" in capsys.readouterr().err


def test_record_point_and_next_serve_continue_a_match_from_the_log(tmp_path: Path) -> None:
    from studio.library.match import last_robot_serve, next_serve, record_point

    lib = make_library(tmp_path / "lib", [("top", 250.0, 0.0), ("back", -200.0, 0.0), ("side", 0.0, 220.0)])
    first = next_serve(lib)  # empty log: least used, then highest reward
    assert first.id == "side"
    points = record_point(lib, server="robot", serve=first.id, winner="robot", ace=True, opponent="A. Player", time=T0)
    assert points == [Point(time=T0, server="robot", serve="side", winner="robot", ace=True, opponent="A. Player")]
    assert lib.get("side").data["usage"] == {"used": 1, "won": 1, "lost": 0, "aces": 1}
    record_point(lib, server="opponent", winner="opponent")  # receiving points do not change the previous serve
    assert last_robot_serve(load_points(lib.folder / MATCH_LOG)) == "side"
    second = next_serve(lib)  # a later session: the previous serve comes from the log
    assert second.id != "side" and second.id == "back"
    assert next_serve(lib, "back").id == "top"  # an explicit previous serve wins over the log
    assert next_serve(lib, "pruned-meanwhile").id == "back"  # unknown: no previous serve (least used, then reward)
    with pytest.raises(InvalidInputError, match="'pruned-meanwhile' is not in the library"):
        next_serve(lib, "pruned-meanwhile", strict=True)  # the CLI's --previous
    for bad, match in (
        (dict(server="robot", winner="robot"), "required when the robot serves"),
        (dict(server="robot", serve="nope", winner="robot"), "'nope' not found"),
        (dict(server="opponent", serve="top", winner="robot"), "only for robot serves"),
        (dict(server="robot", serve="top", winner="opponent", ace=True), "ace"),
        (dict(server="referee", winner="robot"), "server"),
    ):
        with pytest.raises(InvalidInputError, match=match):
            record_point(lib, **bad)  # type: ignore[arg-type]
    assert len(load_points(lib.folder / MATCH_LOG)) == 2  # nothing appended by the refused points


# --- appends never glue records; a torn or corrupt log is kept and reported -----------------------


def test_record_repairs_a_missing_final_newline_and_refuses_a_torn_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from studio.library.match import record_point

    lib = make_library(tmp_path / "lib", [("top", 250.0, 0.0), ("back", -200.0, 0.0)])
    log = lib.folder / MATCH_LOG
    record_point(lib, server="robot", serve="top", winner="robot", time=T0)
    record_point(lib, server="opponent", winner="opponent", time=T0)
    log.write_bytes(log.read_bytes().rstrip(b"\n"))  # a valid last line without its newline (hand-edited)
    points = record_point(lib, server="robot", serve="back", winner="opponent", time=T0)
    assert len(points) == 3 and load_points(log) == points  # both lines parse: nothing glued
    assert log.read_bytes().count(b"\n") == 3 and log.read_bytes().endswith(b"\n")
    assert lib.get("back").data["usage"]["used"] == 1

    log.write_bytes(log.read_bytes() + b'{"time": "2026-04-12T10:00:00+00:00", "server": "rob')  # torn by a kill
    torn = log.read_bytes()
    index = (lib.folder / INDEX_NAME).read_bytes()
    with pytest.raises(DataFileError, match=r"matches.jsonl: line 4: not valid JSON"):
        record_point(lib, server="opponent", winner="robot", time=T0)
    with pytest.raises(DataFileError, match=r"matches.jsonl: line 4: incomplete last line"):
        append_point(log, receive("robot"))  # the appender itself refuses too
    assert main(["library", "record", str(lib.folder), "--server", "opponent", "--winner", "robot"]) == 2
    err = capsys.readouterr().err
    assert "matches.jsonl: line 4" in err and "Traceback" not in err
    assert log.read_bytes() == torn and (lib.folder / INDEX_NAME).read_bytes() == index  # both kept byte for byte


def test_a_point_with_a_lone_surrogate_is_refused(tmp_path: Path) -> None:
    from studio.library.match import record_point

    lib = make_library(tmp_path / "lib", [("top", 250.0, 0.0)])
    with pytest.raises(InvalidInputError, match="'opponent' is not valid Unicode"):
        record_point(lib, server="opponent", winner="robot", opponent="M. \udcc3bel")  # undecodable argv byte
    assert not (lib.folder / MATCH_LOG).exists()
    (lib.folder / MATCH_LOG).write_text(json.dumps({"time": T0, "server": "opponent", "serve": None, "winner": "robot", "ace": False, "opponent": "\ud800"}) + "\n")
    with pytest.raises(DataFileError, match="line 1: field 'opponent' is not valid Unicode"):
        load_points(lib.folder / MATCH_LOG)
