"""Serve optimization with HEBO (the paper's training loop).

The paper optimizes the normalized genome z in [0, 1]^10 (:class:`studio.serve.params.GenomeBounds`)
with HEBO, 100 iterations of 20 suggestions, maximizing the reward F; HEBO minimizes
y = -F. :func:`optimize_serve` runs that loop (the run's settings in :class:`OptimizeOptions`,
the loop's state in :class:`OptimizationRun`):

1. hand-designed seed serves are normalized, evaluated and observed before the first
   suggestion;
2. each iteration asks HEBO (:class:`studio.optimize.hebo_adapter.HeboAdapter`) for ``population``
   points, evaluates them in ``workers`` local processes (each builds its own
   :class:`~studio.serve.evaluate.EvaluationContext` once) and observes them;
3. every evaluation is appended to ``run_dir/evaluations.jsonl`` as soon as it is known
   (flushed and fsynced), next to ``run_dir/run.json`` (configuration);
4. the final serve: the ``top_k`` best candidates (``final_spread`` apart) are
   re-evaluated on ``final_tosses`` recorded tosses (fresh draws); among those legal on
   at least ``min_legal_fraction`` of them the best *mean* reward wins (if none is, the
   best mean).

Resume and reproducibility: with ``resume=True`` the JSONL is re-read (a torn last line
is dropped) and every record is re-observed, nothing is re-evaluated. Suggestions depend
only on ``seed`` and the observations (see :mod:`studio.optimize.hebo_adapter`), and evaluations
are deterministic, so a run resumed after a complete batch continues exactly like the
uninterrupted run. If a batch was cut short, only the missing count is suggested, from a
model that already holds the batch's finished part: the run goes on correctly (same
budget, nothing repeated) but no longer matches the uninterrupted run point for point.

Workers are *spawned* processes (torch is loaded in the parent; fork after torch is
unsafe), so a script that calls :func:`optimize_serve` with ``workers > 1`` needs the
usual ``if __name__ == "__main__":`` guard. Each worker runs its BLAS/OpenMP pools with
one thread (see :data:`WORKER_THREAD_VARS`). Workers die with their driver: on Linux each
asks the kernel for SIGKILL when its parent ends (``prctl(PR_SET_PDEATHSIG)``, elsewhere a
thread polls ``os.getppid()``), so a ``kill -9`` of the driver leaves no worker behind. A
worker that dies (killed, out of memory) ends the run with :class:`WorkerDiedError` (one
line: which worker, how, and that ``--resume`` continues; every evaluation finished
before it is in the log, and the resume evaluates the rest of the budget once).

Robust by default: ``tosses=5`` recorded tosses per evaluation (the paper's multi-toss
training; ``serve-studio optimize`` and ``train`` use 5 too) and the legal-first, spread
final pick above. Over five seeds the mean toss only (``tosses=1``) with the pick before
issue 16 chose, on some seeds, serves illegal on most fresh tosses; the defaults chose
serves legal on all of them. Its cost: a 5-toss evaluation takes less than twice the CPU of a
mean-toss one (the motion is planned once, each toss is a flight); the final pick is small
beside the run. Figures: ``docs/optimization.md#training-time`` ("Robust by default").
"""

from __future__ import annotations

import ctypes
import functools
import json
import math
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from studio.errors import DataFileError, InvalidInputError, StudioError
from studio.optimize.hebo_adapter import HeboAdapter, HeboConfig
from studio.optimize.threads import THREAD_VARS, single_thread_env
from studio.serve.params import GENE_NAMES, GenomeBounds, HandServe, LimitScale, ServeParams, TossSide
from studio.serve.reward import PLANNER_FAILURE_PENALTY
from studio.storage.jsonlog import ensure_line_end, read_jsonl, write_line

__all__ = [
    "HeboConfig",
    "Outcome",
    "EvaluationRecord",
    "FinalCandidate",
    "OptimizationResult",
    "EvaluatorPool",
    "WorkerDiedError",
    "RunHistory",
    "load_run_history",
    "RunSummary",
    "list_runs",
    "bounds_for_toss",
    "OptimizeOptions",
    "OptimizationRun",
    "optimize_serve",
    "RUN_SCHEMA",
    "read_run_meta",
    "read_evaluations",
]

RUN_SCHEMA = "serve-studio/optimization-run@1"
"""Schema tag of ``run.json``."""
_CONFIG_BEFORE_WARM_STARTS: dict[str, Any] = {
    "refit_every": None,
    "warm_epochs": 10,
    "refit_tolerance": 0.3,
    "lean_nsga": False,
}
"""What a run logged before these :class:`HeboConfig` options ran with (cold fits, pymoo's NSGA-II)."""

TAU_AFTER_APEX = 0.02
"""Earliest contact after the toss's apex [s]: the ball must be falling when struck (ITTF 2.6.3)."""
TAU_MIN_HEIGHT = 0.05
"""Latest contact: when the mean ball centre falls to this height above the playing surface [m]."""


DEFAULT_BOUNDS = GenomeBounds()
"""The paper's genome bounds (:class:`studio.serve.params.GenomeBounds` defaults)."""


def bounds_for_toss(
    toss: Any,
    *,
    after_apex: float = TAU_AFTER_APEX,
    min_height: float = TAU_MIN_HEIGHT,
    base: GenomeBounds = DEFAULT_BOUNDS,
) -> GenomeBounds:
    """Genome bounds whose tau range [s, toss clock] follows the toss model.

    From ``after_apex`` after the mean path's apex to the time the mean ball centre
    falls to ``min_height`` above the table (z = 0), clipped to the model's time grid.
    ``toss``: a :class:`studio.toss.model.TossModel` (uses ``t`` (N,) and ``p`` (N, 3)).
    """
    t = np.asarray(toss.t, dtype=float)
    z = np.asarray(toss.p, dtype=float)[:, 2]
    i_apex = int(np.argmax(z))
    lo = float(t[i_apex]) + after_apex
    after = np.nonzero((t > t[i_apex]) & (z <= min_height))[0]
    if len(after):
        k = int(after[0])  # interpolate the crossing between k-1 and k
        z0, z1 = z[k - 1], z[k]
        hi = float(t[k - 1] + (t[k] - t[k - 1]) * (z0 - min_height) / (z0 - z1)) if z0 != z1 else float(t[k])
    else:
        hi = float(t[-1])
    if not lo < hi:
        raise InvalidInputError(
            f"bounds_for_toss: the {getattr(toss, 'side', '?')} toss gives no contact window (apex {t[i_apex]:.3f} s, low {lo:.3f} s >= high {hi:.3f} s)"
        )
    return GenomeBounds(
        tau=(lo, hi), velocity=base.velocity, yaw=base.yaw, roll=base.roll, t_return=base.t_return, offset=base.offset
    )


