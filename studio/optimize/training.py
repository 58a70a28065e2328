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
- on a Ray cluster (``ray_address``: a cluster's address such as ``"auto"`` or
  ``"host:6379"``; ``"local"`` starts a private local Ray instance; set-up in
  ``docs/cluster.md``): every run is one Ray task (1 CPU, evaluation in the task's
  process), as many at once as the cluster has CPUs. Each task is a streaming generator
  that yields its evaluation records as they are made; this process (the driver) appends
  them to the local run folder, so the run folders, the library and resuming work as in
  local mode (the nodes need no shared file system).

``exported.json`` in a finished run folder holds the verdict on the mean toss, the summary
row and the chosen serve (hand-serve JSON, so ``serve-studio evaluate`` reproduces it).

Resume: a run whose folder holds ``exported.json`` is finished and skipped; a run with a
partial ``evaluations.jsonl`` continues without repeating an evaluation (in Ray mode the
partial log is sent to the task). Records in flight when the driver is killed are lost
(at most the batch being evaluated per run).

Ray failures (issue 18): Ray never retries a task itself (``max_retries=0``: a retry would
start from the log the task was first given and send records the driver holds). The
driver keeps a record only when it is the next one of the run's log (a repeat of a held
index with the same genome is dropped, with another genome the run stops with an error
naming it). When a task's worker or node is lost (worker crash, node death, lost object,
dead actor), the driver resubmits the run from its current log, at most
:attr:`TrainConfig.ray_retries` times; a run that still does not finish, a cluster left
without CPUs or a failing cluster end the training with one
:class:`TrainingFailedError` naming the runs and their logs, which a rerun resumes.
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np

from studio.errors import DataFileError, InvalidInputError, StudioError
from studio.serve.params import HandServe, LimitScale, TossSide
from studio.storage.jsonfile import read_json_file
from studio.storage.jsonlog import write_line

# Ray >= 2.45 notices a driver started by ``uv run`` (as ``./dev`` does) and starts its
# workers with ``uv run`` too, packaging the working directory; here that failed ("worker
# startup repeatedly failed"). The workers run the driver's interpreter instead; a remote
# cluster's nodes need the environment installed (``uv sync`` of this project).
os.environ.setdefault("RAY_ENABLE_UV_RUN_RUNTIME_ENV", "0")

SideChoice = Literal["right", "left", "both"]
_LOG = logging.getLogger("studio.optimize.training")

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
    ray_retries: int = 3
    """On Ray: how often a run whose worker or node was lost is resubmitted (from the
    driver's log) before the training reports it as not finished."""

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
        if isinstance(self.ray_retries, bool) or not isinstance(self.ray_retries, int) or self.ray_retries < 0:
            raise InvalidInputError(f"train: ray_retries must be a whole number >= 0, got {self.ray_retries!r}")
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
    from studio.optimize.optimizer import OptimizeOptions, optimize_serve
    from studio.optimize.workflow import chosen_serve

    options = OptimizeOptions(
        side=side,
        task=cfg.task,
        iterations=cfg.iterations,
        population=cfg.population,
        tosses=cfg.tosses,
        seed=seed,
        workers=workers,
        overlap=cfg.overlap,
        limit_scale=cfg.limit_scale,
    )
    res = optimize_serve(
        options,
        run_dir=run_dir,
        seeds=[s for s in cfg.seeds if s.side == side],
        resume=(run_dir / "evaluations.jsonl").exists(),
        on_record=on_record,
    )
    return chosen_serve(res, name=f"{cfg.task} {side} {seed}")


