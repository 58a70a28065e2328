"""Training many serves for one task (the paper's "4 tasks x 25 serves" experiment).

:func:`train_serves` runs ``count`` HEBO optimizations (:func:`studio.optimize.optimizer.optimize_serve`),
run ``i`` on toss side ``sides[i % len(sides)]`` with seed ``seed + i``, each into its own
run folder ``runs_dir/<i>-<side>-seed<k>`` (``run.json``, ``evaluations.jsonl``); the
chosen serve of each run is evaluated on the mean toss and exported to the serve library
when it is legal (provenance: the run folder). :func:`summary_table` prints the
statistics of the legal serves beside the paper's Table II simulation rows.

Where the runs execute:

- locally (default): one run after the other, each with ``workers`` evaluation processes
  (the evaluations of a run are what is parallel);
- on a Ray cluster (``ray_address``, e.g. ``"auto"`` or ``"ray://host:10001"``; ``"local"``
  starts a private local Ray instance): every run is one Ray task (1 CPU, evaluation in
  the task's process), as many at once as the cluster has CPUs. Each task streams its
  evaluation records back to this process as they are made, which appends them to the
  local run folder, so the run folders, the library and resuming work as in local mode
  (the nodes need no shared file system).

``exported.json`` in a finished run folder holds the verdict on the mean toss, the summary
row and the chosen serve (hand-serve JSON, so ``serve-studio evaluate`` reproduces it).

Resume: a run whose folder holds ``exported.json`` is finished and skipped; a run with a
partial ``evaluations.jsonl`` continues without repeating an evaluation (in Ray mode the
partial log is sent to the task). Records in flight when the driver is killed are lost
(at most the batch being evaluated per run).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from studio.errors import InvalidInputError
from studio.serve.params import HandServe, LimitScale, TossSide

# Ray >= 2.45 notices a driver started by ``uv run`` (as ``./dev`` does) and starts its
# workers with ``uv run`` too, packaging the working directory; here that failed ("worker
# startup repeatedly failed"). The workers run the driver's interpreter instead; a remote
# cluster's nodes need the environment installed (``uv sync`` of this project).
os.environ.setdefault("RAY_ENABLE_UV_RUN_RUNTIME_ENV", "0")

SideChoice = Literal["right", "left", "both"]

PAPER_TABLE_II_SIM: dict[str, dict[str, tuple[float, float]]] = {
    "aiming": {
        "aim_mm": (166, 285),
        "vx": (2.6, 1.2),
        "vy": (-0.9, 0.4),
        "vz": (2.3, 0.3),
        "cork": (26.9, 41.6),
        "topback": (60.0, 129.0),
        "side": (-12.9, 124.6),
    },
    "topspin_velocity": {
        "vx": (4.5, 1.3),
        "vy": (-0.7, 0.8),
        "vz": (2.0, 0.1),
        "cork": (33.8, 44.2),
        "topback": (218.0, 75.4),
        "side": (38.2, 143.8),
    },
    "backspin": {
        "vx": (2.7, 0.9),
        "vy": (-0.9, 0.5),
        "vz": (1.7, 0.1),
        "cork": (-68.9, 70.5),
        "topback": (-164.7, 128.0),
        "side": (19.1, 113.3),
    },
    "sidespin": {
        "vx": (3.5, 0.8),
        "vy": (-0.4, 0.8),
        "vz": (1.9, 0.1),
        "cork": (13.2, 44.1),
        "topback": (124.4, 108.0),
        "side": (84.3, 243.8),
    },
}
"""The paper's Table II, "Sim (N = 25)" rows: mean and std of the ball at the second
bounce per task (aim error [mm], velocity [m/s], spin components [rad/s])."""

COLUMNS = {
    "aim_mm": "aim error [mm]",
    "vx": "v_x [m/s]",
    "vy": "v_y [m/s]",
    "vz": "v_z [m/s]",
    "cork": "cork [rad/s]",
    "topback": "top/back [rad/s]",
    "side": "side [rad/s]",
}
"""Summary columns (keys of :attr:`TrainedServe.row`) and their headings."""


@dataclass(frozen=True)
class TrainConfig:
    """What :func:`train_serves` trains."""

    task: str
    """Reward task preset (:func:`studio.serve.reward.task_weights`)."""
    count: int = 25
    """Number of serves (HEBO runs)."""
    side: SideChoice = "both"
    """Toss side of the runs; ``both`` alternates right, left, right, ..."""
    iterations: int = 100
    """HEBO batches per run (paper: 100)."""
    population: int = 20
    """Suggestions per batch (paper: 20)."""
    tosses: int = 5
    """Recorded tosses per training evaluation (robust training)."""
    seed: int = 0
    """Seed of run 0; run i uses ``seed + i``."""
    workers: int = 2
    """Evaluation processes per run in local mode (Ray tasks evaluate in their process)."""
    seeds: tuple[HandServe, ...] = ()
    """Hand-designed seed serves (each run gets those of its side)."""
    runs_dir: Path = field(default_factory=lambda: Path("runs"))
    """Folder of the run folders."""
    overlap: bool | None = None
    """Suggest the next batch while the current one is evaluated (``optimize_serve``'s
    ``overlap``; ``None``: when a run has 2+ evaluation processes)."""
    limit_scale: LimitScale = field(default_factory=LimitScale)
    """Dynamic limit expansion of every run (``optimize_serve``'s ``limit_scale``); a
    resumed run must have been started with the same scale."""
    robustify: int = 0
    """Candidates of the local robustness search (:func:`studio.optimize.robust.robustify_serve`)
    run on each chosen serve before it is judged and exported (0: none). Logged in
    ``<run>/robustify/`` and resumed with the run."""

    def __post_init__(self) -> None:
        from studio.serve.reward import task_weights

        task_weights(self.task)
        if self.count < 1 or self.iterations < 0 or self.population < 1 or self.tosses < 1 or self.workers < 1:
            raise InvalidInputError(
                f"train: count, population, tosses and workers must be >= 1 and iterations >= 0 (got {self.count}, {self.population}, {self.tosses}, {self.workers}, {self.iterations})"
            )
        if isinstance(self.robustify, bool) or not isinstance(self.robustify, int) or self.robustify < 0:
            raise InvalidInputError(
                f"train: robustify must be a whole number of candidates >= 0, got {self.robustify!r}"
            )
        if self.side not in ("right", "left", "both"):
            raise InvalidInputError(f"train: side must be right, left or both, got {self.side!r}")

    def jobs(self) -> list[tuple[int, TossSide, int, Path]]:
        """(index, side, seed, run folder) of every run."""
        sides: list[TossSide] = ["right", "left"] if self.side == "both" else [self.side]  # type: ignore[list-item]
        out = []
        for i in range(self.count):
            side = sides[i % len(sides)]
            out.append((i, side, self.seed + i, Path(self.runs_dir) / f"{i:03d}-{side}-seed{self.seed + i}"))
        return out


@dataclass(frozen=True)
class TrainedServe:
    """One finished run."""

    index: int
    """Run number."""
    run_dir: Path
    """Its run folder."""
    legal: bool
    """Chosen serve legal on the mean toss."""
    reward: float
    """Its reward on the mean toss [-]."""
    row: dict[str, float]
    """Ball state at the second bounce (keys of :data:`COLUMNS`) when legal."""
    entry_id: str | None
    """Library id (legal serves within the robot's effort limits only)."""
    seconds: float
    """Wall time of the run [s] (0 when it was finished earlier)."""
    reason: str = ""
    """Why it is not legal or not exported (effort limits), or ``already trained``."""


def _row(ev: Any, task: str) -> dict[str, float]:
    from studio.serve.reward import task_weights

    sb = ev.metrics.second_bounce if ev.metrics else None
    if sb is None:
        return {}
    target = task_weights(task).target
    return {
        "aim_mm": 1000.0 * float(np.hypot(sb["p"][0] - target[0], sb["p"][1] - target[1])),
        "vx": float(sb["v"][0]),
        "vy": float(sb["v"][1]),
        "vz": float(sb["v"][2]),
        "cork": float(sb["cork"]),
        "topback": float(sb["topspin"]),
        "side": float(sb["sidespin"]),
    }


def _run_job(
    side: TossSide,
    seed: int,
    cfg: TrainConfig,
    run_dir: Path,
    *,
    workers: int,
    on_record: Callable[[dict[str, Any]], None] | None = None,
) -> HandServe | None:
    """One HEBO run into ``run_dir`` (resumed if it holds a log); the chosen serve."""
    from studio.optimize.optimizer import optimize_serve

    res = optimize_serve(
        side=side,
        task=cfg.task,
        run_dir=run_dir,
        seeds=[s for s in cfg.seeds if s.side == side],
        iterations=cfg.iterations,
        population=cfg.population,
        tosses=cfg.tosses,
        seed=seed,
        workers=workers,
        resume=(run_dir / "evaluations.jsonl").exists(),
        on_record=on_record,
        overlap=cfg.overlap,
        limit_scale=cfg.limit_scale,
    )
    if res.best is None:
        return None
    return replace(res.best, name=f"{cfg.task} {side} {seed}", task=cfg.task)


def _ray_job(
    side: TossSide, seed: int, cfg: TrainConfig, run_json: str | None, log: bytes, queue: Any, index: int
) -> dict[str, Any] | None:
    """Ray task: the run in a scratch folder seeded with the driver's partial log; records
    are streamed to the driver through ``queue``; returns the chosen serve (JSON)."""
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        run_dir.mkdir()
        sent = [run_json is not None and bool(log)]
        if sent[0]:
            (run_dir / "run.json").write_text(run_json)  # type: ignore[arg-type]
            (run_dir / "evaluations.jsonl").write_bytes(log)

        def on_record(rec: dict[str, Any]) -> None:
            if not sent[0]:  # a new run: its run.json goes ahead of its first record
                queue.put((index, {"run.json": (run_dir / "run.json").read_text()}))
                sent[0] = True
            queue.put((index, rec))

        best = _run_job(side, seed, cfg, run_dir, workers=1, on_record=on_record)
        return best.to_json() if best is not None else None


def _finish(
    index: int,
    run_dir: Path,
    seed: int,
    best: HandServe | None,
    cfg: TrainConfig,
    context: Any,
    library: Any,
    seconds: float,
) -> TrainedServe:
    """Evaluate the chosen serve on the mean toss, export it if legal, mark the run done."""
    from studio.serve.efforts import EffortLimitError
    from studio.serve.evaluate import evaluate_serve

    if best is None:
        return TrainedServe(index, run_dir, False, -math.inf, {}, None, seconds, "nothing evaluated")
    if cfg.robustify:
        from studio.optimize.robust import robustify_chosen

        best = robustify_chosen(best, run_dir, evaluations=cfg.robustify, task=cfg.task, context=context).serve
    ev = evaluate_serve(best, context, task=cfg.task)
    row = _row(ev, cfg.task) if ev.legal else {}
    entry_id, reason = None, "" if ev.legal else ev.reason
    if ev.legal:
        try:
            entry_id = library.add(
                ev,
                provenance={"kind": "hebo", "run": str(run_dir), "seed": seed},
                task=cfg.task,
                preparation=context.preparation(best.side),
            ).id
        except EffortLimitError as err:  # legal but beyond the robot's efforts: kept in the run, not exported
            reason = f"not exported: {err}"
    reward = float(ev.reward.total)
    done: dict[str, Any] = {
        "id": entry_id,
        "legal": bool(ev.legal),
        "reward": reward if math.isfinite(reward) else None,
        "row": row,
        "reason": reason or ev.reason,
        "serve": best.to_json(),
    }
    (run_dir / "exported.json").write_text(json.dumps(done, allow_nan=False))
    return TrainedServe(index, run_dir, bool(ev.legal), float(ev.reward.total), row, entry_id, seconds, reason)


def _check_scale(run_dir: Path, cfg: TrainConfig) -> None:
    """Refuse a run folder that was trained with another limit scale than ``cfg``'s."""
    from studio.optimize.optimizer import read_run_meta

    if not (run_dir / "run.json").exists():
        return
    scale = LimitScale.from_json(read_run_meta(run_dir)["limit_scale"])
    if scale != cfg.limit_scale:
        raise InvalidInputError(
            f"{run_dir} was trained with limit_scale {scale.to_json()}, this call asks for {cfg.limit_scale.to_json()}: use another --runs folder"
        )


def _already(index: int, run_dir: Path, cfg: TrainConfig) -> TrainedServe | None:
    _check_scale(run_dir, cfg)
    done = run_dir / "exported.json"
    if not done.exists():
        return None
    d = json.loads(done.read_text())
    reward = d.get("reward")
    return TrainedServe(
        index,
        run_dir,
        bool(d.get("legal", d.get("id") is not None)),
        math.nan if reward is None else float(reward),
        dict(d.get("row", {})),
        d.get("id"),
        0.0,
        "already trained",
    )


def finished_runs(cfg: TrainConfig) -> list[TrainedServe]:
    """The runs of ``cfg`` that are finished (their folder holds ``exported.json``), in run
    order, without training anything (for a report while or after training)."""
    out = []
    for i, _side, _seed, run_dir in cfg.jobs():
        done = _already(i, run_dir, cfg)
        if done is not None:
            out.append(done)
    return out


def train_serves(
    cfg: TrainConfig,
    library_dir: str | Path,
    *,
    ray_address: str | None = None,
    progress: Callable[[TrainedServe, int], None] | None = None,
) -> list[TrainedServe]:
    """Train ``cfg.count`` serves and export the legal ones to the library at ``library_dir``.

    Args:
        cfg: what to train.
        library_dir: serve library folder (created).
        ray_address: run on a Ray cluster (``ray.init(address=...)``; ``"local"``: a private
            local instance); ``None``: locally, one run after the other.
        progress: called with each finished run and the total count.

    Returns:
        One :class:`TrainedServe` per run, in run order.
    """
    from studio.library.store import ServeLibrary
    from studio.serve.evaluate import EvaluationContext

    library = ServeLibrary(library_dir)
    context = EvaluationContext.default()
    results: dict[int, TrainedServe] = {r.index: r for r in finished_runs(cfg)}
    for done in results.values():
        if progress:
            progress(done, cfg.count)
    todo = [job for job in cfg.jobs() if job[0] not in results]
    if ray_address is None:
        for i, side, seed, run_dir in todo:
            t0 = time.perf_counter()
            best = _run_job(side, seed, cfg, run_dir, workers=cfg.workers)
            results[i] = _finish(i, run_dir, seed, best, cfg, context, library, time.perf_counter() - t0)
            if progress:
                progress(results[i], cfg.count)
    elif todo:
        _train_on_ray(cfg, todo, ray_address, context, library, results, progress)
    return [results[i] for i in sorted(results)]


def _train_on_ray(
    cfg: TrainConfig,
    todo: list[tuple[int, TossSide, int, Path]],
    address: str,
    context: Any,
    library: Any,
    results: dict[int, TrainedServe],
    progress: Callable[[TrainedServe, int], None] | None,
) -> None:
    import ray
    from ray.util.queue import Empty, Queue

    from studio.serve.params import serve_from_json

    started_here = not ray.is_initialized()
    if started_here:
        try:
            if address == "local":
                ray.init(include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=address, log_to_driver=False)
        except Exception as exc:  # noqa: BLE001 - ray raises several unrelated types here
            raise InvalidInputError(f"train: cannot start or reach the Ray cluster at {address!r}: {exc}") from exc
    logs: dict[int, Any] = {}
    folders = {i: run_dir for i, _, _, run_dir in todo}
    try:
        queue = Queue()
        task = ray.remote(num_cpus=1)(_ray_job)
        pending: dict[Any, tuple[int, int, float]] = {}
        for i, side, seed, run_dir in todo:
            run_dir.mkdir(parents=True, exist_ok=True)
            log_path, meta = run_dir / "evaluations.jsonl", run_dir / "run.json"
            log = log_path.read_bytes() if log_path.exists() and meta.exists() else b""
            log = log[: log.rfind(b"\n") + 1]  # a torn last line is dropped, as optimize_serve does
            log_path.write_bytes(log)
            logs[i] = open(log_path, "ab")
            ref = task.remote(side, seed, cfg, meta.read_text() if log else None, log, queue, i)
            pending[ref] = (i, seed, time.perf_counter())

        def drain() -> None:
            """Append the streamed records to the local run folders (run.json first)."""
            while True:
                try:
                    i, rec = queue.get_nowait()
                except Empty:
                    return
                if "run.json" in rec:
                    (folders[i] / "run.json").write_text(rec["run.json"])
                else:
                    logs[i].write((json.dumps(rec, allow_nan=False) + "\n").encode("utf-8"))
                    logs[i].flush()

        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            drain()
            for ref in ready:
                i, seed, t0 = pending.pop(ref)
                best_json = ray.get(ref)
                drain()  # the task put its last records before returning
                logs[i].close()
                best = serve_from_json(best_json) if best_json is not None else None
                results[i] = _finish(i, folders[i], seed, best, cfg, context, library, time.perf_counter() - t0)
                if progress:
                    progress(results[i], cfg.count)
    finally:
        for f in logs.values():
            f.close()
        if started_here:
            ray.shutdown()


def _stats(rows: Sequence[dict[str, float]], key: str) -> str:
    vals = [r[key] for r in rows if key in r]
    return f"{np.mean(vals):.1f} ± {np.std(vals):.1f}" if vals else "-"


def summary_table(results: Sequence[TrainedServe], task: str) -> str:
    """Markdown table: the legal serves' second-bounce statistics (mean ± std) beside the
    paper's Table II simulation row for ``task``."""
    legal = [r.row for r in results if r.legal and r.row]
    cols = list(COLUMNS) if task == "aiming" else [c for c in COLUMNS if c != "aim_mm"]
    lines = [
        f"{task}: {len(legal)} legal of {len(results)} trained serves (simulation, ball at the second bounce; mean ± std)",
        "",
    ]
    lines.append("| | N | " + " | ".join(COLUMNS[c] for c in cols) + " |")
    lines.append("| --- | --- |" + " --- |" * len(cols))
    lines.append(f"| this run | {len(legal)} | " + " | ".join(_stats(legal, c) for c in cols) + " |")
    paper = PAPER_TABLE_II_SIM.get(task)
    if paper is not None:
        lines.append(
            "| paper, Sim | 25 | "
            + " | ".join(f"{paper[c][0]:.1f} ± {paper[c][1]:.1f}" if c in paper else "N/A" for c in cols)
            + " |"
        )
    return "\n".join(lines)
