"""Serve library: export round trip, validation of corrupt files, no pickles."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from studio.errors import DataFileError, InvalidInputError
from studio.library.store import INDEX_NAME, ServeLibrary
from studio.serve.evaluate import EvaluationContext, evaluate_serve
from studio.serve.params import load_serve

EXAMPLE = sorted((Path(__file__).resolve().parent.parent / "examples" / "serves").glob("topspin_right.json"))[0]


@pytest.fixture(scope="module")
def evaluation():  # type: ignore[no-untyped-def]
    serve = load_serve(EXAMPLE)
    return evaluate_serve(serve, EvaluationContext.default())


def test_export_and_read_back_is_identical(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    lib = ServeLibrary(tmp_path / "lib")
    entry = lib.add(evaluation, provenance={"kind": "hand-designed", "file": EXAMPLE.name})
    again = ServeLibrary(tmp_path / "lib").get(entry.id)
    assert again.serve.params == evaluation.serve.params
    assert again.serve.side == evaluation.serve.side and again.serve.name == evaluation.serve.name
    arrays = again.arrays()
    P, M = round(float(arrays["t_toss"]) / 1e-3), len(evaluation.t)  # the evaluation's preparation leads
    assert P == evaluation.motion.preparation.u.shape[0] and entry.data["t_toss"] == float(arrays["t_toss"])
    np.testing.assert_allclose(arrays["t"][P : P + M], evaluation.t + P * 1e-3, atol=1e-12)
    np.testing.assert_array_equal(arrays["u"][P : P + M], evaluation.u)
    np.testing.assert_array_equal(arrays["q"][P : P + M], evaluation.q)
    assert len(arrays["t"]) == P + M + entry.data["settle"]["samples"]  # then the final hold
    np.testing.assert_array_equal(arrays["ball_p"], evaluation.ball.p)
    assert np.all(np.diff(arrays["t"]) == pytest.approx(1e-3))  # 1 kHz
    assert again.data["legal"] is True and again.data["reward"] == pytest.approx(evaluation.reward.total)
    assert len(again.data["robot"]["urdf_sha256"]) == 64
    # a second export appends, ids stay unique
    lib.add(evaluation)
    ids = [e.id for e in lib.entries()]
    assert len(ids) == 2 and len(set(ids)) == 2
    assert not list((tmp_path / "lib").glob(".*tmp"))  # atomic writes leave no temporaries


def test_export_holds_preparation_toss_and_strike_on_one_clock(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    context = EvaluationContext.default()
    prep = context.preparation(evaluation.serve.side)
    entry = ServeLibrary(tmp_path / "lib").add(evaluation, preparation=prep)
    a = entry.arrays()
    P = prep.u.shape[0]
    assert entry.data["t_toss"] == pytest.approx(P * 1e-3) and float(a["t_toss"]) == pytest.approx(P * 1e-3)
    assert a["t"][0] == 0.0 and np.all(np.diff(a["t"]) == pytest.approx(1e-3))  # one 1 kHz clock from 0
    np.testing.assert_allclose(a["q"][0], context.robot.q_flat, atol=1e-12)  # starts at rest at the feeder pose
    M = len(evaluation.u)
    np.testing.assert_array_equal(a["u"][P : P + M], evaluation.u)  # then the toss, strike and return, unchanged
    np.testing.assert_array_equal(a["u"][P + M :], np.repeat(evaluation.u[-1:], len(a["u"]) - P - M, axis=0))  # then the hold
    np.testing.assert_allclose(a["u"][P - 1], evaluation.u[0], atol=1e-12)  # the hold is at the toss's first command
    np.testing.assert_allclose(a["q"][P - 1], evaluation.u[0], atol=1e-6)  # and the joints have settled there
    np.testing.assert_allclose(a["ball_t"], evaluation.ball.t - evaluation.t[0] + P * 1e-3)  # ball on the same clock
    assert prep.duration > 0.3 and prep.max_tilt < np.radians(45)
    assert prep.cup is not None and prep.cup.passed and prep.duration == pytest.approx(prep.motion_time + 0.3)


def test_exported_arrays_end_with_the_joints_at_rest(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    """numpy only on the NPZ: the last command is held until the predicted joints are within
    0.1 mm / 0.1 mrad of it and move less than 1 mm/s / 1 mrad/s (finite differences)."""
    entry = ServeLibrary(tmp_path / "lib").add(evaluation)
    with np.load(tmp_path / "lib" / entry.data["arrays"], allow_pickle=False) as npz:
        t, u, q = npz["t"], npz["u"], npz["q"]
    dt = 1e-3
    assert np.all(np.abs(np.diff(t) - dt) < 1e-9)  # one 1 kHz clock, the hold included
    np.testing.assert_allclose(u[-1], evaluation.u[-1], atol=0)  # the rest command
    assert np.all(np.abs(q[-2:] - u[-1]) <= 1e-4)  # position
    assert np.all(np.abs(np.diff(q[-3:], axis=0)) / dt <= 1e-3)  # speed over the last two intervals
    n = entry.data["settle"]["samples"]
    assert entry.data["settle"] == {"samples": n, "position": 1e-4, "velocity": 1e-3}
    assert 50 <= n <= 300 and np.all(u[-n - 1 :] == u[-1])  # the hold was needed, and is a hold
    end = len(t) - n - 1  # where the return's commands end: the joints were still moving
    assert np.abs(q[end] - u[-1]).max() > 3e-3 and np.abs(q[end] - q[end - 1]).max() / dt > 0.1


def test_exported_efforts_are_on_the_npz_clock_and_cover_the_preparation(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    """The effort report equals RNEA recomputed from the exported arrays (speeds by central
    differences of q, accelerations from the joint model), with peak times on the NPZ's t."""
    from studio.robot.model import load_robot
    from studio.serve.efforts import effort_report

    robot = load_robot()
    rep = effort_report(evaluation.motion, robot)
    entry = ServeLibrary(tmp_path / "lib").add(evaluation)
    with np.load(tmp_path / "lib" / entry.data["arrays"], allow_pickle=False) as npz:
        t, u, q = npz["t"], npz["u"], npz["q"]
    qd = np.gradient(q, t, axis=0)
    dyn = robot.dynamics
    tau = np.abs(robot.joint_efforts(q, qd, dyn.wn**2 * (u - q) - 2 * dyn.zeta * dyn.wn * qd))
    np.testing.assert_allclose(rep.peak, tau.max(axis=0), rtol=0.02)
    for j in range(8):  # each reported peak time is on the NPZ clock, where the recomputed efforts peak too
        k = int(np.searchsorted(t, rep.at[j]))
        assert abs(t[k] - rep.at[j]) < 1e-9 and tau[max(k - 2, 0) : k + 3, j].max() >= 0.98 * tau[:, j].max()
    assert entry.data["robot"]["efforts"]["at"] == pytest.approx(list(rep.at))
    P = round(float(entry.data["t_toss"]) / 1e-3)
    prep_peak = tau[:P].max(axis=0)  # the preparation is part of the motion reported
    assert np.all(rep.peak >= 0.98 * prep_peak) and t[P] > 0.8