def _ray_job(side: TossSide, seed: int, cfg: TrainConfig, run_json: str | None, log: bytes) -> Iterator[dict[str, Any]]:
    """Ray task, a streaming generator: the run in a scratch folder seeded with the driver's
    current log (``run_json`` and ``log``; a new run when ``log`` is empty).

    Yields ``{"kind": "start", "node", "pid", "scratch"}`` first, then for a new run
    ``{"kind": "run.json", "text"}`` ahead of its first record, ``{"kind": "record",
    "record"}`` for every new evaluation as it is logged, and last ``{"kind": "done",
    "serve"}`` (the chosen serve's JSON or None) or ``{"kind": "error", "message"}``. The
    optimization runs in a thread of this task; nothing here waits in ``ray.get`` (a task
    blocked there lends its CPU to another task: the reported three tasks on two CPUs)."""
    import ray

    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        run_dir.mkdir()
        yield {
            "kind": "start",
            "node": ray.get_runtime_context().get_node_id(),
            "pid": os.getpid(),
            "scratch": str(run_dir),
        }
        resumed = run_json is not None and bool(log)
        if resumed:
            (run_dir / "run.json").write_text(run_json or "")
            (run_dir / "evaluations.jsonl").write_bytes(log)
        items: queue.Queue[dict[str, Any]] = queue.Queue()
        args = (items, side, seed, cfg, run_dir, resumed)
        thread = threading.Thread(target=_job_thread, args=args, name="serve-studio-run", daemon=True)
        thread.start()
        while True:
            item = items.get()
            yield item
            if item["kind"] in ("done", "error"):
                break
        thread.join()


def _job_thread(
    items: queue.Queue[dict[str, Any]], side: TossSide, seed: int, cfg: TrainConfig, run_dir: Path, resumed: bool
) -> None:
    """The run of :func:`_ray_job`: its items put on ``items``, the last one ``done`` or ``error``."""
    sent = [resumed]

    def on_record(rec: dict[str, Any]) -> None:
        if not sent[0]:  # a new run: its run.json goes ahead of its first record
            items.put({"kind": "run.json", "text": (run_dir / "run.json").read_text()})
            sent[0] = True
        items.put({"kind": "record", "record": rec})

    try:
        best = _run_job(side, seed, cfg, run_dir, workers=1, on_record=on_record)
    except StudioError as exc:
        items.put({"kind": "error", "message": str(exc)})
    except BaseException as exc:  # noqa: BLE001 - a bug or an interrupt: one message to the driver, never a hang
        where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        at = f" (at {Path(where.filename).name}:{where.lineno} in {where.name})" if where else ""
        items.put({"kind": "error", "message": f"{type(exc).__name__}: {exc}{at}"})
    else:
        items.put({"kind": "done", "serve": best.to_json() if best is not None else None})


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
    from studio.optimize.workflow import export_evaluation, hebo_provenance, make_robust
    from studio.serve.efforts import EffortLimitError
    from studio.serve.evaluate import evaluate_serve

    if best is None:
        return TrainedServe(index, run_dir, False, -math.inf, {}, None, seconds, "nothing evaluated")
    best = make_robust(best, run_dir, evaluations=cfg.robustify, task=cfg.task, context=context)
    ev = evaluate_serve(best, context, task=cfg.task)
    row = _row(ev, cfg.task) if ev.legal else {}
    entry_id, reason = None, "" if ev.legal else ev.reason
    if ev.legal:
        try:
            provenance = hebo_provenance(run_dir, seed)
            entry_id = export_evaluation(library, ev, context=context, task=cfg.task, provenance=provenance).id
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
    d = _finished_record(done)
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


def _finished_record(path: Path) -> dict[str, Any]:
    """A finished run's ``exported.json``, its fields checked (DataFileError naming the
    file and the field): ``legal`` a bool, ``id`` a string or null, ``reward`` a number or
    null, ``row`` an object of numbers (the summary's ball state; :func:`read_json_file`
    already refuses non-finite numbers)."""
    d = read_json_file(path)
    if not isinstance(d, dict):
        raise DataFileError(path, "expected a JSON object (a finished run's exported.json)")

    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    checks = {
        "legal": lambda v: isinstance(v, bool),
        "id": lambda v: v is None or isinstance(v, str),
        "reward": lambda v: v is None or number(v),
        "row": lambda v: isinstance(v, dict) and all(number(x) for x in v.values()),
    }
    for key, ok in checks.items():
        if key in d and not ok(d[key]):
            raise DataFileError(path, f"field {key!r}: unexpected value {d[key]!r} for a finished run")
    return d


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


