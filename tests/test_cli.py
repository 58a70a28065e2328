"""The serve-studio command line: evaluate (text, JSON, export), optimize, errors."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest

from studio.cli import main
from studio.library.store import ServeLibrary

EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "serves"


def test_evaluate_json_has_the_documented_fields(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code = main(["evaluate", str(EXAMPLES / "topspin_right.json"), "--json", "--export", str(tmp_path / "lib")])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["legal"] is True and out["failed_check"] is None
    for key in ("reward", "terms", "second_bounce", "net_clearance", "max_height", "planner"):
        assert key in out
    for key in ("p", "v", "w", "topspin", "sidespin"):
        assert key in out["second_bounce"]
    assert out["planner"]["status"] == "ok" and out["planner"]["solve_ms"] > 0
    assert len(out["efforts"]["peak"]) == 8 and out["efforts"]["usage"] == pytest.approx([p / lim for p, lim in zip(out["efforts"]["peak"], out["efforts"]["limit"])])
    (entry,) = ServeLibrary(tmp_path / "lib").entries()
    assert entry.id == out["exported"]["id"]


def test_evaluate_text_and_robust(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["evaluate", str(EXAMPLES / "sidespin_right.json"), "--tosses", "4", "--legal-fraction", "0.25"])
    text = capsys.readouterr().out
    assert "over 4 recorded tosses" in text and "check" in text
    assert code in (0, 1)


def test_bad_serve_file_is_a_clear_error(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"name": "x", "side": "right", "params": {"tau": 0.8, "velocity": [1, 2], "yaw": 0, "roll": 0}}))
    assert main(["evaluate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and "params.velocity" in err


def test_optimize_tiny_budget_writes_run_and_best(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    run = tmp_path / "run"
    code = main(["optimize", str(EXAMPLES / "topspin_right.json"), "--iterations", "1", "--population", "2", "--workers", "1", "--run-dir", str(run)])
    out = capsys.readouterr().out
    assert "chosen serve" in out and code in (0, 1)
    assert (run / "best_serve.json").exists() and (run / "evaluations.jsonl").exists()
    assert len((run / "evaluations.jsonl").read_text().splitlines()) == 3  # the seed + 2 suggestions
    with pytest.raises(SystemExit) as usage:
        main(["optimize", str(EXAMPLES / "topspin_right.json"), "--robustify", "-1"])
    assert usage.value.code == 2 and "argument --robustify: '-1' is outside the allowed range" in capsys.readouterr().err


def test_limit_scale_option_evaluates_exports_and_optimizes(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code = main(["evaluate", str(EXAMPLES / "topspin_right.json"), "--json", "--limit-scale", "1.4", "--export", str(tmp_path / "lib")])
    assert code == 0 and json.loads(capsys.readouterr().out)["legal"] is True
    (entry,) = ServeLibrary(tmp_path / "lib").entries()
    assert entry.data["robot"]["limit_scale"] == {"velocity": 1.0, "acceleration": 1.4, "jerk": 1.4}
    assert main(["evaluate", str(EXAMPLES / "topspin_right.json"), "--limit-scale", "jerk=fast"]) == 2
    assert "limit scale 'jerk=fast': jerk must be a number" in capsys.readouterr().err
    run = tmp_path / "run"
    code = main(["optimize", str(EXAMPLES / "topspin_right.json"), "--iterations", "1", "--population", "2", "--workers", "1", "--run-dir", str(run), "--limit-scale", "acceleration=1.2,jerk=1.3"])
    capsys.readouterr()
    assert code in (0, 1)
    best = json.loads((run / "best_serve.json").read_text())
    assert best["limit_scale"] == {"velocity": 1.0, "acceleration": 1.2, "jerk": 1.3}
    assert json.loads((run / "run.json").read_text())["limit_scale"] == best["limit_scale"]
    # without --limit-scale an optimization takes its seed serves' own scale
    seed = tmp_path / "seed.json"
    seed.write_text(json.dumps({**json.loads((EXAMPLES / "topspin_right.json").read_text()), "limit_scale": {"jerk": 1.6}}))
    code = main(["optimize", str(seed), "--iterations", "0", "--workers", "1", "--run-dir", str(tmp_path / "run2")])
    capsys.readouterr()
    assert json.loads((tmp_path / "run2" / "run.json").read_text())["limit_scale"] == {"velocity": 1.0, "acceleration": 1.0, "jerk": 1.6}


def test_train_exports_legal_serves_and_resumes(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    args = ["train", "--task", "topspin_velocity", "--count", "1", "--side", "right", "--library", str(tmp_path / "lib"),
            "--runs", str(tmp_path / "runs"), "--iterations", "1", "--population", "2", "--tosses", "2", "--workers", "1",
            "--seeds", str(EXAMPLES / "topspin_right.json"), "--robustify", "12"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "1 legal of 1 trained serves" in out and "top/back [rad/s]" in out
    (entry,) = ServeLibrary(tmp_path / "lib").entries()
    assert entry.data["provenance"]["kind"] == "hebo" and entry.data["legal"] is True
    robust_log = tmp_path / "runs" / "000-right-seed0" / "robustify" / "robustify.jsonl"
    assert len(robust_log.read_text().splitlines()) == 12  # the chosen serve was robustified before export
    assert main(args) == 0  # a second invocation finds the finished run and trains nothing
    assert "already trained" in capsys.readouterr().out
    assert len(ServeLibrary(tmp_path / "lib").entries()) == 1
    report = ["train", "--task", "topspin_velocity", "--count", "3", "--side", "right", "--runs", str(tmp_path / "runs"), "--report"]
    assert main(report) == 0  # the summary of what is finished, no library needed, nothing trained
    out = capsys.readouterr().out
    assert "1 of 3 topspin_velocity runs finished" in out and "1 legal of 1 trained serves" in out
    assert not (tmp_path / "runs" / "001-right-seed1").exists()
    assert main(report[:-1]) == 2  # training needs --library


def test_in_process_training_gets_single_thread_pools(monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    from studio.cli import single_thread_pools
    from studio.optimize.threads import THREAD_VARS

    for var in THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "4")  # a user's own setting is kept
    assert not single_thread_pools(argparse.Namespace(command="train", workers=2, ray=None))
    assert not single_thread_pools(argparse.Namespace(command="evaluate"))
    assert "OMP_NUM_THREADS" not in os.environ
    assert single_thread_pools(argparse.Namespace(command="train", workers=1, ray=None))
    assert os.environ["OMP_NUM_THREADS"] == os.environ["OPENBLAS_NUM_THREADS"] == "1" and os.environ["MKL_NUM_THREADS"] == "4"


def test_robustify_reports_and_writes_only_an_improvement(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    src = tmp_path / "serve.json"
    src.write_text((EXAMPLES / "sidespin_left.json").read_text())
    code = main(["robustify", str(src), "--evaluations", "12", "--run-dir", str(tmp_path / "run")])
    out = capsys.readouterr().out
    start = re.search(r"Start: legal on (\d+)/20 recorded tosses, net spin top/back ([-+]\d+), side ([-+]\d+) rad/s", out)
    keep = re.search(r"keeping topspin >= (\d+) and sidespin \(-\) >= (\d+) rad/s at the net", out)
    assert start and keep, out
    # the start's count and spins agree with `evaluate --tosses 20` (another code path)
    assert main(["evaluate", str(src), "--tosses", "20", "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert int(start.group(1)) == round(20 * ev["legal_fraction"])
    top, side = int(start.group(2)), int(start.group(3))
    assert abs(int(keep.group(1)) - 0.9 * abs(top)) <= 1 and abs(int(keep.group(2)) - 0.9 * abs(side)) <= 1
    written = tmp_path / "serve_robust.json"
    assert (code == 0) == written.exists()  # written only when a candidate beat the start
    assert len((tmp_path / "run" / "robustify.jsonl").read_text().splitlines()) == 12
    code = main(["robustify", str(src), "--evaluations", "24", "--run-dir", str(tmp_path / "run"), "--resume"])
    capsys.readouterr()
    assert len((tmp_path / "run" / "robustify.jsonl").read_text().splitlines()) == 24  # 12 replayed, 12 new
    with pytest.raises(SystemExit) as usage:
        main(["robustify", str(src), "--keep-spin", "2"])
    assert usage.value.code == 2 and "argument --keep-spin: '2' is outside the allowed range [0, 1]" in capsys.readouterr().err


EXAMPLE_FILES = sorted(EXAMPLES.glob("*.json"))


@pytest.fixture(scope="module")
def analytic() -> dict[str, dict]:  # type: ignore[type-arg]
    """The analytic verdict of every example serve (one shared context)."""
    from studio.serve.evaluate import EvaluationContext, evaluate_serve
    from studio.serve.params import load_serve

    context = EvaluationContext.default()
    out = {}
    for path in EXAMPLE_FILES:
        serve = load_serve(path)
        out[path.stem] = evaluate_serve(serve, context, task=serve.task or "topspin_velocity").to_json()
    return out


@pytest.mark.parametrize("path", EXAMPLE_FILES, ids=[p.stem for p in EXAMPLE_FILES])
def test_evaluate_mujoco_agrees_with_the_analytic_verdict(path: Path, analytic: dict, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[type-arg]
    """The MuJoCo rollout follows the ball to the end of its flight (past the end of the
    robot's motion: the issue's "X covers 1496 samples, t_end needs 2524") and gives the
    analytic verdict. Its toss differs a little (released from the predicted cup motion,
    not the recorded mean path): strikes ~1-2 ms apart, bounces within a few cm."""
    code = main(["evaluate", str(path), "--mujoco", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    mj, an = json.loads(captured.out), analytic[path.stem]
    assert "mujoco" in mj["timings_ms"]  # the verdict is the rollout's
    assert (mj["status"], mj["legal"], mj["failed_check"]) == (an["status"], an["legal"], an["failed_check"]) == ("legal", True, None)
    assert [c["passed"] for c in mj["checks"]] == [c["passed"] for c in an["checks"]]
    assert len(mj["bounces"]) >= 2 and len(an["bounces"]) == 2
    np.testing.assert_allclose(np.array(mj["bounces"][:2])[:, :2], np.array(an["bounces"])[:, :2], atol=0.08)
    assert mj["net_clearance"] == pytest.approx(an["net_clearance"], abs=0.02)
    assert mj["reward"] == pytest.approx(an["reward"], abs=0.05)


def test_evaluate_refuses_mujoco_with_several_tosses(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", str(EXAMPLES / "topspin_right.json"), "--mujoco", "--tosses", "3"]) == 2
    err = capsys.readouterr().err
    assert "--mujoco cannot be combined with --tosses > 1" in err and "recorded tosses" in err


def test_robust_export_stores_the_mean_toss_evaluation(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """evaluate --tosses N --export: the library gets the plan with the mean toss's ball
    path and verdict (as optimize/train export), never one sampled toss's evaluation
    under the serve's name; the robust result is recorded beside it."""
    from studio.serve.evaluate import EvaluationContext, evaluate_serve
    from studio.serve.params import load_serve

    path = EXAMPLES / "sidespin_right.json"
    code = main(["evaluate", str(path), "--json", "--tosses", "4", "--legal-fraction", "0.25", "--export", str(tmp_path / "lib")])
    out = json.loads(capsys.readouterr().out)
    assert code == (0 if out["legal"] else 1)
    assert out["tosses"] == 4 and out["metrics_toss_sample"] == out["per_toss"][0]["toss_sample"]
    assert len({p["toss_sample"] for p in out["per_toss"]}) == 4
    (entry,) = ServeLibrary(tmp_path / "lib").entries()
    serve = load_serve(path)
    mean = evaluate_serve(serve, EvaluationContext.default(), task=serve.task or "topspin_velocity")
    assert entry.data["legal"] == mean.legal and entry.data["reward"] == pytest.approx(mean.reward.total)
    assert out["exported"] == {"library": str(tmp_path / "lib"), "id": entry.id, "toss": "mean", "legal": mean.legal, "reward": pytest.approx(mean.reward.total)}
    np.testing.assert_allclose(entry.arrays()["ball_p"], mean.ball.p)  # type: ignore[union-attr]
    robust = entry.data["provenance"]["robust"]
    assert robust["tosses"] == 4 and robust["legal"] == out["legal"] and robust["legal_fraction"] == out["legal_fraction"]
    assert robust["toss_samples"] == [p["toss_sample"] for p in out["per_toss"]] and robust["mean_reward"] == pytest.approx(out["reward"])
    # the text output names the toss its checks belong to and what was exported
    main(["evaluate", str(path), "--tosses", "4", "--export", str(tmp_path / "lib2")])
    text = capsys.readouterr().out
    assert f"checks and metrics of recorded toss {robust['toss_samples'][0] + 1} (the first of 4 drawn" in text
    assert "the mean toss path's evaluation" in text and "the robust result is in its provenance" in text