@dataclass(frozen=True, slots=True)
class Outcome:
    """What the optimizer keeps of one evaluation."""

    reward: float
    """Reward F (mean over tosses; penalties included) [-]."""
    legal: bool
    """Legal (for several tosses: at least ``min_legal_fraction`` of them legal)."""
    status: str
    """``legal``, ``illegal``, ``planner_failed`` or ``collision`` (first toss)."""
    failed_check: str | None = None
    """Name of the first failing check (the mean toss), or with several tosses the check most of them failed; ``None`` when legal."""
    legal_fraction: float = 1.0
    """Fraction of legal tosses."""
    rewards: tuple[float, ...] = ()
    """Per-toss rewards (empty for a single toss)."""


EvaluateFn = Callable[[HandServe, int, np.random.Generator], Outcome]
"""``evaluate(serve, tosses, rng) -> Outcome``: the injectable evaluation (tests)."""


@dataclass(frozen=True, slots=True)
class EvaluationRecord:
    """One line of ``evaluations.jsonl``."""

    index: int
    """Evaluation number (0-based, seeds first)."""
    batch: int
    """-1 for seeds, else the HEBO iteration."""
    source: str
    """``seed:<name>`` or ``hebo``."""
    genome: list[float]
    """Normalized genome (10,) in [0, 1] (seeds may lie outside)."""
    params: dict[str, float]
    """Physical genes by :data:`studio.serve.params.GENE_NAMES`."""
    reward: float
    """Reward F [-]."""
    legal: bool
    """Legal verdict."""
    status: str
    """Evaluation status."""
    failed_check: str | None
    """First failing check or ``None``."""
    legal_fraction: float
    """Fraction of legal tosses."""
    seconds: float
    """Wall time of this evaluation in its worker [s]."""

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> EvaluationRecord:
        return cls(**{k: d[k] for k in cls.__slots__})  # type: ignore[attr-defined]


@dataclass(frozen=True, slots=True)
class FinalCandidate:
    """A top candidate re-evaluated on fresh tosses."""

    params: ServeParams
    """Its physical parameters."""
    genome: tuple[float, ...]
    """Its normalized genome (10,)."""
    train_reward: float
    """Reward seen during training (``tosses`` tosses) [-]."""
    mean_reward: float
    """Mean reward over the ``final_tosses`` re-evaluation tosses [-]."""
    legal: bool
    """Legal over the re-evaluation (fraction >= ``min_legal_fraction``)."""
    legal_fraction: float
    """Fraction of legal re-evaluation tosses."""
    rewards: tuple[float, ...]
    """Per-toss rewards of the re-evaluation."""


@dataclass(frozen=True)
class OptimizationResult:
    """Result of :func:`optimize_serve`."""

    best: HandServe | None
    """The chosen serve (the first of :attr:`candidates`), ``None`` if nothing was evaluated."""
    summary: FinalCandidate | None
    """The chosen serve's re-evaluation."""
    candidates: tuple[FinalCandidate, ...]
    """All re-evaluated candidates: those legal on the re-evaluation first, each group by
    mean reward, best first."""
    history: npt.NDArray[np.float64]
    """Reward per evaluation (n,), in evaluation order (seeds first)."""
    evaluations: int
    """Number of evaluations in the run (resumed ones included)."""
    stopped: bool
    """True when the stop event ended the run before its budget."""
    timings: dict[str, float] = field(default_factory=dict)
    """Wall times [s] of this call: ``suggest`` (all HEBO suggestions), ``suggest_overlapped``
    (the part made while workers evaluated; it is inside ``evaluate`` too), ``evaluate``
    (batches, from hand-over to the last result), ``final``, ``total`` (``evaluate_cpu``:
    sum of per-evaluation worker wall times). ``suggest_cpu``: CPU time [s] of this process
    during the suggestions (all its threads; on a loaded machine a better measure of
    their cost than their wall time)."""
    run_dir: Path | None = None
    """Where ``run.json`` and ``evaluations.jsonl`` are."""
    observed_X: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, len(GENE_NAMES))))
    """What HEBO holds at the end: normalized genomes (n, 10), in observation order."""
    observed_y: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    """What HEBO holds at the end: minimized targets y = -F (n,) (penalties for non-finite F)."""
    gp_fits: dict[str, int] = field(default_factory=dict)
    """GP fits of this call's suggestions by kind (:class:`studio.optimize.hebo_adapter.GPFit`:
    ``cold``, ``first``, ``scheduled``, ``warm``, ``degraded``)."""

    @property
    def best_so_far(self) -> npt.NDArray[np.float64]:
        """Running maximum of :attr:`history` (n,)."""
        return np.maximum.accumulate(self.history) if len(self.history) else self.history


# -- evaluation in worker processes ---------------------------------------------------

_WORKER_CONTEXT: Any = None


WORKER_THREAD_VARS = THREAD_VARS
"""Thread-count variables set to 1 in evaluation workers (:mod:`studio.optimize.threads`)."""


PR_SET_PDEATHSIG = 1
"""Linux ``prctl`` option: the signal this process gets when its parent ends."""
PARENT_POLL = 0.5
"""Seconds between parent checks of a worker where ``prctl`` is not available."""


class WorkerDiedError(StudioError):
    """An evaluation worker process ended abruptly (killed, out of memory) during a run."""


def _watch_parent(parent_pid: int) -> None:
    """Exit this process as soon as its parent is no longer ``parent_pid`` (polling)."""
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL)
    os._exit(1)


def _die_with_parent(parent_pid: int | None) -> None:
    """Make this (worker) process end when its parent ``parent_pid`` ends, however it
    ends: SIGKILL from the kernel (Linux ``prctl(PR_SET_PDEATHSIG)`` via ctypes), else a
    daemon thread polling ``os.getppid()``. Exits at once if the parent is gone already
    (it died before this ran). ``None``: nothing to watch (in-process use)."""
    if parent_pid is None:
        return
    armed = False
    if sys.platform.startswith("linux"):
        try:
            armed = ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent_pid:
        os._exit(1)
    if not armed:
        threading.Thread(target=_watch_parent, args=(parent_pid,), name="watch-parent", daemon=True).start()


def _worker_init(side: TossSide | None = None, ipopt_fallback: bool = False, parent_pid: int | None = None) -> None:
    """Initializer of an evaluation process: tied to the life of ``parent_pid`` (the
    driver; :func:`_die_with_parent`), one thread per BLAS/OpenMP pool, a training
    context (:meth:`EvaluationContext.for_training`) warmed up for ``side``."""
    global _WORKER_CONTEXT
    _die_with_parent(parent_pid)
    single_thread_env(keep_user_settings=False)
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    from studio.serve.evaluate import EvaluationContext

    _WORKER_CONTEXT = EvaluationContext.for_training(ipopt_fallback=ipopt_fallback)
    if side is not None:
        _WORKER_CONTEXT.warm_up(side)


def _context() -> Any:
    if _WORKER_CONTEXT is None:
        _worker_init()
    return _WORKER_CONTEXT