class TrainingFailedError(StudioError):
    """Training on a Ray cluster left runs unfinished: which, why, and that a rerun resumes them."""


class _RunFailed(Exception):
    """One run cannot go on (its message says why); the others can."""


@dataclass
class _RayRun:
    """Driver-side state of one run trained as a Ray task (mutable: it follows the task
    through resubmissions)."""

    index: int
    side: TossSide
    seed: int
    run_dir: Path
    genomes: list[list[float]]
    """Genome of every record the local log holds, by evaluation index."""
    log: IO[str]
    """The local ``evaluations.jsonl``, open for appending."""
    t0: float = field(default_factory=time.perf_counter)
    task: Any = None
    """The current task's ``ObjectRefGenerator`` (None while a resubmission waits)."""
    resubmit_at: float = 0.0
    """When the run is resubmitted after a loss (``time.monotonic``)."""
    node: str = ""
    """Node of the current task (from its ``start`` item)."""
    scratch: str = ""
    """The task's scratch run folder (replaced by :attr:`run_dir` in its messages)."""
    lost: list[str] = field(default_factory=list)
    """The worker and node losses of this run, one line each."""
    repeated: int = 0
    """Records received again that the log held already (same index and genome; not appended)."""

    @property
    def log_path(self) -> Path:
        return self.run_dir / "evaluations.jsonl"


def _held_records(run_dir: Path) -> list[Any]:
    """The records of ``run_dir``'s log, checked before any of it is sent to a task: indices
    0, 1, 2, ... and a ``run.json`` beside a non-empty log (DataFileError naming the file
    and line otherwise; :func:`studio.optimize.optimizer.read_evaluations`)."""
    from studio.optimize.optimizer import read_evaluations

    log_path = run_dir / "evaluations.jsonl"
    records = read_evaluations(log_path)
    for k, rec in enumerate(records):
        if not isinstance(rec.genome, list):
            raise DataFileError(log_path, f"line {k + 1}: genome is not a list of numbers")
    if records and not (run_dir / "run.json").is_file():
        raise DataFileError(
            log_path,
            f"{len(records)} evaluations but no run.json beside it: the run cannot be resumed; move the folder away to train it anew",
        )
    return records


def _open_run(index: int, side: TossSide, seed: int, run_dir: Path) -> _RayRun:
    run_dir.mkdir(parents=True, exist_ok=True)
    records = _held_records(run_dir)
    log = open(run_dir / "evaluations.jsonl", "a", encoding="utf-8")
    return _RayRun(index, side, seed, run_dir, [list(r.genome) for r in records], log)


def _submit(task: Any, run: _RayRun, cfg: TrainConfig) -> None:
    """Start (or restart) the run's task from the driver's current log."""
    run.log.flush()
    resumed = bool(run.genomes)
    log = run.log_path.read_bytes() if resumed else b""
    meta = (run.run_dir / "run.json").read_text(encoding="utf-8") if resumed else None
    run.task, run.node, run.scratch = task.remote(run.side, run.seed, cfg, meta, log), "", ""


def _accept(run: _RayRun, rec: Any) -> None:
    """Append a streamed record to the run's log unless the log holds it already.

    The log holds records 0 .. n-1: a record with one of those indices and the same genome
    is a repeat (not appended, counted), with another genome an error naming the run; index
    n is appended (flushed and fsynced); anything else does not follow the log (an error)."""
    from studio.optimize.optimizer import EvaluationRecord

    held = len(run.genomes)
    index = rec.get("index") if isinstance(rec, dict) else None
    if isinstance(index, int) and 0 <= index < held:
        if rec.get("genome") == run.genomes[index]:
            run.repeated += 1
            return
        raise _RunFailed(
            f"its Ray task sent record {index} with another genome than the log's record {index}: not appended (the log keeps its {held} records)"
        )
    if index != held:
        raise _RunFailed(
            f"its Ray task sent a record with index {index!r} after the log's {held} records: not appended"
        )
    try:
        EvaluationRecord.from_json(rec)
    except (KeyError, TypeError) as exc:
        raise _RunFailed(f"its Ray task sent a malformed record {index} ({exc!r}): not appended") from None
    write_line(run.log, rec)
    run.genomes.append(list(rec["genome"]))