def test_corrupt_index_is_rejected_with_file_and_field(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    lib = ServeLibrary(tmp_path)
    lib.add(evaluation)
    index = tmp_path / INDEX_NAME
    doc = json.loads(index.read_text())
    for mutate, field in [
        (lambda d: d.__setitem__("schema", "other"), "schema"),
        (lambda d: d["serves"][0].__setitem__("reward", "high"), "serves[0].reward"),
        (lambda d: d["serves"][0].__setitem__("id", "../evil"), "serves[0].id"),
        (lambda d: d["serves"][0]["params"].__setitem__("tau", None), "params.tau"),
        (lambda d: d["serves"][0].pop("legal"), "serves[0]"),
        (lambda d: d["serves"][0].__setitem__("t_toss", -0.5), "serves[0].t_toss"),
    ]:
        bad = json.loads(json.dumps(doc))
        mutate(bad)
        index.write_text(json.dumps(bad))
        with pytest.raises(DataFileError, match=f"index.json.*{field.replace('[', '.').replace(']', '.')}"):
            lib.entries()
    index.write_text("{broken")
    with pytest.raises(DataFileError, match="index.json: not valid JSON"):
        lib.entries()


def test_arrays_are_never_unpickled(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    lib = ServeLibrary(tmp_path)
    entry = lib.add(evaluation)
    path = tmp_path / entry.data["arrays"]
    np.savez(path, t=np.array([object()], dtype=object), u=np.zeros((1, 8)), q=np.zeros((1, 8)), ball_t=np.zeros(1), ball_p=np.zeros((1, 3)))
    with pytest.raises(DataFileError, match=entry.data["arrays"]):
        entry.arrays()
    np.savez(path, t=np.arange(3.0), u=np.zeros((3, 8)), q=np.zeros((3, 8)), ball_t=np.zeros(1), ball_p=np.zeros((1, 3)), t_toss=np.array(9.0))
    with pytest.raises(DataFileError, match="t_toss"):  # the toss must start within the arrays' time span
        entry.arrays()
    np.savez(path, t=np.zeros(3), u=np.zeros((2, 8)), q=np.zeros((3, 8)), ball_t=np.zeros(1), ball_p=np.zeros((1, 3)))
    with pytest.raises(DataFileError, match="'u' and 'q'"):
        entry.arrays()


def test_serve_without_plan_cannot_be_exported(tmp_path: Path) -> None:
    import math

    from studio.serve.params import HandServe, ServeParams

    early = HandServe(name="early", side="right", params=ServeParams(tau=0.4, velocity=(3.0, 0, 0), yaw=math.pi / 2, roll=0.0))
    ev = evaluate_serve(early, EvaluationContext.default())
    with pytest.raises(InvalidInputError, match="no motion plan"):
        ServeLibrary(tmp_path).add(ev)
    assert not (tmp_path / INDEX_NAME).exists()


def test_export_records_the_limit_scale_and_the_limits_it_needs(tmp_path: Path) -> None:
    from dataclasses import replace

    from studio.robot.model import load_robot
    from studio.serve.params import LimitScale

    context = EvaluationContext.default()
    scale = LimitScale(velocity=1.1, acceleration=1.5, jerk=1.5)
    serve = replace(load_serve(EXAMPLE), limit_scale=scale)
    lib = ServeLibrary(tmp_path / "lib")
    entry = lib.add(evaluate_serve(serve, context))
    robot = lib.get(entry.id).data["robot"]
    base = load_robot().limits
    assert robot["limit_scale"] == {"velocity": 1.1, "acceleration": 1.5, "jerk": 1.5}
    np.testing.assert_allclose(robot["limits"]["velocity"], 1.1 * base.velocity)
    np.testing.assert_allclose(robot["limits"]["acceleration"], 1.5 * base.acceleration)
    np.testing.assert_allclose(robot["limits"]["jerk"], 1.5 * base.jerk)
    assert lib.get(entry.id).serve.limit_scale == scale  # back into the studio / a seed with its scale
    plain = lib.add(evaluate_serve(load_serve(EXAMPLE), context))
    assert plain.data["robot"]["limit_scale"] == LimitScale().to_json() and plain.serve.limit_scale.is_identity
    # an index entry without the field (older libraries) plans with the robot's limits
    doc = json.loads((tmp_path / "lib" / INDEX_NAME).read_text())
    del doc["serves"][0]["robot"]["limit_scale"]
    (tmp_path / "lib" / INDEX_NAME).write_text(json.dumps(doc))
    assert lib.get(entry.id).serve.limit_scale.is_identity
    # a corrupt scale is rejected with the file, entry and field named
    doc["serves"][1]["robot"]["limit_scale"] = {"jerk": -1}
    (tmp_path / "lib" / INDEX_NAME).write_text(json.dumps(doc))
    with pytest.raises(DataFileError, match=r"index.json: serves\[1\].robot: field 'limit_scale': LimitScale.jerk"):
        lib.entries()


def test_export_records_the_peak_joint_efforts(tmp_path: Path) -> None:
    from studio.serve.efforts import effort_report

    context = EvaluationContext.default()
    ev = evaluate_serve(load_serve(EXAMPLE), context)
    lib = ServeLibrary(tmp_path / "lib")
    rep = effort_report(ev.motion, context.robot)
    entry = lib.add(ev)
    stored = lib.get(entry.id).data["robot"]["efforts"]
    expected = rep.to_json()
    assert set(stored) == set(expected) and stored["names"] == expected["names"] and len(stored["usage"]) == 8
    for key in ("peak", "at", "limit", "usage"):
        assert stored[key] == pytest.approx(expected[key], rel=1e-9), key
    assert stored["within"] is True and stored["exceeded"] == [] and stored["raised"] == []


# --- a library that cannot be read is never rewritten --------------------------------------------

CORRUPT = [  # (what, mutation of a valid index, field named in the error)
    ("NaN in the net state", lambda d: d["serves"][0]["net"]["v"].__setitem__(0, float("nan")), "serves[0].net.v[0]"),
    ("a string where the net state goes", lambda d: d["serves"][0].__setitem__("net", "fast"), "serves[0].net"),
    ("Infinity in a second-bounce spin", lambda d: d["serves"][0]["second_bounce"].__setitem__("topspin", float("inf")), "serves[0].second_bounce.topspin"),
    ("a 10**400 counter", lambda d: d["serves"][0]["usage"].__setitem__("used", 10**400), "serves[0].usage.used"),
    ("a lone surrogate in a name", lambda d: d["serves"][0].__setitem__("name", "top\ud800spin"), "serves[0].name"),
    ("NaN in a reward term", lambda d: d["serves"][0]["terms"].__setitem__("r_pos", float("nan")), "serves[0].terms.r_pos"),
]


@pytest.mark.parametrize("what, mutate, field", CORRUPT, ids=[c[0] for c in CORRUPT])
def test_no_writer_rewrites_a_corrupt_index(tmp_path: Path, evaluation, what, mutate, field, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    import re

    from studio.cli import main
    from studio.library.match import MATCH_LOG, prune, record_point, sync_usage

    lib = ServeLibrary(tmp_path / "lib")
    sid = lib.add(evaluation).id
    doc = json.loads(lib.index_path.read_text())
    mutate(doc)
    lib.index_path.write_text(json.dumps(doc, indent=1))  # Python's json writes NaN, Infinity, huge ints, \ud800
    original = lib.index_path.read_bytes()
    files = sorted(p.name for p in lib.folder.iterdir())
    named = rf"index.json: field '{re.escape(field)}'"
    writers = [
        lambda: lib.add(evaluation),
        lambda: record_point(lib, server="robot", serve=sid, winner="robot"),
        lambda: record_point(lib, server="opponent", winner="robot"),
        lambda: sync_usage(lib, []),
        lambda: prune(lib, [sid]),
        lambda: lib.replace_entries([json.loads(json.dumps(doc["serves"][0]).replace("NaN", "0").replace("Infinity", "0"))]),
    ]
    for write in writers:
        with pytest.raises(DataFileError, match=named):
            write()
        assert lib.index_path.read_bytes() == original  # kept byte for byte
        assert sorted(p.name for p in lib.folder.iterdir()) == files  # no NPZ, no log, no pruned/ folder
    for argv in (["library", "record", str(lib.folder), "--server", "opponent", "--winner", "robot"], ["library", "prune", str(lib.folder), "--min-uses", "1"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert re.search(named, err) and "Traceback" not in err and err.count("\n") == 1
    assert lib.index_path.read_bytes() == original and not (lib.folder / MATCH_LOG).exists()


def test_cli_export_to_a_corrupt_library_exits_2_and_keeps_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from studio.cli import main

    folder = tmp_path / "lib"
    folder.mkdir()
    index = folder / INDEX_NAME
    index.write_bytes(b'{"schema": "serve-studio/library@1", "serves": [{"id": "x", "net": NaN}]}\n')
    original = index.read_bytes()
    assert main(["evaluate", str(EXAMPLE), "--export", str(folder)]) == 2
    err = capsys.readouterr().err
    assert "index.json: field 'serves[0].net': must be a finite number" in err and "Traceback" not in err
    assert index.read_bytes() == original and sorted(p.name for p in folder.iterdir()) == [INDEX_NAME]


def test_legacy_infinite_cup_ratio_is_read_and_kept(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    lib = ServeLibrary(tmp_path)
    lib.add(evaluation)
    doc = json.loads(lib.index_path.read_text())
    doc["serves"][0].setdefault("cup_hold", {})["worst_ratio"] = float("inf")  # written by an earlier version
    lib.index_path.write_text(json.dumps(doc))
    assert lib.entries()[0].data["cup_hold"]["worst_ratio"] == float("inf")
    lib.add(evaluation)  # a write keeps it as it was
    assert json.loads(lib.index_path.read_text())["serves"][0]["cup_hold"]["worst_ratio"] == float("inf")
    doc["serves"][0]["cup_hold"]["worst_ratio"] = float("nan")  # NaN never
    lib.index_path.write_text(json.dumps(doc))
    with pytest.raises(DataFileError, match=r"serves\[0\].cup_hold.worst_ratio"):
        lib.entries()


def test_export_writes_arrays_first_and_removes_them_when_the_index_write_fails(tmp_path: Path, evaluation, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    import studio.library.store as L

    lib = ServeLibrary(tmp_path)
    first = lib.add(evaluation)
    original = lib.index_path.read_bytes()
    written: list[str] = []
    real = L._atomic_write

    def failing(path: Path, data: bytes) -> None:
        written.append(path.name)
        if path.name == INDEX_NAME:
            raise OSError(28, "No space left on device")
        real(path, data)

    monkeypatch.setattr(L, "_atomic_write", failing)
    with pytest.raises(OSError, match="No space"):
        lib.add(evaluation)
    assert written[0].endswith(".npz") and written[1] == INDEX_NAME  # arrays first, index last
    assert lib.index_path.read_bytes() == original
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == [first.data["arrays"]]  # no orphan NPZ


@pytest.mark.parametrize(
    "raw, message",
    [
        (b'{"schema": "serve-studio/library@1", "serves": [], "n": ' + b"9" * 5000 + b"}", "an integer of 5000 digits"),
        (b"[" * 100_000 + b"]" * 100_000, "nested 100000 levels deep, more than the 64 allowed"),
        (b'{"schema": "serve-studio/library@1", "serves": [], "name": "\xed\xa0\x80"}', "not UTF-8 text"),
    ],
    ids=["5000-digit integer", "nested 100000 deep", "encoded lone surrogate"],
)
def test_unparsable_index_is_reported_and_kept(tmp_path: Path, raw: bytes, message: str) -> None:
    from studio.library.match import record_point, sync_usage

    lib = ServeLibrary(tmp_path)
    lib.index_path.write_bytes(raw)
    for write in (lambda: record_point(lib, server="opponent", winner="robot"), lambda: sync_usage(lib, [])):
        with pytest.raises(DataFileError, match=f"index.json: {message}"):
            write()
    assert lib.index_path.read_bytes() == raw and sorted(p.name for p in tmp_path.iterdir()) == [".lock", INDEX_NAME]


def test_library_files_are_group_readable_and_links_out_are_refused(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    """Files get the umask's mode (a controller of the group can read them); a pruned/ or
    matches.jsonl that is a symlink is refused, nothing written outside the library; an NPZ
    that is a FIFO or links out is refused at once by validate."""
    import os
    import stat
    import subprocess
    import sys

    from studio.library.match import MATCH_LOG, Point, append_point, prune

    lib = ServeLibrary(tmp_path / "lib")
    entry = lib.add(evaluation)
    umask = os.umask(0o022)
    os.umask(umask)
    for path in (lib.index_path, tmp_path / "lib" / entry.data["arrays"]):
        assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (tmp_path / "lib" / "pruned").symlink_to(outside)
    with pytest.raises(DataFileError, match="pruned: is a symbolic link"):
        prune(lib, [entry.id])
    assert list(outside.iterdir()) == [] and lib.get(entry.id)
    (tmp_path / "lib" / MATCH_LOG).symlink_to(outside / "log.jsonl")
    with pytest.raises(DataFileError, match="is a symbolic link"):
        append_point(tmp_path / "lib" / MATCH_LOG, Point(time="2026-01-01T00:00:00+00:00", server="robot", serve=entry.id, winner="robot", ace=False, opponent="x"))
    assert not (outside / "log.jsonl").exists()
    (tmp_path / "lib" / MATCH_LOG).unlink()
    npz = tmp_path / "lib" / entry.data["arrays"]
    npz.unlink()
    os.mkfifo(npz)
    out = subprocess.run([sys.executable, "-m", "studio.cli", "library", "validate", str(tmp_path / "lib")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and "not a regular file" in out.stderr and "Traceback" not in out.stderr


def test_validate_names_orphan_files(tmp_path: Path, evaluation) -> None:  # type: ignore[no-untyped-def]
    from studio.library.store import orphan_files

    lib = ServeLibrary(tmp_path / "lib")
    entry = lib.add(evaluation)
    (tmp_path / "lib" / "ghost-0000.npz").write_bytes(b"x")
    (tmp_path / "lib" / ".index.json.abc.tmp").write_bytes(b"x")
    assert orphan_files(lib, lib.entries()) == [".index.json.abc.tmp", "ghost-0000.npz"]
    assert entry.data["arrays"] not in orphan_files(lib, lib.entries())