def evaluate_outcome(
    serve: HandServe,
    *,
    task: str,
    tosses: int,
    min_legal_fraction: float,
    rng: np.random.Generator,
    context: Any = None,
) -> Outcome:
    """Evaluate ``serve`` on the mean toss (``tosses == 1``) or on ``tosses`` recorded tosses."""
    from studio.serve.evaluate import evaluate_robust, evaluate_serve

    ctx = context if context is not None else _context()
    if tosses <= 1:
        ev = evaluate_serve(serve, ctx, task=task)
        return Outcome(
            float(ev.reward.total), bool(ev.legal), str(ev.status), ev.failed_check, 1.0 if ev.legal else 0.0
        )
    rob = evaluate_robust(serve, ctx, task=task, tosses=tosses, min_legal_fraction=min_legal_fraction, rng=rng)
    counts = rob.failed_checks()
    failed = None if rob.legal or not counts else max(counts, key=lambda c: counts[c])  # the check most tosses failed
    return Outcome(
        float(rob.reward), bool(rob.legal), str(rob.evaluations[0].status), failed, float(rob.legal_fraction),
        tuple(float(e.reward.total) for e in rob.evaluations),
    )  # fmt: skip


def _worker_eval(job: tuple[str, str, list[float], int, float, int, dict[str, float]]) -> tuple[dict[str, Any], float]:
    side, task, x, tosses, p, rng_seed, scale = job
    t0 = time.perf_counter()
    serve = HandServe(name="candidate", side=side, params=ServeParams.from_vector(x), limit_scale=LimitScale(**scale))  # type: ignore[arg-type]
    out = evaluate_outcome(serve, task=task, tosses=tosses, min_legal_fraction=p, rng=np.random.default_rng(rng_seed))
    return asdict(out), time.perf_counter() - t0


class EvaluatorPool:
    """Evaluates physical genomes (n, 10) in ``workers`` spawned processes (1: in-process).

    Each worker builds a training :class:`~studio.serve.evaluate.EvaluationContext` once
    (initializer; :meth:`~studio.serve.evaluate.EvaluationContext.for_training`, IPOPT fallback
    off unless ``ipopt_fallback``) and warms it up for ``side``. The workers are spawned
    at construction and initialize in the background (a few seconds) while the caller goes on.
    Every candidate is planned with ``limit_scale`` (:class:`~studio.serve.params.LimitScale`).
    Use as a context manager; ``evaluate`` overrides the real evaluation (in-process).
    The workers end with this process (:func:`_die_with_parent`); if one dies, :meth:`map`
    raises :class:`WorkerDiedError` naming it and how it ended.
    """

    def __init__(
        self, *, side: TossSide, task: str, workers: int = 2, min_legal_fraction: float = 0.8, evaluate: EvaluateFn | None = None,
        context: Any = None, ipopt_fallback: bool = False, limit_scale: LimitScale | None = None,
    ) -> None:  # fmt: skip
        if workers < 1:
            raise InvalidInputError(f"workers must be >= 1, got {workers}")
        self.side, self.task, self.workers, self.p = side, task, int(workers), float(min_legal_fraction)
        self._evaluate = evaluate
        self._context = context
        self._ipopt_fallback = bool(ipopt_fallback)
        self.limit_scale = limit_scale if limit_scale is not None else LimitScale()
        self._pool: ProcessPoolExecutor | None = None
        if evaluate is None and workers > 1:
            self._pool = ProcessPoolExecutor(
                workers,
                mp_context=mp.get_context("spawn"),
                initializer=_worker_init,
                initargs=(side, self._ipopt_fallback, os.getpid()),
            )
            # spawn every worker now (submit starts the processes), with the single-thread
            # variables in its environment from the start (set in os.environ of this
            # process only while spawning); they initialize while the caller goes on
            saved = {v: os.environ.get(v) for v in WORKER_THREAD_VARS}
            try:
                os.environ.update({v: "1" for v in WORKER_THREAD_VARS})
                for _ in range(workers):
                    self._pool.submit(os.getpid)
            finally:
                for v, old in saved.items():
                    if old is None:
                        os.environ.pop(v, None)
                    else:
                        os.environ[v] = old
        self._procs = list(getattr(self._pool, "_processes", {}).values())  # for naming a dead worker

    def _died(self) -> WorkerDiedError:
        """The error for a broken pool: which worker died and how (exit code or signal)."""
        deadline = time.monotonic() + 2.0
        for proc in self._procs:  # the pool is ending them all; wait briefly for their exit codes
            proc.join(max(0.0, deadline - time.monotonic()))
        ended = [(proc.pid, proc.exitcode) for proc in self._procs if proc.exitcode not in (None, 0)]
        first = [e for e in ended if e[1] != -signal.SIGTERM] or ended  # the pool SIGTERMs the others
        how = []
        for pid, code in first:
            if code < 0:
                name = signal.Signals(-code).name if -code in signal.valid_signals() else f"signal {-code}"
                how.append(f"evaluation worker pid {pid} was killed by {name}")
            else:
                how.append(f"evaluation worker pid {pid} exited with code {code}")
        what = "; ".join(how) or "an evaluation worker process ended abruptly (killed or out of memory)"
        return WorkerDiedError(f"{what}: the evaluation pool is broken")

    def __enter__(self) -> EvaluatorPool:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def map(
        self, X: npt.NDArray[np.float64], *, tosses: int, rng_seeds: Sequence[int]
    ) -> Iterator[tuple[Outcome, float]]:
        """(outcome, seconds) per row of physical genomes X (n, 10), in order, as they finish.

        With worker processes every row is submitted at once, before this returns (the
        caller may do other work meanwhile); in-process evaluation runs as it is iterated.
        """
        X = np.atleast_2d(X)
        if self._evaluate is not None or self._pool is None:
            return self._map_here(X, tosses, rng_seeds)
        scale = self.limit_scale.to_json()
        pool = self._pool
        try:
            futs = [
                pool.submit(_worker_eval, (self.side, self.task, [float(v) for v in x], tosses, self.p, int(s), scale))
                for x, s in zip(X, rng_seeds)
            ]
        except BrokenProcessPool:
            raise self._died() from None

        def results() -> Iterator[tuple[Outcome, float]]:
            for f in futs:
                try:
                    d, sec = f.result()
                except BrokenProcessPool:
                    raise self._died() from None
                d["rewards"] = tuple(d["rewards"])
                yield Outcome(**d), sec

        return results()

    def _map_here(
        self, X: npt.NDArray[np.float64], tosses: int, rng_seeds: Sequence[int]
    ) -> Iterator[tuple[Outcome, float]]:
        for x, s in zip(X, rng_seeds):
            t0 = time.perf_counter()
            serve = HandServe(
                name="candidate", side=self.side, params=ServeParams.from_vector(x), limit_scale=self.limit_scale
            )
            rng = np.random.default_rng(s)
            if self._evaluate is not None:
                out = self._evaluate(serve, tosses, rng)
            else:
                if self._context is None:
                    from studio.serve.evaluate import EvaluationContext

                    self._context = EvaluationContext.for_training(ipopt_fallback=self._ipopt_fallback)
                ctx = self._context
                out = evaluate_outcome(
                    serve, task=self.task, tosses=tosses, min_legal_fraction=self.p, rng=rng, context=ctx
                )
            yield out, time.perf_counter() - t0


# -- run files --------------------------------------------------------------------------