def _lost_worker(exc: BaseException) -> str | None:
    """One line naming the lost worker or node when ``exc`` (from a task's result) is one
    (a retry from the log can succeed); None for other errors."""
    from ray import exceptions as rex

    lost = (
        rex.WorkerCrashedError,
        rex.NodeDiedError,
        rex.ObjectLostError,
        rex.RayActorError,
        rex.OutOfMemoryError,
        rex.RaySystemError,
    )
    cause = exc.cause if isinstance(exc, rex.RayTaskError) and isinstance(exc.cause, BaseException) else exc
    return _first_line(cause) if isinstance(cause, lost) else None


def _first_line(exc: BaseException) -> str:
    """``Type: first sentence of the message`` (at most 300 characters), for one-line
    reports (Ray's messages go on for lines; a wrapped cause is named, not the wrapper)."""
    from ray.exceptions import RayTaskError

    if isinstance(exc, RayTaskError) and isinstance(exc.cause, BaseException):
        exc = exc.cause
    lines = str(exc).strip().splitlines()
    line = lines[0] if lines else ""
    cut = line.find(". ")
    line = line[: cut + 1] if cut > 0 else line
    return f"{type(exc).__name__}: {line[:300]}{'...' if len(line) > 300 else ''}"


def _on_item(run: _RayRun, item: Any) -> dict[str, Any] | None:
    """Handle one item of a task (module doc of :func:`_ray_job`); the ``done`` item or None."""
    kind = item.get("kind") if isinstance(item, dict) else None
    if kind == "start":
        run.node, run.scratch = str(item["node"]), str(item["scratch"])
    elif kind == "run.json":
        if not run.genomes:  # a new run's configuration; a resumed run keeps its own
            (run.run_dir / "run.json").write_text(item["text"], encoding="utf-8")
    elif kind == "record":
        _accept(run, item["record"])
    elif kind == "error":
        message = str(item["message"])
        raise _RunFailed(message.replace(run.scratch, str(run.run_dir)) if run.scratch else message)
    elif kind == "done":
        return item
    else:
        raise _RunFailed(f"its Ray task sent an unknown item {str(item)[:80]!r}")
    return None


def _step(run: _RayRun, cfg: TrainConfig) -> dict[str, Any] | None:
    """Take the next item of the run's task (it must be ready); the ``done`` item or None.
    A lost worker or node schedules the run's resubmission (:func:`_lost`); _RunFailed
    when the run cannot go on."""
    import ray
    from ray.exceptions import RayError

    try:
        item = ray.get(next(run.task))
    except StopIteration:
        raise _RunFailed("its Ray task ended without a result") from None
    except RayError as exc:
        _lost(run, exc, cfg)
        return None
    return _on_item(run, item)


def _lost(run: _RayRun, exc: BaseException, cfg: TrainConfig) -> None:
    """The run's task failed with ``exc``: schedule its resubmission from the driver's log
    (after 1 s per loss so far, at most 5 s: time for the cluster to mark a dead node), at
    most ``cfg.ray_retries`` times; _RunFailed for other failures or too many losses."""
    lost = _lost_worker(exc)
    if lost is None:
        raise _RunFailed(f"its Ray task failed: {_first_line(exc)}")
    run.lost.append(lost)
    if len(run.lost) > cfg.ray_retries:
        raise _RunFailed(f"lost its Ray worker {len(run.lost)} times (last: {lost})")
    delay = min(5.0, 1.0 * len(run.lost))
    _LOG.warning(
        "run %s: %s (node %s); resubmitted in %.0f s from the %d evaluations in its log (retry %d of %d)",
        run.run_dir, lost, run.node[:12] or "?", delay, len(run.genomes), len(run.lost), cfg.ray_retries,
    )  # fmt: skip
    run.task, run.resubmit_at = None, time.monotonic() + delay