@pytest.mark.parametrize("name, check", [
    ("largest_backspin", lambda net: net["topspin"] <= -300.0),
    ("fastest", lambda net: net["speed"] >= 7.0),
    ("spinniest_within_efforts", lambda net: math.hypot(*net["w"]) > 550.0 and net["speed"] > 6.7),
    ("largest_backspin_within_efforts", lambda net: net["topspin"] <= -300.0),
])  # fmt: skip
def test_envelope_serves_hold_in_the_mujoco_rollout(capsys: pytest.CaptureFixture[str], name: str, check: object) -> None:
    """The envelope's claims (experiments/envelope/README.md) in the MuJoCo rollout: ball in
    the cup, released by the predicted motion, racket contact found by MuJoCo's geometry."""
    path = Path(__file__).resolve().parent.parent / "experiments" / "envelope" / f"{name}.json"
    assert main(["evaluate", str(path), "--mujoco", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["legal"] and check(out["net"])  # type: ignore[operator]


def test_calibrate_refuses_bad_input_before_any_fit(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["calibrate", "--match", str(tmp_path / "missing.csv")]) == 2
    err = capsys.readouterr().err
    assert "missing.csv" in err and "not found" in err
    bad = tmp_path / "match.csv"
    bad.write_bytes(b"player_id,rally_id\n\xff\xfe\n")
    assert main(["calibrate", "--match", str(bad)]) == 2
    assert "match.csv" in capsys.readouterr().err
    assert main(["calibrate", "--serve-contacts", str(bad), "--no-serve-contacts"]) == 2
    assert "exclude each other" in capsys.readouterr().err


def test_calibrate_prints_one_table_of_every_model(capsys: pytest.CaptureFixture[str]) -> None:
    """The shipped data and the shared match file (skipped where ../shared is absent)."""
    from studio.physics.flight_calibration import DEFAULT_MATCH_CSV

    if not DEFAULT_MATCH_CSV.is_file():
        pytest.skip(f"match data not found at {DEFAULT_MATCH_CSV} (not shipped: ../shared/data/ace_match/)")
    assert main(["calibrate", "--no-cv", "--folds", "2"]) == 0
    out = capsys.readouterr().out
    row = re.search(r"racket_01\s+serve_contacts\s+([\d.]+) m/s\s+([\d.]+) rad/s \|\s+([\d.]+) m/s\s+([\d.]+) rad/s", out)
    assert row, out
    assert float(row.group(3)) < 1.25 and float(row.group(4)) < 40.0  # the refit, 2-fold CV
    rally = re.search(r"rally shot->bounce \(\d+\)\s+landing error median \[mm\]\s+([\d.]+)\s+([\d.]+)", out)
    assert rally and float(rally.group(2)) < 110.0 < float(rally.group(1))  # after < target < before


def test_export_beyond_the_effort_limits_is_refused_unless_raised(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """backspin_heavy_right (limits x2) needs more gantry_x force than the robot's limit: the
    report is printed, the export refused with the flag that would raise the limit; with
    the flag the entry is written and records the raised limit."""
    path = str(EXAMPLES / "backspin_heavy_right.json")
    assert main(["evaluate", path, "--export", str(tmp_path / "lib")]) == 1
    text = capsys.readouterr().out
    assert "Joint efforts EXCEED the limits" in text and "not exported" in text and "--effort-limit gantry_x=" in text
    assert not (tmp_path / "lib" / "index.json").exists()
    assert main(["evaluate", path, "--json", "--export", str(tmp_path / "lib"), "--effort-limit", "gantry_x=5200"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["efforts"]["raised"] == ["gantry_x"] and out["efforts"]["within"] is True
    (entry,) = ServeLibrary(tmp_path / "lib").entries()
    assert entry.id == out["exported"]["id"] and entry.data["robot"]["efforts"]["limit"][0] == 5200.0
    assert main(["evaluate", path, "--effort-limit", "gantry_x=-1"]) == 2
    assert "gantry_x: must be a finite number > 0" in capsys.readouterr().err


def test_toss_generate_writes_recordings_then_summarizes_them(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["toss", "--generate", "--out", str(tmp_path), "--n", "4", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "right.csv").exists() and (tmp_path / "left.csv").exists() and "wrote" in out
    ids = {line.split(",")[0] for line in (tmp_path / "right.csv").read_text().splitlines() if line and not line.startswith(("#", "toss_id"))}
    assert len(ids) == 4
