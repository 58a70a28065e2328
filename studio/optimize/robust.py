"""Make a serve robust to the toss's variability by a local search around it.

A serve designed on the mean toss path, by hand or by HEBO, often stays legal on only a
few of the recorded tosses: the ball it meets is a centimetre off. The paper makes serves
robust by training on sampled tosses (``OptimizeOptions(tosses=K)``), a global search that
may leave the kind of serve it started from (a run from a backspin example returned only
topspin serves among its best legal candidates: ``docs/evaluation.md#making-a-serve-robust``).
:func:`robustify_serve` searches *around* the serve instead (settings:
:class:`RobustifyOptions`): CMA-ES (``cma``) on the normalized genome
(:class:`studio.serve.params.GenomeBounds`), started at the serve with step ``sigma``, minimizing

    -(legal count over the recorded tosses + 0.1 x mean reward over them)
    + spin deficit / SPIN_PER_TOSS

where the spin deficit [rad/s] is how far the spin components at the net crossing on the
mean toss (top/back and side, each one the starting serve has) fall short of ``keep_spin``
times their starting values (same signs). A candidate illegal on the mean toss
scores :data:`ILLEGAL_ON_MEAN`. The result is the best candidate without spin deficit, or
the starting serve when none beats it: never worse than the start.

Every candidate is planned once on the mean toss (the toss commands are the same for
every recorded toss) and flown on each recorded toss, as :func:`studio.serve.evaluate.evaluate_robust`
does: one plan and 20 flights a candidate with the shipped tosses (timing:
``docs/measured.md``).

Resume: with ``run_dir`` every evaluation is appended to ``robustify.jsonl`` (flushed and
fsynced) next to ``robustify.json`` (settings). CMA-ES's candidates depend only on its
seed and on the values it was told, so a resumed search replays the log (asks, finds each
candidate logged, tells the logged value) and goes on exactly as the uninterrupted search.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from studio.errors import DataFileError, InvalidInputError
from studio.serve.params import GENE_NAMES, GenomeBounds, HandServe, ServeParams
from studio.storage.jsonlog import append_jsonl, read_jsonl

T = TypeVar("T")

ROBUST_SCHEMA = "serve-studio/robustify-run@1"
"""Schema tag of ``robustify.json``."""
LOG_NAME = "robustify.jsonl"
"""Evaluation log of a robustify run folder."""
META_NAME = "robustify.json"
"""Settings of a robustify run folder."""
SPIN_PER_TOSS = 3.0
"""Spin deficit [rad/s] that costs as much as one toss more or less legal (engineering
choice: 10 rad/s of spin lost must buy more than three more legal tosses)."""
ILLEGAL_ON_MEAN = 100.0
"""Objective of a candidate that is not legal on the mean toss (every other objective is
below it: the spin penalty is capped at :data:`MAX_SPIN_PENALTY`)."""
MAX_SPIN_PENALTY = 50.0
"""Cap of the spin-deficit term (a serve whose spin turned round costs this, still less
than one illegal on the mean toss)."""
MIN_SPIN = 20.0
"""A net spin component of the starting serve below this [rad/s] is not worth keeping: no
constraint on it."""


@dataclass(frozen=True, slots=True)
class RobustScore:
    """How one serve fares on the mean toss and on the recorded tosses."""

    mean_legal: bool
    """Legal on the mean toss path."""
    legal: int
    """Recorded tosses on which it is legal."""
    tosses: int
    """Recorded tosses tried."""
    mean_reward: float
    """Mean reward over the recorded tosses [-] (the mean toss's when it is illegal there)."""
    net_topspin: float | None
    """Top/back spin at the net crossing on the mean toss [rad/s] (> 0 topspin; None: no crossing)."""
    net_sidespin: float | None
    """Sidespin at the net crossing on the mean toss [rad/s]."""

    @property
    def legal_fraction(self) -> float:
        """legal / tosses."""
        return self.legal / self.tosses if self.tosses else 0.0


ScoreFn = Callable[[HandServe], RobustScore]
"""Scores a serve (replaces :func:`robust_score` in tests)."""


def robust_score(serve: HandServe, context: Any, *, task: str) -> RobustScore:
    """Plan ``serve`` once on its side's toss and fly the ball on the mean path and on every
    recorded toss (:class:`studio.serve.evaluate.EvaluationContext` ``context``)."""
    from studio.serve.evaluate import evaluate_motion, plan_motion

    motion = plan_motion(serve, context)
    mean = evaluate_motion(motion, context, task=task)
    n = context.toss_model(serve.side).n_tosses
    net = mean.metrics.net if mean.metrics is not None else None
    top = float(net["topspin"]) if net else None
    side = float(net["sidespin"]) if net else None
    if not mean.legal:
        return RobustScore(False, 0, n, float(mean.reward.total), top, side)
    evs = [evaluate_motion(motion, context, task=task, toss_sample=i) for i in range(n)]
    return RobustScore(True, sum(e.legal for e in evs), n, float(np.mean([e.reward.total for e in evs])), top, side)


@dataclass(frozen=True, slots=True)
class SpinKeep:
    """The spin constraint: for each kept component c, ``sign_c * value_c >= floor_c`` at
    the net crossing on the mean toss."""

    components: tuple[tuple[str, float, float], ...]
    """(component "topspin" or "sidespin", sign +1 / -1, least magnitude [rad/s]) of each
    component of the starting serve's net spin worth keeping (|value| >= :data:`MIN_SPIN`)."""

    def deficit(self, score: RobustScore) -> float:
        """How far ``score`` falls short, summed over the components [rad/s] (inf without a
        net crossing)."""
        total = 0.0
        for component, sign, floor in self.components:
            value = score.net_topspin if component == "topspin" else score.net_sidespin
            if value is None:
                return math.inf
            total += max(0.0, floor - sign * value)
        return total

    def describe(self) -> str:
        if not self.components:
            return "no spin to keep"
        names = {
            ("topspin", 1.0): "topspin",
            ("topspin", -1.0): "backspin",
            ("sidespin", 1.0): "sidespin (+)",
            ("sidespin", -1.0): "sidespin (-)",
        }
        return (
            " and ".join(f"{names[(c, sign)]} >= {floor:.0f}" for c, sign, floor in self.components)
            + " rad/s at the net"
        )


def spin_keep(start: RobustScore, keep: float) -> SpinKeep:
    """The constraint for a starting serve: ``keep`` of each of its net spin components
    (top/back, side) of at least :data:`MIN_SPIN`, with its sign."""
    out = []
    for component, value in (("topspin", start.net_topspin), ("sidespin", start.net_sidespin)):
        if value is not None and abs(value) >= MIN_SPIN and keep > 0.0:
            out.append((component, math.copysign(1.0, value), keep * abs(value)))
    return SpinKeep(tuple(out))


def objective(score: RobustScore, keep: SpinKeep) -> float:
    """The value CMA-ES minimizes (module docstring)."""
    if not score.mean_legal:
        return ILLEGAL_ON_MEAN
    penalty = min(keep.deficit(score) / SPIN_PER_TOSS, MAX_SPIN_PENALTY)
    return -(score.legal + 0.1 * score.mean_reward) + penalty


@dataclass(frozen=True)
class RobustifyResult:
    """The outcome of :func:`robustify_serve`."""

    serve: HandServe
    """The chosen serve (the starting one when nothing beat it); name, side, task and
    limit scale as the start's, notes extended."""
    start: RobustScore
    """The starting serve's score."""
    best: RobustScore
    """The chosen serve's score."""
    keep: SpinKeep
    """The spin constraint applied."""
    evaluations: int
    """Candidates scored (logged ones included)."""
    stopped: bool
    """Ended by ``stop`` before the budget."""
    run_dir: Path | None
    """The run folder, if any."""
    improved: bool
    """A candidate beat the starting serve."""

    def summary(self) -> str:
        """One paragraph for a person: what was kept, tried and found."""

        def spin(sc: RobustScore) -> str:
            top, side = ("-" if v is None else f"{v:+.0f}" for v in (sc.net_topspin, sc.net_sidespin))
            return f"net spin top/back {top}, side {side} rad/s"

        s0, s1 = self.start, self.best
        head = f"{'Stopped' if self.stopped else 'Done'} after {self.evaluations} candidates, keeping {self.keep.describe()}."
        start = f"Start: legal on {s0.legal}/{s0.tosses} recorded tosses{'' if s0.mean_legal else ', NOT legal on the mean toss'}, {spin(s0)}."
        if not self.improved:
            return f"{head} {start} No candidate beat it."
        return f"{head} {start} Found: legal on {s1.legal}/{s1.tosses} recorded tosses, {spin(s1)}."


def _log_record(d: Any) -> dict[str, Any]:
    """Validate one logged candidate (``index``, ``genome``, ``objective``, ``score``)."""
    if not isinstance(d, dict) or not isinstance(d.get("genome"), list) or len(d["genome"]) != len(GENE_NAMES):
        raise ValueError("not a robustify record")
    d["objective"] = float(d["objective"])
    d["score"] = RobustScore(**d["score"])
    return d


def _check_settings(keep_spin: float, sigma: float, evaluations: int, population: int, seed: int) -> None:
    """Raise InvalidInputError naming the first robustify setting out of range."""
    for name, value, ok in (
        ("keep_spin", keep_spin, isinstance(keep_spin, (int, float)) and 0.0 <= keep_spin <= 1.0),
        ("sigma", sigma, isinstance(sigma, (int, float)) and 0.0 < sigma <= 0.5),
        ("evaluations", evaluations, isinstance(evaluations, int) and evaluations >= 1),
        ("population", population, isinstance(population, int) and population >= 4),
        ("seed", seed, isinstance(seed, int) and 0 <= seed < 2**31 - 1),
    ):
        if isinstance(value, bool) or not ok:
            raise InvalidInputError(
                f"robustify: {name} out of range, got {value!r} (keep_spin in [0, 1], sigma in (0, 0.5], "
                "whole numbers evaluations >= 1, population >= 4, 0 <= seed < 2**31 - 1)"
            )


@dataclass(frozen=True, kw_only=True)
class RobustifyOptions:
    """What :func:`robustify_serve` searches for and how: the search's settings.

    The runtime hooks (progress, stop, an injected score) and places (context, run folder,
    resume) are arguments of :func:`robustify_serve`, not options. Checked on construction:
    a setting out of range raises :class:`~studio.errors.InvalidInputError` naming it.
    """

    task: str | None = None
    """Reward task of the mean-reward tie-break; ``None``: the serve's, else
    topspin_velocity."""
    keep_spin: float = 0.9
    """Fraction in [0, 1] of each of the starting serve's net spin components to keep."""
    sigma: float = 0.03
    """CMA-ES initial step on the normalized genome, in (0, 0.5]."""
    evaluations: int = 600
    """Candidates to score in all (>= 1), rounded up to whole generations of
    ``population`` (a resumed search counts the logged ones; logged candidates beyond the
    budget are not used)."""
    population: int = 12
    """CMA-ES population (>= 4)."""
    seed: int = 0
    """CMA-ES seed, 0 <= seed < 2**31 - 1."""
    bounds: GenomeBounds | None = None
    """Genome bounds; ``None``: :func:`studio.optimize.optimizer.bounds_for_toss` of the
    serve's side."""

    def __post_init__(self) -> None:
        _check_settings(self.keep_spin, self.sigma, self.evaluations, self.population, self.seed)
        if self.task is not None:
            from studio.serve.reward import task_weights

            task_weights(self.task)  # an unknown task: InvalidInputError naming the known ones
        if self.bounds is not None and not isinstance(self.bounds, GenomeBounds):
            raise InvalidInputError(f"robustify: bounds must be a GenomeBounds, got {type(self.bounds).__name__}")


def _model_scorer(context: Any, task: str) -> tuple[ScoreFn, Any]:
    """:func:`robust_score` on ``context`` (default: the shipped models) and that context;
    an unknown task fails first."""
    from studio.serve.reward import task_weights

    task_weights(task)  # an unknown task fails before anything is loaded or written
    if context is None:
        from studio.serve.evaluate import EvaluationContext

        context = EvaluationContext.default()
    ctx = context

    def score(s: HandServe) -> RobustScore:
        return robust_score(s, ctx, task=task)

    return score, context


def _default_bounds(serve: HandServe, context: Any) -> GenomeBounds:
    """The optimizer's genome bounds for the serve's toss (the context's, else the shipped one)."""
    from studio.optimize.optimizer import bounds_for_toss

    if context is None:
        from studio.toss.defaults import load_default_toss_model

        return bounds_for_toss(load_default_toss_model(serve.side))
    return bounds_for_toss(context.toss_model(serve.side))


def _open_run(run_dir: str | Path, meta: dict[str, Any], resume: bool) -> tuple[list[dict[str, Any]], Path]:
    """Prepare the run folder: check a resumed search's settings, read its log, write the settings."""
    folder = Path(run_dir)
    folder.mkdir(parents=True, exist_ok=True)
    log_path = folder / LOG_NAME
    meta_path = folder / META_NAME
    log: list[dict[str, Any]] = []
    if resume and meta_path.exists():
        _check_meta(meta_path, meta)
        log = read_jsonl(log_path, _log_record)
    elif log_path.exists() and log_path.stat().st_size > 0:
        raise InvalidInputError(f"{log_path} already holds a search: pass resume=True or use another folder")
    meta_path.write_text(json.dumps(meta, indent=2), encoding="utf-8")
    return log, log_path


def _check_meta(meta_path: Path, meta: dict[str, Any]) -> None:
    """Raise DataFileError when the logged search's settings differ from this call's."""
    try:
        old = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DataFileError(meta_path, f"not readable JSON ({exc})") from None
    for key, value in json.loads(json.dumps(meta)).items():
        if not isinstance(old, dict) or old.get(key) != value:
            raise DataFileError(
                meta_path,
                f"field {key!r}: the logged search has {old.get(key) if isinstance(old, dict) else old!r}, this call {value!r}",
            )


def _keeping_global_rng(call: Callable[[], T]) -> T:
    """``call()`` with numpy's global random state restored afterwards (cma touches it)."""
    saved = np.random.get_state()
    try:
        return call()
    finally:
        np.random.set_state(saved)


def _new_strategy(z0: npt.NDArray[np.float64], sigma: float, population: int, seed: int) -> Any:
    """A CMA-ES on [0, 1]^n started at ``z0`` that draws from its own seeded generator."""
    import cma

    # CMA-ES draws from its own generator (cma would reseed and use numpy's global one);
    # numpy's global state is restored around every call into cma all the same
    rng = np.random.default_rng(seed)
    options = {"popsize": population, "seed": seed + 1, "bounds": [0.0, 1.0], "verbose": -9, "randn": lambda *shape: rng.standard_normal(shape)}  # fmt: skip
    return _keeping_global_rng(lambda: cma.CMAEvolutionStrategy(z0, sigma, options))


@dataclass
class _Search:
    """A running robustness search: what it scores with, its log, and the best candidate so far."""

    serve: HandServe
    """The starting serve."""
    bounds: GenomeBounds
    """Genome bounds (candidates are normalized genomes in [0, 1])."""
    score: ScoreFn
    """Scores a candidate."""
    keep: SpinKeep
    """The spin constraint."""
    log: list[dict[str, Any]]
    """Logged candidates to replay (resume)."""
    log_path: Path | None
    """Where new candidates are logged, if anywhere."""
    best_serve: HandServe
    """Best candidate so far (the start until one beats it)."""
    best_score: RobustScore
    """Its score."""
    best_obj: float
    """Its objective."""
    done: int = 0
    """Candidates scored or replayed."""

    def candidate(self, z: npt.NDArray[np.float64]) -> HandServe:
        """The serve of normalized genome ``z``."""
        low, high = self.bounds.lows_highs()
        return replace(self.serve, params=ServeParams.from_vector(low + z * (high - low)))

    def replayed(self, z: npt.NDArray[np.float64]) -> tuple[float, RobustScore]:
        """The logged objective and score of the next candidate (DataFileError if the log differs)."""
        rec = self.log[self.done]
        if rec.get("index") != self.done or not np.allclose(rec["genome"], z, rtol=0, atol=1e-9):
            raise DataFileError(
                self.log_path,
                f"line {self.done + 1}: the logged candidate differs from the replayed one (not this search's log)",
            )
        return rec["objective"], rec["score"]

    def scored(self, z: npt.NDArray[np.float64]) -> tuple[float, RobustScore]:
        """Score the next candidate and log it."""
        sc = self.score(self.candidate(z))
        value = objective(sc, self.keep)
        if self.log_path is not None:
            append_jsonl(
                self.log_path,
                {"index": self.done, "genome": [float(v) for v in z], "objective": value, "score": asdict(sc)},
            )
        return value, sc

    def generation(self, es: Any) -> None:
        """Ask CMA-ES for a generation, score (or replay) it, keep the best, tell the values."""
        Z = _keeping_global_rng(lambda: [np.clip(np.asarray(z, dtype=float), 0.0, 1.0) for z in es.ask()])
        values = []
        for z in Z:
            value, sc = self.replayed(z) if self.done < len(self.log) else self.scored(z)
            values.append(value)
            if self.keep.deficit(sc) == 0 and value < self.best_obj:
                self.best_serve, self.best_score, self.best_obj = self.candidate(z), sc, value
            self.done += 1
        _keeping_global_rng(lambda: es.tell([list(z) for z in Z], values))


def robustify_serve(
    serve: HandServe,
    options: RobustifyOptions | None = None,
    *,
    context: Any = None,
    run_dir: str | Path | None = None,
    resume: bool = False,
    progress: Callable[[int, int, RobustScore], None] | None = None,
    stop: threading.Event | None = None,
    score: ScoreFn | None = None,
) -> RobustifyResult:
    """Search around ``serve`` for one that is legal on more recorded tosses (module docstring);
    :class:`RobustifyOptions` holds the search's settings.

    Args:
        serve: the starting serve (its side's tosses are used; its limit scale is kept).
        options: the search's settings (task, spin kept, CMA-ES step, budget, population,
            seed, bounds); ``None``: the defaults.
        context: :class:`studio.serve.evaluate.EvaluationContext` (default: the shipped models).
        run_dir: folder for ``robustify.json`` and ``robustify.jsonl`` (optional).
        resume: continue the search logged in ``run_dir`` (same settings required).
        progress: called after each generation with (candidates done, budget in whole
            generations, best score so far).
        stop: when set, the search ends after the current generation.
        score: replaces :func:`robust_score` (tests).

    Raises:
        InvalidInputError: resume without ``run_dir``, an unknown task (settings out of
            range are refused by :class:`RobustifyOptions`); DataFileError: a log that does
            not belong to this search.
    """
    opts = options if options is not None else RobustifyOptions()
    keep_spin, sigma, population, seed = opts.keep_spin, opts.sigma, opts.population, opts.seed
    if resume and run_dir is None:
        raise InvalidInputError("robustify: resume needs run_dir")
    task = opts.task or serve.task or "topspin_velocity"
    if score is None:
        score, context = _model_scorer(context, task)
    bounds = opts.bounds if opts.bounds is not None else _default_bounds(serve, context)
    start_score = score(serve)
    keep = spin_keep(start_score, keep_spin)
    meta = {
        "schema": ROBUST_SCHEMA, "serve": serve.to_json(), "task": task, "keep_spin": keep_spin, "sigma": sigma,
        "population": population, "seed": seed, "bounds": asdict(bounds),
        # the models' verdict on the start: a resume on other tosses, robot or physics would mix objectives
        "start": asdict(start_score),
    }  # fmt: skip
    log, log_path = _open_run(run_dir, meta, resume) if run_dir is not None else ([], None)
    z0 = np.clip(serve.params.normalize(bounds), 0.0, 1.0)  # a start outside the bounds: the nearest genome
    es = _new_strategy(z0, sigma, population, seed)
    budget = -(-opts.evaluations // population) * population  # whole generations
    search = _Search(serve, bounds, score, keep, log, log_path, serve, start_score, objective(start_score, keep))
    stopped = False
    while search.done < opts.evaluations:
        if stop is not None and stop.is_set():
            stopped = True
            break
        search.generation(es)
        if progress is not None:
            progress(search.done, budget, search.best_score)
    return _result(serve, search, start_score, sigma, stopped, run_dir)


def _result(
    serve: HandServe, search: _Search, start_score: RobustScore, sigma: float, stopped: bool, run_dir: str | Path | None
) -> RobustifyResult:
    """The search's outcome; an improved serve's notes say how it was found."""
    best_serve, best_score, done, keep = search.best_serve, search.best_score, search.done, search.keep
    improved = best_serve is not serve
    if improved:
        note = (
            f"Made robust by robustify (CMA-ES sigma {sigma}, {done} candidates, keeping {keep.describe()}): "
            f"legal on {best_score.legal}/{best_score.tosses} recorded tosses (was {start_score.legal}/{start_score.tosses})."
        )
        best_serve = replace(best_serve, notes=(serve.notes + " " + note).strip())
    return RobustifyResult(
        best_serve,
        start_score,
        best_score,
        keep,
        done,
        stopped,
        Path(run_dir) if run_dir is not None else None,
        improved,
    )


RUN_SUBDIR = "robustify"
"""Sub-folder of an optimization run that logs the robustness search of its chosen serve."""


def robustify_chosen(
    serve: HandServe, run_dir: str | Path, *, evaluations: int, task: str, context: Any = None
) -> RobustifyResult:
    """:func:`robustify_serve` on an optimization run's chosen serve, logged in
    ``run_dir/robustify/`` and resumed from there when that search was started before
    (``optimize``/``train --robustify``)."""
    folder = Path(run_dir) / RUN_SUBDIR
    return robustify_serve(
        serve,
        RobustifyOptions(task=task, evaluations=evaluations),
        context=context,
        run_dir=folder,
        resume=(folder / META_NAME).exists(),
    )