def _cancel(run: _RayRun) -> None:
    """Stop the run's task (best effort: it may have ended or its node be gone)."""
    import ray

    if run.task is None:
        return
    try:
        ray.cancel(run.task, force=True)
    except Exception:  # noqa: BLE001, S110 - nothing more to do about a task that cannot be cancelled
        pass


@dataclass
class _CpuWatch:
    """Ends the training when the cluster has had no CPU for ``limit`` seconds (its tasks
    would wait forever), checking every ``every`` seconds."""

    limit: float = 60.0
    every: float = 5.0
    last: float = field(default_factory=time.monotonic)
    since: float | None = None

    def check(self) -> None:
        import ray

        now = time.monotonic()
        if now - self.last < self.every:
            return
        self.last = now
        if ray.cluster_resources().get("CPU", 0.0) >= 1.0:
            self.since = None
        elif self.since is None:
            self.since = now
        elif now - self.since > self.limit:
            raise _NoCpu(f"the Ray cluster has had no CPU for {self.limit:.0f} s (its nodes died or left)")


class _NoCpu(Exception):
    """The cluster cannot run a task any more."""


class _Receiver(threading.Thread):
    """Follows the runs' tasks in a thread of the driver, so that every item is taken as
    soon as it is there while the driver's thread evaluates and exports finished runs (Ray
    drops the items a task yielded but the driver had not taken when the task fails:
    measured, a node killed while the driver exported another run lost 5 records). It
    appends the records, resubmits runs whose worker or node was lost, and puts each
    finished run with its ``done`` item on :attr:`done` (None when nothing is left)."""

    def __init__(self, task: Any, runs: list[_RayRun], cfg: TrainConfig) -> None:
        super().__init__(name="serve-studio-ray-receiver", daemon=True)
        self.task, self.cfg, self.active = task, cfg, list(runs)
        self.done: queue.Queue[tuple[_RayRun, dict[str, Any]] | None] = queue.Queue()
        self.failed: dict[int, str] = {}
        """Message of each run that cannot go on, by run index."""
        self.error: BaseException | None = None
        """What ended the following early (e.g. the driver lost the cluster)."""
        self.halt = threading.Event()

    def run(self) -> None:
        try:
            self._follow()
        except BaseException as exc:  # noqa: BLE001 - handed to the driver's thread
            self.error = exc
        finally:
            self.done.put(None)

    def _follow(self) -> None:
        import ray

        watch = _CpuWatch()
        while self.active and not self.halt.is_set():
            now = time.monotonic()
            for run in self.active:
                if run.task is None and run.resubmit_at <= now:
                    _submit(self.task, run, self.cfg)
            tasks = [r.task for r in self.active if r.task is not None]
            ready = ray.wait(tasks, num_returns=len(tasks), timeout=0.2)[0] if tasks else []
            if not tasks:
                time.sleep(0.2)
            for gen in ready:
                self._drain(next(r for r in self.active if r.task is gen))
            try:
                watch.check()
            except _NoCpu as exc:
                self._give_up(list(self.active), str(exc))

    def _drain(self, run: _RayRun) -> None:
        """Take every item of the run's task that is there."""
        import ray

        gen = run.task
        while run.task is gen and ray.wait([gen], num_returns=1, timeout=0)[0]:
            try:
                item = _step(run, self.cfg)
            except _RunFailed as exc:
                self._give_up([run], str(exc))
                return
            if item is not None:
                self.active.remove(run)
                self.done.put((run, item))
                return

    def _give_up(self, runs: list[_RayRun], message: str) -> None:
        for run in runs:
            _cancel(run)
            self.active.remove(run)
            self.failed[run.index] = message


