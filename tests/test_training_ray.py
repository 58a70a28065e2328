"""Training on Ray when things go wrong (issue 18): the driver keeps only records it does not
hold, a lost worker's run is resubmitted from the driver's current log, failures end in one
message and a log that a rerun resumes.

Classes covered: repeated and conflicting records from a task (unit), a run log with
repeated indices (the old retry bug) or without its run.json (refused before Ray is
reached, CLI exit 2), Ray's failure exceptions (classified: lost worker or not), a cluster
without CPUs, and a task's worker killed mid-run on a local Ray instance (retries off: the
training ends with a message; on: resubmitted from the log; both times no duplicate index
and a rerun completes). The two-raylet cluster with a node killed: test_training_ray_cluster.py.
"""

from __future__ import annotations

import json
import logging
import os
import signal
from pathlib import Path
from typing import Any

import pytest

import studio.optimize.training as training
from studio.errors import DataFileError
from studio.optimize.training import TrainConfig, TrainingFailedError, train_serves

EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "serves"


def _record(index: int, genome: list[float]) -> dict[str, Any]:
    params = {f"g{k}": 0.0 for k in range(10)}
    return {
        "index": index, "batch": 0, "source": "hebo", "genome": genome, "params": params, "reward": -1.0,
        "legal": False, "status": "ok", "failed_check": "net", "legal_fraction": 0.0, "seconds": 0.01,
    }  # fmt: skip


def _run(tmp_path: Path) -> training._RayRun:
    run_dir = tmp_path / "000-right-seed0"
    return training._open_run(0, "right", 0, run_dir)


def _indices(run_dir: Path) -> list[int]:
    return [json.loads(line)["index"] for line in (run_dir / "evaluations.jsonl").read_text().splitlines()]


def test_driver_appends_only_the_next_record(tmp_path: Path) -> None:
    run = _run(tmp_path)
    try:
        training._accept(run, _record(0, [0.1] * 10))
        training._accept(run, _record(1, [0.2] * 10))
        training._accept(run, _record(1, [0.2] * 10))  # a repeat: dropped, counted
        training._accept(run, _record(0, [0.1] * 10))
        assert run.repeated == 2
        with pytest.raises(training._RunFailed, match="record 1 with another genome"):
            training._accept(run, _record(1, [0.3] * 10))
        with pytest.raises(training._RunFailed, match="index 5 after the log's 2 records"):
            training._accept(run, _record(5, [0.3] * 10))
        with pytest.raises(training._RunFailed, match="index None"):
            training._accept(run, {"genome": [0.0] * 10})
    finally:
        run.log.close()
    assert _indices(run.run_dir) == [0, 1]


def test_a_resubmitted_task_gets_the_driver_log(tmp_path: Path) -> None:
    run = _run(tmp_path)
    (run.run_dir / "run.json").write_text("{}")
    sent: list[tuple[Any, ...]] = []

    class Task:
        @staticmethod
        def remote(*args: Any) -> str:
            sent.append(args)
            return f"task{len(sent)}"

    cfg = TrainConfig(task="backspin", count=1, side="right", runs_dir=tmp_path)
    try:
        training._submit(Task, run, cfg)
        for k in range(3):
            training._accept(run, _record(k, [k / 10] * 10))
        training._submit(Task, run, cfg)
    finally:
        run.log.close()
    assert sent[0][3:] == (None, b"")  # a new run
    assert sent[1][3] == "{}" and sent[1][4].count(b"\n") == 3  # the three records received since
    assert run.task == "task2" and run.node == ""


def _write_log(run_dir: Path, indices: list[int], *, meta: bool = True) -> bytes:
    from studio.optimize.optimizer import RUN_SCHEMA

    run_dir.mkdir(parents=True)
    if meta:
        (run_dir / "run.json").write_text(json.dumps({"schema": RUN_SCHEMA}))
    text = "".join(json.dumps(_record(i, [i / 10] * 10)) + "\n" for i in indices).encode()
    (run_dir / "evaluations.jsonl").write_bytes(text)
    return text


