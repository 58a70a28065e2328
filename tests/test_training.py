"""Training many serves: run layout, summary beside the paper's Table II, local and Ray runs, resume."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from studio.errors import InvalidInputError
from studio.library.store import ServeLibrary
from studio.serve.params import serve_from_json
from studio.optimize.training import PAPER_TABLE_II_SIM, TrainConfig, TrainedServe, summary_table, train_serves


def test_jobs_alternate_sides_and_seeds(tmp_path: Path) -> None:
    cfg = TrainConfig(task="backspin", count=3, side="both", seed=7, runs_dir=tmp_path)
    assert [(i, side, seed, d.name) for i, side, seed, d in cfg.jobs()] == [
        (0, "right", 7, "000-right-seed7"), (1, "left", 8, "001-left-seed8"), (2, "right", 9, "002-right-seed9"),
    ]  # fmt: skip
    assert {side for _, side, _, _ in TrainConfig(task="backspin", count=2, side="left").jobs()} == {"left"}


@pytest.mark.parametrize("kw", [{"task": "nope"}, {"task": "aiming", "count": 0}, {"task": "aiming", "side": "up"}, {"task": "aiming", "tosses": 0}, {"task": "aiming", "robustify": -1}, {"task": "aiming", "robustify": 2.5}])
def test_bad_configuration_is_rejected(kw: dict) -> None:
    with pytest.raises(InvalidInputError):
        TrainConfig(**kw)


def test_summary_table_statistics_and_paper_row(tmp_path: Path) -> None:
    rows = [{"aim_mm": 100.0, "vx": 3.0, "vy": -1.0, "vz": 2.0, "cork": 10.0, "topback": 100.0, "side": -50.0},
            {"aim_mm": 300.0, "vx": 5.0, "vy": 1.0, "vz": 2.0, "cork": 30.0, "topback": 300.0, "side": 50.0}]  # fmt: skip
    results = [TrainedServe(i, tmp_path, True, 1.0, r, f"id{i}", 1.0) for i, r in enumerate(rows)]
    results.append(TrainedServe(2, tmp_path, False, -3.0, {}, None, 1.0, "net"))
    text = summary_table(results, "aiming")
    assert "2 legal of 3 trained serves" in text
    ours = next(line for line in text.splitlines() if line.startswith("| this run"))
    assert "| 2 |" in ours and "200.0 ± 100.0" in ours and "4.0 ± 1.0" in ours and "200.0 ± 100.0" in ours
    paper = next(line for line in text.splitlines() if line.startswith("| paper"))
    assert "166.0 ± 285.0" in paper and "2.6 ± 1.2" in paper
    assert "aim error" not in summary_table(results, "backspin")  # aim error only for the aiming task
    assert set(PAPER_TABLE_II_SIM) == {"aiming", "topspin_velocity", "backspin", "sidespin"}


def _cfg(tmp_path: Path, iterations: int) -> TrainConfig:
    from studio.serve.params import load_serve

    seed_serve = load_serve(Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json")
    return TrainConfig(task="topspin_velocity", count=2, side="right", iterations=iterations, population=2, tosses=1, workers=1, seeds=(seed_serve,), runs_dir=tmp_path / "runs")


def test_training_on_ray_streams_records_resumes_and_exports(tmp_path: Path) -> None:
    import studio.optimize.training  # noqa: F401  (sets RAY_ENABLE_UV_RUN_RUNTIME_ENV=0 before ray is imported)

    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=80 * 1024 * 1024)
    try:
        # run 0 was started locally and interrupted after its first batch: a partial log, not exported
        cfg1 = _cfg(tmp_path, iterations=1)
        from studio.optimize.training import _run_job

        run0 = cfg1.jobs()[0][3]
        _run_job("right", 0, cfg1, run0, workers=1)
        assert len((run0 / "evaluations.jsonl").read_text().splitlines()) == 3  # the seed + 2 suggestions
        cfg = _cfg(tmp_path, iterations=2)
        done: list[int] = []
        results = train_serves(cfg, tmp_path / "lib", ray_address="auto", progress=lambda r, n: done.append(r.index))
        assert sorted(done) == [0, 1] and len(results) == 2
        for r in results:
            lines = [json.loads(x) for x in (r.run_dir / "evaluations.jsonl").read_text().splitlines()]
            assert [x["index"] for x in lines] == list(range(5))  # seed + 2 x 2, nothing repeated
            assert json.loads((r.run_dir / "run.json").read_text())["task"] == "topspin_velocity"
            done = json.loads((r.run_dir / "exported.json").read_text())
            chosen = serve_from_json(done["serve"])  # the chosen serve, reproducible from the run folder
            assert chosen.side == "right" and done["legal"] == r.legal
        first = [json.loads(x) for x in (results[0].run_dir / "evaluations.jsonl").read_text().splitlines()]
        assert [x["batch"] for x in first] == [-1, 0, 0, 1, 1]  # the local batch kept, the Ray task went on
        entries = ServeLibrary(tmp_path / "lib").entries()
        assert len(entries) == sum(r.legal for r in results)
        assert all(e.data["provenance"]["kind"] == "hebo" for e in entries)
        again = train_serves(cfg, tmp_path / "lib", ray_address="auto")
        assert all(r.reason == "already trained" for r in again)
    finally:
        ray.shutdown()



def test_runs_folder_of_another_limit_scale_is_refused(tmp_path: Path) -> None:
    from studio.serve.params import LimitScale
    from studio.optimize.training import finished_runs

    cfg = TrainConfig(task="backspin", count=1, side="right", runs_dir=tmp_path)
    (_, _, _, run_dir) = cfg.jobs()[0]
    run_dir.mkdir(parents=True)
    from studio.optimize.optimizer import RUN_SCHEMA

    (run_dir / "run.json").write_text(json.dumps({"schema": RUN_SCHEMA, "limit_scale": {"acceleration": 1.5, "jerk": 1.5}}))
    (run_dir / "exported.json").write_text(json.dumps({"id": None, "legal": False, "reward": -3.0, "row": {}}))
    with pytest.raises(InvalidInputError, match="trained with limit_scale .*'acceleration': 1.5.*use another --runs folder"):
        finished_runs(cfg)  # not counted as trained at the robot's limits
    same = TrainConfig(task="backspin", count=1, side="right", runs_dir=tmp_path, limit_scale=LimitScale.uniform(1.5))
    assert len(finished_runs(same)) == 1
    (run_dir / "run.json").write_text("[1, 2]")
    with pytest.raises(InvalidInputError, match="run.json: schema must be"):
        finished_runs(same)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (b'{"reward": 0.5, "row": ', "exported.json: .*JSON"),  # cut short by a kill
        (b"[1, 2]", "exported.json: expected a JSON object"),
        (b'{"reward": "high", "row": {}}', "exported.json: field 'reward': unexpected value 'high'"),
        (b'{"reward": true, "row": {}}', "field 'reward': unexpected value True"),
        (b'{"reward": 0.5, "row": [1]}', "field 'row': unexpected value \\[1\\]"),
        (b'{"reward": 0.5, "row": {"topback": "x"}}', "field 'row'"),
        (b'{"legal": "no", "reward": 0.5}', "field 'legal': unexpected value 'no'"),
        (b'{"id": {"a": 1}, "reward": 0.5}', "field 'id'"),
        (b'{"reward": 0.5, "row": {}}\xff', "exported.json: not UTF-8 text"),
    ],
)
def test_corrupt_exported_json_of_a_finished_run_names_the_file(tmp_path: Path, text: bytes, match: str) -> None:
    """A finished run's exported.json that cannot be read stops the report (``finished_runs``,
    which a resumed training calls first through the same reader) with the file and field
    named, not a raw JSON or type error; the file is left as it is."""
    from studio.errors import DataFileError
    from studio.optimize.training import finished_runs

    cfg = TrainConfig(task="backspin", count=1, side="right", runs_dir=tmp_path)
    (_, _, _, run_dir) = cfg.jobs()[0]
    run_dir.mkdir(parents=True)
    (run_dir / "exported.json").write_bytes(text)
    with pytest.raises(DataFileError, match=match) as info:
        finished_runs(cfg)
    assert info.value.path == str(run_dir / "exported.json")
    assert (run_dir / "exported.json").read_bytes() == text


SEEDED = Path(__file__).resolve().parent.parent / "experiments" / "table2_seeded" / "backspin"


def test_the_seeded_table2_backspin_row_meets_the_target_and_its_serves_evaluate_the_same(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """experiments/table2/RESULTS.md: the 25 seeded backspin runs, all legal, −250.8 ± 14.4
    rad/s after the second bounce (issue #13's target: <= −100 with >= 20 of 25 legal), read
    straight from the committed exported.json files; two chosen serves (one per toss side)
    re-evaluated today give the same ball state and the reward, and hold in the MuJoCo rollout."""
    import numpy as np

    from studio.cli import main
    from studio.serve.evaluate import EvaluationContext, evaluate_serve

    done = [json.loads(p.read_text(encoding="utf-8")) for p in sorted(SEEDED.glob("*/exported.json"))]
    assert len(done) == 25 and sum(bool(d["legal"]) for d in done) == 25
    tb = np.array([d["row"]["topback"] for d in done])
    assert np.all(tb < -150.0) and tb.mean() == pytest.approx(-250.8, abs=0.05) and tb.std() == pytest.approx(14.4, abs=0.05)
    for d in done[:2]:
        serve = serve_from_json(d["serve"])
        assert serve.limit_scale.is_identity  # planned at the robot's own limits
        ev = evaluate_serve(serve, EvaluationContext.default(), task="backspin")
        assert ev.legal and ev.metrics is not None and ev.metrics.second_bounce is not None
        assert ev.metrics.second_bounce["topspin"] == pytest.approx(d["row"]["topback"], abs=0.5)
        assert ev.reward.total == pytest.approx(d["reward"], abs=1e-3)
        path = tmp_path / f"{serve.side}.json"
        path.write_text(json.dumps(d["serve"]), encoding="utf-8")
        assert main(["evaluate", str(path), "--mujoco", "--json", "--task", "backspin"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["legal"] and "mujoco" in out["timings_ms"] and out["net"]["topspin"] < -200.0