def _drive(
    task: Any,
    runs: list[_RayRun],
    cfg: TrainConfig,
    finish: Callable[[_RayRun, HandServe | None], None],
) -> dict[int, str]:
    """Follow the runs' tasks (:class:`_Receiver`) and finish each run that is done, in
    this thread; the messages of the runs that did not finish, by run index."""
    from studio.serve.params import serve_from_json

    receiver = _Receiver(task, runs, cfg)
    receiver.start()
    try:
        while (event := receiver.done.get()) is not None:
            run, item = event
            finish(run, serve_from_json(item["serve"]) if item["serve"] is not None else None)
    finally:
        receiver.halt.set()
        receiver.join(timeout=10.0)
    if receiver.error is not None:
        raise receiver.error
    return receiver.failed


def _failure_report(failed: dict[int, str], runs: list[_RayRun]) -> str:
    """The message of :class:`TrainingFailedError`: each unfinished run, why, and its log."""
    by_index = {r.index: r for r in runs}
    lines = [f"{len(failed)} of the {len(runs)} runs trained on Ray did not finish:"]
    for i in sorted(failed):
        run = by_index[i]
        lines.append(f"  {run.run_dir}: {failed[i]}; {len(run.genomes)} evaluations are logged in {run.log_path}")
    lines.append(
        "Run the same command again to resume them (finished runs are skipped, logged evaluations are not repeated)"
    )
    return "\n".join(lines)


def _connect(address: str) -> bool:
    """``ray.init`` for ``address`` unless Ray is initialized; True when it was started here."""
    import ray

    if ray.is_initialized():
        return False
    try:
        if address == "local":
            ray.init(include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    except Exception as exc:  # noqa: BLE001 - ray raises several unrelated types here
        raise InvalidInputError(
            f"train: cannot start or reach the Ray cluster at {address!r}: {_first_line(exc)} "
            "(a cluster with token authentication needs RAY_AUTH_MODE=token and its token here: docs/cluster.md)"
        ) from None
    return True


def _train_on_ray(
    cfg: TrainConfig,
    todo: list[tuple[int, TossSide, int, Path]],
    address: str,
    context: Any,
    library: Any,
    results: dict[int, TrainedServe],
    progress: Callable[[TrainedServe, int], None] | None,
) -> None:
    """The runs ``todo`` as Ray tasks (:func:`_ray_job`, one CPU each, resubmitted by this
    driver from its current log when a worker or node is lost); TrainingFailedError naming
    the runs that did not finish (their logs resume on a rerun)."""
    import ray
    from ray.exceptions import RayError

    runs: list[_RayRun] = []
    started_here = False

    def finish(run: _RayRun, best: HandServe | None) -> None:
        elapsed = time.perf_counter() - run.t0
        if run.repeated:
            _LOG.warning("run %s: %d records received again were not appended", run.run_dir, run.repeated)
        results[run.index] = _finish(run.index, run.run_dir, run.seed, best, cfg, context, library, elapsed)
        if progress:
            progress(results[run.index], cfg.count)

    try:
        for i, side, seed, run_dir in todo:  # every log is checked before the cluster is reached
            runs.append(_open_run(i, side, seed, run_dir))
        started_here = _connect(address)
        task = ray.remote(num_cpus=1, max_retries=0)(_ray_job)  # retried here, from the driver's log
        for run in runs:
            _submit(task, run, cfg)
        failed = _drive(task, runs, cfg, finish)
    except RayError as exc:
        held = ", ".join(f"{r.run_dir.name}: {len(r.genomes)}" for r in runs)
        raise TrainingFailedError(
            f"the Ray cluster failed while training ({_first_line(exc)}); the evaluations received are logged "
            f"({held}): run the same command again to resume"
        ) from None
    finally:
        for run in runs:
            run.log.close()
        if started_here:
            ray.shutdown()
    if failed:
        raise TrainingFailedError(_failure_report(failed, runs))


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