@pytest.mark.parametrize(
    ("indices", "meta", "message"),
    [
        ([0, 1, 2, 0, 1], True, r"line 4: record 3 has index 0 and repeats line 1 .*keep only them \(e.g. head -n 3\)"),
        ([0, 2], True, r"line 2: record 1 has index 2: not one run's log"),
        ([0, 1], False, r"2 evaluations but no run.json beside it"),
    ],
)
def test_a_broken_run_log_is_refused_before_ray_is_reached(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], indices: list[int], meta: bool, message: str
) -> None:
    from studio.cli import main

    cfg = TrainConfig(task="backspin", count=1, side="right", runs_dir=tmp_path / "runs")
    run_dir = cfg.jobs()[0][3]
    before = _write_log(run_dir, indices, meta=meta)
    with pytest.raises(DataFileError, match=message):
        training._open_run(0, "right", 0, run_dir)
    argv = ["train", "--task", "backspin", "--count", "1", "--side", "right", "--runs", str(tmp_path / "runs")]
    code = main([*argv, "--library", str(tmp_path / "lib"), "--ray", "no-such-host:1"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "evaluations.jsonl" in err and "cannot start or reach" not in err  # refused before connecting
    assert (run_dir / "evaluations.jsonl").read_bytes() == before  # kept byte for byte


def test_ray_failures_are_classified() -> None:
    from ray import exceptions as rex

    lost = [rex.WorkerCrashedError(), rex.NodeDiedError("node 1 is dead"), rex.ActorUnavailableError("gone", None),
            rex.ActorDiedError(), rex.ObjectLostError("ab" * 14, None, "")]  # fmt: skip
    for exc in lost:
        assert training._lost_worker(exc) is not None, exc
    wrapped = rex.RayTaskError("_ray_job", "Traceback ...", rex.NodeDiedError("node 2 is dead"))
    assert training._lost_worker(wrapped) == "NodeDiedError: node 2 is dead"
    bug = rex.RayTaskError("_ray_job", "Traceback ...", ValueError("bad value\nsecond line"))
    assert training._lost_worker(bug) is None
    assert training._first_line(bug) == "ValueError: bad value"
    assert training._lost_worker(rex.TaskCancelledError()) is None


def test_a_cluster_without_cpus_ends_the_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    import ray

    cpus = {"CPU": 0.0}
    monkeypatch.setattr(ray, "cluster_resources", lambda: cpus)
    clock = [0.0]
    monkeypatch.setattr(training.time, "monotonic", lambda: clock[0])
    watch = training._CpuWatch(limit=30.0, every=5.0, last=-10.0)
    for t in (0.0, 10.0, 20.0):
        clock[0] = t
        watch.check()
    cpus["CPU"] = 1.0  # a node came back: the count starts again
    clock[0] = 26.0
    watch.check()
    cpus["CPU"] = 0.0
    for t in (31.0, 40.0, 50.0, 60.0):
        clock[0] = t
        watch.check()
    clock[0] = 70.0
    with pytest.raises(training._NoCpu, match="no CPU for 30 s"):
        watch.check()


def _cfg(tmp_path: Path, **kw: Any) -> TrainConfig:
    from studio.serve.params import load_serve

    seed_serve = load_serve(EXAMPLES / "topspin_right.json")
    return TrainConfig(task="topspin_velocity", count=2, side="right", iterations=ITERATIONS, population=2, tosses=1,
                       workers=1, seeds=(seed_serve,), runs_dir=tmp_path / "runs", **kw)  # fmt: skip


ITERATIONS = 6
"""HEBO batches of 2 per run: 13 records (the seed first), so that a kill after the 2nd record
lands while the task still has records to send (with 5 a fast task could stream them all
before the kill and leave nothing to resume)."""
RECORDS = 1 + 2 * ITERATIONS


def _kill_worker_of_run_0_at(monkeypatch: pytest.MonkeyPatch, records: int) -> list[int]:
    """Make the driver SIGKILL run 0's task worker once it holds ``records`` records."""
    real, pids, killed = training._on_item, {}, []

    def on_item(run: training._RayRun, item: Any) -> Any:
        if item.get("kind") == "start":
            pids[run.index] = item["pid"]
        out = real(run, item)
        if run.index == 0 and not killed and len(run.genomes) == records:
            os.kill(pids[0], signal.SIGKILL)
            killed.append(pids[0])
        return out

    monkeypatch.setattr(training, "_on_item", on_item)
    return killed


@pytest.mark.slow
def test_a_killed_task_worker_ends_in_a_message_or_a_resubmission(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=80 * 1024 * 1024)
    try:
        # retries off: the killed run is reported, the other one finishes
        killed = _kill_worker_of_run_0_at(monkeypatch, 2)
        with pytest.raises(TrainingFailedError) as err:
            train_serves(_cfg(tmp_path, ray_retries=0), tmp_path / "lib", ray_address="auto")
        run0, run1 = (job[3] for job in _cfg(tmp_path).jobs())
        text = str(err.value)
        assert killed and "1 of the 2 runs trained on Ray did not finish" in text
        assert f"{run0}: lost its Ray worker 1 times (last: WorkerCrashedError" in text
        assert "Run the same command again to resume them" in text
        held = _indices(run0)
        assert held == list(range(len(held))) and 2 <= len(held) < RECORDS and not (run0 / "exported.json").exists()
        assert (run1 / "exported.json").exists() and _indices(run1) == list(range(RECORDS))
        # the rerun resumes run 0 from its log; its worker is killed again and resubmitted
        killed = _kill_worker_of_run_0_at(monkeypatch, len(held) + 1)
        with caplog.at_level(logging.WARNING, logger="studio.optimize.training"):
            results = train_serves(_cfg(tmp_path), tmp_path / "lib", ray_address="auto")
        assert killed and "resubmitted in 1 s from the" in caplog.text and "(retry 1 of 3)" in caplog.text
        assert [r.reason == "already trained" for r in results] == [False, True]
        assert _indices(run0) == list(range(RECORDS))  # nothing lost, nothing repeated
        assert (run0 / "exported.json").exists()
    finally:
        ray.shutdown()