def _bounds_json(b: GenomeBounds) -> dict[str, Any]:
    return {
        "tau": list(b.tau),
        "velocity": list(b.velocity),
        "yaw": list(b.yaw),
        "roll": list(b.roll),
        "t_return": list(b.t_return),
        "offset": b.offset,
    }


def read_evaluations(path: Path) -> list[EvaluationRecord]:
    """The records of a run's ``evaluations.jsonl`` (:func:`studio.storage.jsonlog.read_jsonl`:
    a torn last line is cut off), in the order 0, 1, 2, ... of their indices (DataFileError
    naming the first line that breaks it, and the valid prefix, otherwise)."""
    good = read_jsonl(path, EvaluationRecord.from_json)
    for k, r in enumerate(good):
        if r.index != k:
            raise DataFileError(str(path), _index_problem(good, k))
    return good


def _index_problem(records: Sequence[EvaluationRecord], k: int) -> str:
    """Why line ``k + 1`` of a run log breaks the 0, 1, 2, ... order of evaluation indices."""
    r = records[k]
    text = f"line {k + 1}: record {k} has index {r.index}"
    if isinstance(r.index, int) and 0 <= r.index < k and records[r.index].genome == r.genome:
        text += f" and repeats line {r.index + 1} (records appended twice, as a Ray retry of an earlier version did)"
    return (
        f"{text}: not one run's log, the file is unchanged. Lines 1-{k} are a valid log: keep only them "
        f"(e.g. head -n {k}) to resume from there, or move the run folder away to run it anew"
    )


@dataclass(frozen=True)
class RunHistory:
    """What an optimization run folder holds, for convergence plots (``run.json`` +
    ``evaluations.jsonl``)."""

    run_dir: Path
    """The run folder."""
    task: str
    """Reward task of the run."""
    side: str
    """Toss side of the run."""
    reward: npt.NDArray[np.float64]
    """Reward F per evaluation (n,), in evaluation order (seeds first) [-]."""
    legal: npt.NDArray[np.bool_]
    """Legal verdict per evaluation (n,)."""
    batch: npt.NDArray[np.int64]
    """Batch per evaluation (n,): -1 for seeds, else the HEBO iteration."""
    seconds: npt.NDArray[np.float64]
    """Worker wall time per evaluation (n,) [s]."""

    @property
    def best_so_far(self) -> npt.NDArray[np.float64]:
        """Running maximum of :attr:`reward` (n,)."""
        return np.maximum.accumulate(self.reward) if len(self.reward) else self.reward

    @property
    def best_legal_so_far(self) -> npt.NDArray[np.float64]:
        """Running maximum over the legal evaluations (n,); -inf before the first legal one."""
        r = np.where(self.legal, self.reward, -np.inf)
        return np.maximum.accumulate(r) if len(r) else r


def read_run_meta(run_dir: str | Path) -> dict[str, Any]:
    """``run_dir/run.json`` (the run's configuration) as a dict, its ``limit_scale`` filled
    in for runs logged before dynamic limit expansion (the robot's own limits).

    Raises:
        DataFileError: the file is missing, not JSON, not a run file, or its
            ``limit_scale`` is malformed (the file and the field named).
    """
    meta_path = Path(run_dir) / "run.json"
    if not meta_path.is_file():
        raise DataFileError(str(meta_path), "missing: not an optimization run folder")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DataFileError(str(meta_path), f"not readable JSON ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("schema") != RUN_SCHEMA:
        raise DataFileError(str(meta_path), f"schema must be {RUN_SCHEMA!r}")
    meta["limit_scale"] = LimitScale.from_json(meta.get("limit_scale", {}), source=str(meta_path)).to_json()
    return meta


def load_run_history(run_dir: str | Path) -> RunHistory:
    """Read an optimization run folder (as written by :func:`optimize_serve`).

    Raises:
        DataFileError: ``run.json`` or ``evaluations.jsonl`` missing or malformed (file and
            line named). A torn last line (interrupted run) is ignored, not an error.
    """
    run_dir = Path(run_dir)
    meta = read_run_meta(run_dir)
    log_path = run_dir / "evaluations.jsonl"
    records: list[EvaluationRecord] = []
    if log_path.is_file():
        raw = log_path.read_bytes()
        complete = raw[: raw.rfind(b"\n") + 1]  # a torn last line belongs to a live or killed run
        for k, line in enumerate(complete.split(b"\n")[:-1]):
            if not line.strip():
                continue
            try:
                rec = EvaluationRecord.from_json(json.loads(line))
                if not (isinstance(rec.reward, (int, float)) and math.isfinite(rec.reward)):
                    raise ValueError(f"reward {rec.reward!r} is not a finite number")
            except (ValueError, KeyError, TypeError) as exc:
                raise DataFileError(str(log_path), f"line {k + 1}: not an evaluation record ({exc})") from exc
            records.append(rec)
    return RunHistory(
        run_dir=run_dir, task=str(meta.get("task", "?")), side=str(meta.get("side", "?")),
        reward=np.array([r.reward for r in records], dtype=float), legal=np.array([bool(r.legal) for r in records], dtype=bool),
        batch=np.array([int(r.batch) for r in records], dtype=np.int64), seconds=np.array([float(r.seconds) for r in records], dtype=float),
    )  # fmt: skip


@dataclass(frozen=True)
class RunSummary:
    """An optimization run folder at a glance (for choosing one to resume)."""

    run_dir: Path
    """The run folder."""
    side: TossSide
    """Toss side."""
    task: str
    """Reward task."""
    seed: int
    """HEBO seed."""
    population: int
    """Suggestions per batch."""
    iterations: int
    """HEBO batches asked for by the last call."""
    tosses: int
    """Tosses per evaluation."""
    seeds: int
    """Hand-designed seed serves the run observed first (a resume takes them from its
    ``run.json``)."""
    limit_scale: LimitScale
    """Dynamic limit expansion of the run."""
    evaluations: int
    """Evaluations logged (complete lines)."""
    best_reward: float
    """Best reward logged [-] (-inf without evaluations)."""

    @property
    def planned(self) -> int:
        """Evaluations of the whole run: seeds + iterations x population."""
        return self.seeds + self.iterations * self.population

    def label(self) -> str:
        """One line for a list: folder, progress and best reward."""
        best = f"best {self.best_reward:+.3f}" if math.isfinite(self.best_reward) else "nothing evaluated"
        return f"{self.run_dir.name}: {self.evaluations}/{self.planned} evaluations, {best}"


_LOG_SUMMARIES: dict[Path, tuple[tuple[int, int], tuple[int, float]]] = {}
"""(size, mtime) -> (evaluations, best reward) of run logs already read (:func:`list_runs`
is called on every side/task change in the studio; logs only grow)."""


def _log_summary(run_dir: Path) -> tuple[int, float]:
    """(evaluations, best reward) of a run folder's log, cached by its size and mtime."""
    log = run_dir / "evaluations.jsonl"
    try:
        st = log.stat()
    except FileNotFoundError:
        return 0, -math.inf
    key = (st.st_size, st.st_mtime_ns)
    hit = _LOG_SUMMARIES.get(log)
    if hit is not None and hit[0] == key:
        return hit[1]
    history = load_run_history(run_dir)
    out = (len(history.reward), float(history.reward.max()) if len(history.reward) else -math.inf)
    _LOG_SUMMARIES[log] = (key, out)
    return out


def list_runs(
    runs_dir: str | Path, *, side: str | None = None, task: str | None = None
) -> tuple[list[RunSummary], list[str]]:
    """The optimization runs directly inside ``runs_dir`` (newest folder name first),
    optionally only those of ``side`` and ``task``, and one message per folder that holds a
    ``run.json`` but cannot be read (file and field named). An absent folder has no runs."""
    runs: list[RunSummary] = []
    problems: list[str] = []
    folder = Path(runs_dir)
    if not folder.is_dir():
        return runs, problems
    for run_dir in sorted(
        (d for d in folder.iterdir() if (d / "run.json").is_file()), key=lambda d: d.name, reverse=True
    ):
        try:
            meta = read_run_meta(run_dir)
            if (side is not None and meta.get("side") != side) or (task is not None and meta.get("task") != task):
                continue
            evaluations, best = _log_summary(run_dir)
            runs.append(RunSummary(
                run_dir=run_dir, side=meta["side"], task=str(meta["task"]), seed=int(meta["seed"]), population=int(meta["population"]),
                iterations=int(meta["iterations"]), tosses=int(meta["tosses"]), seeds=len(meta.get("seeds", [])), limit_scale=LimitScale.from_json(meta["limit_scale"]),
                evaluations=evaluations, best_reward=best,
            ))  # fmt: skip
        except (DataFileError, KeyError, TypeError, ValueError) as exc:
            problems.append(
                str(exc)
                if isinstance(exc, DataFileError)
                else f"{run_dir / 'run.json'}: missing or malformed field ({exc!r})"
            )
    return runs, problems


class _Log:
    """The run's ``evaluations.jsonl``, opened for appending (after a missing final newline
    of a complete last record is repaired: :func:`studio.storage.jsonlog.ensure_line_end`)."""

    def __init__(self, path: Path) -> None:
        ensure_line_end(path, EvaluationRecord.from_json)
        self.f = open(path, "a", encoding="utf-8")

    def write(self, rec: EvaluationRecord) -> None:
        write_line(self.f, asdict(rec))

    def close(self) -> None:
        self.f.close()


# -- the loop ---------------------------------------------------------------------------


def _final_candidates(
    records: Sequence[EvaluationRecord], pool: EvaluatorPool, *, top_k: int, final_tosses: int, seed: int, spread: float
) -> list[FinalCandidate]:
    """The ``top_k`` best candidates of the log (training reward) that lie farther than
    ``spread`` from every better one (Euclidean distance of normalized genomes; 0: all
    distinct ones), each re-evaluated on ``final_tosses`` fresh recorded tosses, ranked
    legal first (legal on at least the pool's ``min_legal_fraction`` of them), then by
    mean reward.

    Legal first because the mean reward of a serve that misses a few tosses can still
    beat that of one legal on all of them (a miss costs a bounded penalty), and the run's
    serve should be one that is legal on most real tosses. The spread keeps the
    candidates from being one basin's near-copies (in a recorded run the best distinct
    candidates were all one serve, and the spread brought in a more robust one:
    ``docs/optimization.md#training-time``).
    """
    candidates: list[FinalCandidate] = []
    if not records or top_k <= 0:
        return candidates
    picked: list[EvaluationRecord] = []
    for r in sorted(records, key=lambda r: (-r.reward, r.index)):
        if all(
            not np.allclose(r.genome, q.genome, atol=1e-9)
            and float(np.linalg.norm(np.subtract(r.genome, q.genome))) > spread
            for q in picked
        ):
            picked.append(r)
        if len(picked) == top_k:
            break
    Xf = np.array([[r.params[g] for g in GENE_NAMES] for r in picked])
    fseeds = [int(np.random.SeedSequence([seed, 2, k]).generate_state(1)[0]) for k in range(len(picked))]
    for r, x, (out, _sec) in zip(picked, Xf, pool.map(Xf, tosses=final_tosses, rng_seeds=fseeds)):
        rewards = out.rewards if out.rewards else (out.reward,)
        candidates.append(
            FinalCandidate(
                ServeParams.from_vector(x),
                tuple(r.genome),
                r.reward,
                float(out.reward),
                bool(out.legal),
                float(out.legal_fraction),
                tuple(rewards),
            )
        )
    candidates.sort(key=lambda c: (not c.legal, -c.mean_reward))
    return candidates


ProgressFn = Callable[[int, int, float, "ServeParams | None"], None]
"""``progress(evaluations done, total, best reward so far, best params so far)``."""
RecordFn = Callable[[dict[str, Any]], None]
"""``on_record(record)``: the JSON object of a new ``evaluations.jsonl`` line."""


@dataclass(frozen=True, kw_only=True)
class OptimizeOptions:
    """What :func:`optimize_serve` optimizes and how: the run's settings (its ``run.json``).

    The runtime hooks (progress, stop, record streaming, an injected evaluation) are
    arguments of :func:`optimize_serve`, not options. Checked on construction: a bad
    value raises :class:`~studio.errors.InvalidInputError`.
    """

    side: TossSide
    """Toss side; seeds of the other side are rejected."""
    task: str
    """Reward task preset (:func:`studio.serve.reward.task_weights`)."""
    iterations: int = 100
    """HEBO batches (paper: 100); a resumed run goes on to this many."""
    population: int = 20
    """Suggestions per batch (paper: 20)."""
    tosses: int = 5
    """Tosses per training evaluation (1: mean toss; K > 1: K recorded tosses drawn per
    evaluation, mean reward, legal if >= ``min_legal_fraction`` legal). Default 5, as
    ``serve-studio optimize`` and ``train``: robust by default (module docstring)."""
    min_legal_fraction: float = 0.8
    """Fraction of legal tosses that makes a multi-toss evaluation (and a final candidate) legal."""
    seed: int = 0
    """Seeds HEBO (numpy, torch, pymoo) and the toss draws."""
    workers: int = 2
    """Evaluation processes (spawned); 1 evaluates in this process."""
    bounds: GenomeBounds | None = None
    """Genome bounds; ``None``: :func:`bounds_for_toss` of the side's toss model."""
    config: HeboConfig | None = None
    """HEBO cost knobs (:class:`HeboConfig`); ``None``: the defaults, or on resume the run's
    own configuration."""
    top_k: int = 10
    """Candidates of the final pick: the ``top_k`` best of the log at least ``final_spread``
    apart are re-evaluated on ``final_tosses`` fresh recorded tosses; the best mean among
    those legal on ``min_legal_fraction`` of them wins (:func:`_final_candidates`). Before
    issue 16 the pick was ``top_k=5, final_spread=0``, ranked by mean reward alone."""
    final_tosses: int = 10
    """Fresh recorded tosses of each final candidate's re-evaluation."""
    final_spread: float = 0.05
    """Least distance between final candidates (normalized genome; 0: distinct)."""
    ipopt_fallback: bool = False
    """Let the strike planner fall back to IPOPT when its SQP misses (off by default in
    training: :meth:`EvaluationContext.for_training`)."""
    overlap: bool | None = None
    """Suggest batch i+1 while the worker processes evaluate batch i, from the observations
    up to batch i-1, with batch i as pending points (kriging believer,
    :attr:`HeboConfig.fantasize`): the suggestion runs beside the evaluation, so a run
    takes less wall time, and the reward stays within the seed-to-seed spread of the
    sequential loop (figures: ``docs/optimization.md#sequential-against-overlapped-suggestions``).
    ``None``: on when ``workers > 1`` and the evaluation is the real one (with one
    process the evaluation cannot run beside the suggestion); on resume the run's own loop."""
    limit_scale: LimitScale | None = None
    """The paper's dynamic limit expansion (:class:`~studio.serve.params.LimitScale`): every
    candidate, the seeds included, is planned with the robot's derivative limits times these
    factors, and the chosen serve carries them (a seed's own scale is replaced by the run's).
    ``None``: the robot's own limits, or on resume the run's own scale."""

    def __post_init__(self) -> None:
        if self.iterations < 0 or self.population < 1:
            raise InvalidInputError(
                f"iterations must be >= 0 and population >= 1, got {self.iterations}, {self.population}"
            )
        if not self.final_spread >= 0.0:
            raise InvalidInputError(f"final_spread must be >= 0, got {self.final_spread}")
        if self.side not in ("right", "left"):
            raise InvalidInputError(f"side must be 'right' or 'left', got {self.side!r}")
        if self.workers < 1:
            raise InvalidInputError(f"workers must be >= 1, got {self.workers}")


_RESUME_KEYS = (
    "side",
    "task",
    "seed",
    "population",
    "tosses",
    "bounds",
    "config",
    "min_legal_fraction",
    "ipopt_fallback",
    "overlap",
    "limit_scale",
)
"""``run.json`` fields a resumed run must share with the call that resumes it."""


def _fill_legacy_meta(old: dict[str, Any], config: HeboConfig) -> None:
    """Fill in, in place, what a ``run.json`` logged before later options lacks: the values
    those runs ran with (``config``: the caller's configuration, for ``fantasize``)."""
    old.setdefault("ipopt_fallback", False)  # runs logged before these options existed
    old.setdefault("overlap", False)
    cfg_old = old.setdefault("config", {})
    cfg_old.setdefault("fast_gp", False)  # runs logged before the option: HEBO's gpytorch GP
    # pending points exist only with overlap; earlier overlapped runs did not fantasize
    cfg_old.setdefault("fantasize", False if old["overlap"] else config.fantasize)
    for key, value in _CONFIG_BEFORE_WARM_STARTS.items():  # runs logged before warm starts
        cfg_old.setdefault(key, value)


class OptimizationRun:
    """One :func:`optimize_serve` call, with its state explicit.

    On construction the options are resolved against the run folder (on resume the run's
    own seeds, scale, loop and HEBO configuration); :meth:`execute` then starts the worker
    pool, writes or checks ``run.json``, re-observes the logged records, runs the seed
    batch and the HEBO batches (with ``overlap`` suggesting the next batch while the
    current one is evaluated), makes the final pick and returns the result.

    State: :attr:`records` (the log, in order), :attr:`timings`, :attr:`stopped`,
    :attr:`ahead` (suggestions made ahead, by batch), the resolved :attr:`overlap`,
    :attr:`config`, :attr:`limit_scale`, :attr:`bounds` and :attr:`seeds`, and while it
    executes the HEBO adapter :attr:`opt` and the open log :attr:`log`. Arguments as
    :func:`optimize_serve`'s.
    """

    bounds: GenomeBounds
    """The genome bounds (resolved by :meth:`execute`)."""
    low: npt.NDArray[np.float64]
    """Lower physical bounds of the genes (10,)."""
    high: npt.NDArray[np.float64]
    """Upper physical bounds of the genes (10,)."""
    opt: HeboAdapter
    """The HEBO adapter (made by :meth:`execute`)."""
    log: _Log
    """The open ``evaluations.jsonl`` (while :meth:`execute` runs)."""

    def __init__(
        self,
        options: OptimizeOptions,
        *,
        run_dir: str | Path,
        context: Any = None,
        seeds: Sequence[HandServe] = (),
        resume: bool = False,
        progress: ProgressFn | None = None,
        stop: threading.Event | None = None,
        on_record: RecordFn | None = None,
        evaluate: EvaluateFn | None = None,
    ) -> None:
        self.t_start = time.perf_counter()
        self.options = options
        self.run_dir = Path(run_dir)
        self.log_path = self.run_dir / "evaluations.jsonl"
        self.context = context
        self.progress = progress
        self.stop = stop
        self.on_record = on_record
        self.evaluate = evaluate
        self.overlap = options.overlap if options.overlap is not None else options.workers > 1 and evaluate is None
        self.config = options.config if options.config is not None else HeboConfig()
        for s in seeds:
            if s.side != options.side:
                raise InvalidInputError(
                    f"seed serve {s.name!r} is for the {s.side} toss, the run is for the {options.side} toss"
                )
        self.resume = resume
        self.old = read_run_meta(self.run_dir) if resume and (self.run_dir / "run.json").exists() else None
        if options.limit_scale is not None:
            self.limit_scale = options.limit_scale
        else:  # a resumed run keeps its own scale
            self.limit_scale = LimitScale.from_json(self.old["limit_scale"]) if self.old is not None else LimitScale()
        self.seeds = self._own_seeds(seeds)
        self.penalty = -PLANNER_FAILURE_PENALTY if PLANNER_FAILURE_PENALTY < 0 else PLANNER_FAILURE_PENALTY
        self.records: list[EvaluationRecord] = []
        self.timings = {
            "suggest": 0.0,
            "suggest_cpu": 0.0,
            "suggest_overlapped": 0.0,
            "evaluate": 0.0,
            "evaluate_cpu": 0.0,
            "final": 0.0,
        }
        self.stopped = False
        self.ahead: dict[int, npt.NDArray[np.float64]] = {}

    def _own_seeds(self, seeds: Sequence[HandServe]) -> Sequence[HandServe]:
        """``seeds``, or for a resumed run given none its own (``run.json`` keeps them)."""
        if self.old is None or seeds or not self.old.get("seeds"):
            return seeds
        from studio.serve.params import serve_from_json

        source = self.run_dir / "run.json"
        return [serve_from_json(d, source=f"{source}: seeds[{i}]") for i, d in enumerate(self.old["seeds"])]

    @property
    def total(self) -> int:
        """Evaluations of the whole run: seeds + iterations x population."""
        return len(self.seeds) + self.options.iterations * self.options.population

    # -- setting up ------------------------------------------------------------------

    def _pool(self) -> EvaluatorPool:
        o = self.options
        return EvaluatorPool(
            side=o.side,
            task=o.task,
            workers=o.workers,
            min_legal_fraction=o.min_legal_fraction,
            evaluate=self.evaluate,
            context=self.context,
            ipopt_fallback=o.ipopt_fallback,
            limit_scale=self.limit_scale,
        )

    def _resolve_bounds(self) -> GenomeBounds:
        """The options' bounds, else those of the side's toss model (the context's, if given)."""
        if self.options.bounds is not None:
            return self.options.bounds
        if self.context is not None:
            toss = self.context.toss_model(self.options.side)
        else:
            from studio.toss.defaults import load_default_toss_model

            toss = load_default_toss_model(self.options.side)
        return bounds_for_toss(toss)

    def _run_json(self, bounds: GenomeBounds) -> dict[str, Any]:
        o = self.options
        return {
            "schema": RUN_SCHEMA,
            "side": o.side,
            "task": o.task,
            "seed": o.seed,
            "iterations": o.iterations,
            "population": o.population,
            "tosses": o.tosses,
            "min_legal_fraction": o.min_legal_fraction,
            "bounds": _bounds_json(bounds),
            "genes": list(GENE_NAMES),
            "config": self.config.to_json(),
            "ipopt_fallback": bool(o.ipopt_fallback),
            "overlap": bool(self.overlap),
            "limit_scale": self.limit_scale.to_json(),
            "seeds": [replace(s, limit_scale=self.limit_scale).to_json() for s in self.seeds],  # at the run's scale
        }

    def _adopt_old(self, old: dict[str, Any], run_json: dict[str, Any]) -> None:
        """Resume: take the run's own loop and HEBO configuration unless the options chose
        them, then refuse a ``run.json`` that differs from this call (field named)."""
        _fill_legacy_meta(old, self.config)
        if self.options.overlap is None:  # a resumed run keeps its own loop unless the caller chose one
            self.overlap = bool(old["overlap"])
            run_json["overlap"] = self.overlap
        if self.options.config is None:  # likewise its HEBO configuration
            try:
                self.config = HeboConfig(**old["config"])
            except (TypeError, InvalidInputError) as exc:
                raise InvalidInputError(
                    f"resume: {self.run_dir / 'run.json'}: unusable HEBO configuration {old['config']!r} ({exc})"
                ) from exc
            run_json["config"] = self.config.to_json()
        for key in _RESUME_KEYS:
            if old.get(key) != json.loads(json.dumps(run_json[key])):
                raise InvalidInputError(
                    f"resume: {self.run_dir / 'run.json'} has {key}={old.get(key)!r}, this call has {run_json[key]!r}"
                )

    def _open(self) -> None:
        """Bounds, the run folder and its ``run.json`` (a resumed one's checked), the logged
        records, and the HEBO adapter that has observed them."""
        self.bounds = self._resolve_bounds()
        if self.evaluate is None:
            from studio.serve.reward import task_weights

            task_weights(self.options.task)  # validate the name early
        self.low, self.high = self.bounds.lows_highs()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        run_json = self._run_json(self.bounds)
        if self.old is not None:
            self._adopt_old(self.old, run_json)
            self.records = read_evaluations(self.log_path)
        elif self.log_path.exists() and self.log_path.stat().st_size > 0:
            if self.resume:
                raise InvalidInputError(f"cannot resume {self.log_path}: {self.run_dir / 'run.json'} is missing")
            raise InvalidInputError(f"{self.log_path} already holds a run: pass resume=True or use another run_dir")
        if self.overlap and self.config.fantasize and not self.config.fast_gp:
            raise InvalidInputError(
                "overlapped suggestions with HeboConfig.fantasize need HeboConfig.fast_gp (HEBO's gpytorch GP cannot take pending points): set fantasize=False or overlap=False"
            )
        (self.run_dir / "run.json").write_text(json.dumps(run_json, indent=2))
        self.opt = HeboAdapter(len(GENE_NAMES), seed=self.options.seed, config=self.config, penalty=self.penalty)
        if self.records:
            self.opt.observe(np.array([r.genome for r in self.records]), -np.array([r.reward for r in self.records]))

    # -- the loop --------------------------------------------------------------------

    def execute(self) -> OptimizationResult:
        """Run the seeds and the batches, make the final pick; the result of the call."""
        # the workers start first and initialize while this process loads the toss model and HEBO
        with self._pool() as pool:
            self._open()
            self.log = _Log(self.log_path)
            try:
                self._run_seeds(pool)
                self._run_iterations(pool)
                candidates = self._final_pick(pool)
            except WorkerDiedError as exc:
                raise WorkerDiedError(
                    f"{exc}; the {len(self.records)} evaluations finished before are logged in {self.log_path}: "
                    f"continue the run with --resume --run-dir {self.run_dir}"
                ) from None
            finally:
                self.log.close()
            return self._result(candidates)

    def _stopping(self) -> bool:
        return self.stop is not None and self.stop.is_set()

    def _best(self) -> tuple[float, ServeParams | None]:
        """The best logged reward and its parameters (-inf, None before the first)."""
        if not self.records:
            return -math.inf, None
        r = max(self.records, key=lambda r: r.reward)
        return r.reward, ServeParams.from_vector([r.params[g] for g in GENE_NAMES])

    def _report(self) -> None:
        if self.progress is not None:
            b, p = self._best()
            self.progress(len(self.records), self.total, b, p)

    def _run_seeds(self, pool: EvaluatorPool) -> None:
        """Evaluate the seeds not logged yet (all of them in a new run)."""
        n_seed_done = sum(1 for r in self.records if r.batch == -1)
        if n_seed_done < len(self.seeds):
            todo = list(self.seeds)[n_seed_done:]
            Z = np.array([s.params.normalize(self.bounds) for s in todo])
            self._run_batch(Z, -1, [f"seed:{s.name}" for s in todo], pool)
            self._report()

    def _run_iterations(self, pool: EvaluatorPool) -> None:
        """The HEBO batches: each suggests what its batch misses (all of it unless resumed
        mid-batch), evaluates, logs and observes it; the stop event ends the loop."""
        for it in range(self.options.iterations):
            missing = self.options.population - sum(1 for r in self.records if r.batch == it)
            if missing <= 0:
                continue
            if self._stopping():
                self.stopped = True
                break
            Z = self._suggest(it, missing)
            meanwhile = functools.partial(self._suggest_ahead, it + 1, Z) if self.overlap else None
            self._run_batch(Z, it, ["hebo"] * missing, pool, meanwhile=meanwhile)
            self._report()

    def _run_batch(
        self,
        Z: npt.NDArray[np.float64],
        batch: int,
        sources: list[str],
        pool: EvaluatorPool,
        meanwhile: Callable[[], None] | None = None,
    ) -> None:
        """Evaluate, log and observe the batch Z; ``meanwhile`` runs after the batch was
        handed to the worker processes, before its results are collected."""
        X = self.low + Z * (self.high - self.low)
        start = len(self.records)
        seed = self.options.seed
        rng_seeds = [int(np.random.SeedSequence([seed, 1, start + i]).generate_state(1)[0]) for i in range(len(Z))]
        t0 = time.perf_counter()
        results = pool.map(X, tosses=self.options.tosses, rng_seeds=rng_seeds)
        if meanwhile is not None:
            meanwhile()
        for i, (out, sec) in enumerate(results):
            reward = out.reward if math.isfinite(out.reward) else -self.penalty
            rec = EvaluationRecord(
                index=start + i,
                batch=batch,
                source=sources[i],
                genome=[float(v) for v in Z[i]],
                params={g: float(v) for g, v in zip(GENE_NAMES, X[i])},
                reward=float(reward),
                legal=bool(out.legal),
                status=out.status,
                failed_check=out.failed_check,
                legal_fraction=float(out.legal_fraction),
                seconds=float(sec),
            )
            self.log.write(rec)
            if self.on_record is not None:
                self.on_record(asdict(rec))
            self.records.append(rec)
            self.opt.observe(Z[i : i + 1], np.array([-reward]))
            self.timings["evaluate_cpu"] += sec
        self.timings["evaluate"] += time.perf_counter() - t0

    def _usable(self, it: int) -> int:
        """Observations batch ``it``'s suggestion is made from (a prefix of the log): all
        of them, or with ``overlap`` those of the seeds and the batches up to it - 2 (batch
        0 follows the seeds, nothing is in flight then)."""
        if not self.overlap:
            return len(self.records)
        return sum(1 for r in self.records if r.batch <= max(it - 2, -1))

    def _pending(self, it: int, in_flight: npt.NDArray[np.float64] | None = None) -> npt.NDArray[np.float64] | None:
        """With ``overlap``: the genomes batch ``it``'s suggestion must know of but does not
        observe: batch it - 1 (logged ones plus ``in_flight``, the part being evaluated)
        and, after a resume, the part of batch ``it`` itself that was logged already."""
        if not self.overlap or it < 1:
            return None
        rows = [r.genome for r in self.records if r.batch in (it - 1, it)]
        if in_flight is not None:
            rows += [list(z) for z in in_flight]
        return np.array(rows, dtype=float).reshape(-1, len(GENE_NAMES)) if rows else None

    def _suggest(self, it: int, missing: int) -> npt.NDArray[np.float64]:
        """Batch ``it``'s ``missing`` points: the ones suggested ahead if they fit, else new."""
        t0, c0 = time.perf_counter(), time.process_time()
        queued = self.ahead.pop(it) if it in self.ahead else None
        if queued is not None and len(queued) == missing:
            Z = queued
        else:
            Z = self.opt.suggest(missing, upto=self._usable(it), skip=len(self.records), pending=self._pending(it))
        self.timings["suggest"] += time.perf_counter() - t0
        self.timings["suggest_cpu"] += time.process_time() - c0
        return Z

    def _suggest_ahead(self, nxt: int, batch: npt.NDArray[np.float64]) -> None:
        """Suggest batch ``nxt`` while ``batch`` (the one before it) is being evaluated."""
        if nxt < self.options.iterations and not self._stopping():
            t1, c1 = time.perf_counter(), time.process_time()
            self.ahead[nxt] = self.opt.suggest(
                self.options.population,
                upto=self._usable(nxt),
                skip=len(self.records) + len(batch),
                pending=self._pending(nxt, batch),
            )
            self.timings["suggest"] += time.perf_counter() - t1
            self.timings["suggest_cpu"] += time.process_time() - c1
            self.timings["suggest_overlapped"] += time.perf_counter() - t1

    # -- the end ---------------------------------------------------------------------

    def _final_pick(self, pool: EvaluatorPool) -> list[FinalCandidate]:
        """Top-k distinct candidates, re-evaluated on fresh tosses (:func:`_final_candidates`)."""
        o = self.options
        t0 = time.perf_counter()
        candidates = _final_candidates(
            self.records, pool, top_k=o.top_k, final_tosses=o.final_tosses, seed=o.seed, spread=o.final_spread
        )
        self.timings["final"] = time.perf_counter() - t0
        return candidates

    def _chosen(self, summary: FinalCandidate | None) -> HandServe | None:
        """The chosen serve: the first candidate, named and annotated, at the run's limit scale."""
        if summary is None:
            return None
        o = self.options
        return HandServe(
            name=f"{o.task}_{o.side}_hebo_s{o.seed}",
            side=o.side,
            params=summary.params,
            task=o.task,
            limit_scale=self.limit_scale,
            notes=f"HEBO run {self.run_dir.name}: mean reward {summary.mean_reward:+.3f} over {len(summary.rewards)} tosses, legal fraction {summary.legal_fraction:.2f}",
        )

    def _result(self, candidates: list[FinalCandidate]) -> OptimizationResult:
        summary = candidates[0] if candidates else None
        best_serve = self._chosen(summary)
        self.timings["total"] = time.perf_counter() - self.t_start
        return OptimizationResult(
            best=best_serve,
            summary=summary,
            candidates=tuple(candidates),
            history=np.array([r.reward for r in self.records], dtype=float),
            evaluations=len(self.records),
            stopped=self.stopped,
            timings=self.timings,
            run_dir=self.run_dir,
            observed_X=self.opt.X,
            observed_y=self.opt.y,
            gp_fits=dict(Counter(f.kind for f in self.opt.fits)),
        )


def optimize_serve(
    options: OptimizeOptions,
    *,
    run_dir: str | Path,
    context: Any = None,
    seeds: Sequence[HandServe] = (),
    resume: bool = False,
    progress: ProgressFn | None = None,
    stop: threading.Event | None = None,
    on_record: RecordFn | None = None,
    evaluate: EvaluateFn | None = None,
) -> OptimizationResult:
    """Optimize a serve's genome for ``options.task`` on the ``options.side`` toss with HEBO
    (maximize F); :class:`OptimizeOptions` holds the run's settings, :class:`OptimizationRun`
    does the work.

    Args:
        options: the run's settings (sizes, tosses, seed, workers, bounds, HEBO
            configuration, final pick, loop, limit scale).
        run_dir: folder for ``run.json`` and ``evaluations.jsonl`` (created).
        context: evaluation context for in-process evaluation (``workers == 1``) and for
            the toss model of the default bounds; worker processes build their own.
            Default: built on demand.
        seeds: hand-designed serves evaluated and observed before the first suggestion (on
            resume, none given: the run's own, from its run.json).
        resume: continue the run in ``run_dir`` (its ``run.json`` must match).
        progress: called after the seeds and after each batch with (evaluations done,
            total, best reward so far, best params so far); an exception from it aborts
            the run (the log keeps everything evaluated so far).
        stop: when set, the run ends cleanly before the next batch (final pick still done).
        on_record: called with each new evaluation record (the JSON object of its
            ``evaluations.jsonl`` line) right after it is logged (Ray streaming).
        evaluate: replaces the evaluation (``evaluate(serve, tosses, rng) -> Outcome``),
            run in this process (tests).
    """
    run = OptimizationRun(
        options,
        run_dir=run_dir,
        context=context,
        seeds=seeds,
        resume=resume,
        progress=progress,
        stop=stop,
        on_record=on_record,
        evaluate=evaluate,
    )
    return run.execute()
