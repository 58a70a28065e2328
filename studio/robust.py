"""Make a serve robust to the toss's variability by a local search around it.

A serve designed on the mean toss path, by hand or by HEBO, often stays legal on only a
few of the recorded tosses: the ball it meets is a centimetre off. The paper makes serves
robust by training on sampled tosses (``optimize_serve(tosses=K)``), a global search that
may leave the kind of serve it started from (session 11: on the left backspin example an
800-evaluation run on the ``backspin_net`` task returned only topspin serves among its 40
best legal candidates). :func:`robustify_serve` searches *around* the serve instead:
CMA-ES (``cma``) on the normalized genome (:class:`studio.serve.GenomeBounds`), started at
the serve with step ``sigma``, minimizing

    -(legal count over the recorded tosses + 0.1 x mean reward over them)
    + spin deficit / SPIN_PER_TOSS

where the spin deficit [rad/s] is how far the dominant spin component at the net crossing
on the mean toss (top/back or side, the larger one of the starting serve) falls short of
``keep_spin`` times the starting value (same sign). A candidate illegal on the mean toss
scores :data:`ILLEGAL_ON_MEAN`. The result is the best candidate without spin deficit, or
the starting serve when none beats it: never worse than the start.

Every candidate is planned once on the mean toss (the toss commands are the same for
every recorded toss) and flown on each recorded toss, as :func:`studio.evaluate.evaluate_robust`
does: ~0.1 s a candidate with the 20 shipped tosses.

Resume: with ``run_dir`` every evaluation is appended to ``robustify.jsonl`` (flushed and
fsynced) next to ``robustify.json`` (settings). CMA-ES's candidates depend only on its
seed and on the values it was told, so a resumed search replays the log (asks, finds each
candidate logged, tells the logged value) and goes on exactly as the uninterrupted search.
"""

from __future__ import annotations

import json
import math
import os
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from studio.errors import DataFileError, InvalidInputError
from studio.serve import GENE_NAMES, GenomeBounds, HandServe, ServeParams

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
below it: at most 20 + a few reward points, with the shipped tosses)."""
MIN_SPIN = 20.0
"""Below this net spin [rad/s] the starting serve has no spin worth keeping: no constraint."""


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
    recorded toss (:class:`studio.evaluate.EvaluationContext` ``context``)."""
    from studio.evaluate import evaluate_motion, plan_motion

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
    """The spin constraint: ``sign * component >= floor`` at the net on the mean toss."""

    component: str
    """"topspin" or "sidespin" (the starting serve's dominant one), or "" for none."""
    sign: float
    """+1 or -1: the starting serve's direction of it."""
    floor: float
    """Least magnitude kept [rad/s]."""

    def deficit(self, score: RobustScore) -> float:
        """How far ``score`` falls short [rad/s] (inf without a net crossing)."""
        if not self.component:
            return 0.0
        value = score.net_topspin if self.component == "topspin" else score.net_sidespin
        if value is None:
            return math.inf
        return max(0.0, self.floor - self.sign * value)

    def describe(self) -> str:
        if not self.component:
            return "no spin to keep"
        name = {("topspin", 1.0): "topspin", ("topspin", -1.0): "backspin"}.get((self.component, self.sign), "sidespin")
        return f"{name} at the net >= {self.floor:.0f} rad/s"


def spin_keep(start: RobustScore, keep: float) -> SpinKeep:
    """The constraint for a starting serve: its dominant net spin component, ``keep`` of it."""
    top, side = start.net_topspin or 0.0, start.net_sidespin or 0.0
    component, value = ("topspin", top) if abs(top) >= abs(side) else ("sidespin", side)
    if abs(value) < MIN_SPIN or keep == 0.0:
        return SpinKeep("", 1.0, 0.0)
    return SpinKeep(component, math.copysign(1.0, value), keep * abs(value))


def objective(score: RobustScore, keep: SpinKeep) -> float:
    """The value CMA-ES minimizes (module docstring)."""
    if not score.mean_legal:
        return ILLEGAL_ON_MEAN
    deficit = keep.deficit(score)
    return -(score.legal + 0.1 * score.mean_reward) + (deficit / SPIN_PER_TOSS if math.isfinite(deficit) else ILLEGAL_ON_MEAN)


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


def _write_line(path: Path, doc: dict[str, Any]) -> None:
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(doc, allow_nan=False) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def _read_log(path: Path) -> list[dict[str, Any]]:
    """Logged evaluations; a torn last line (killed run) is cut off the file."""
    if not path.exists():
        return []
    raw = path.read_bytes()
    lines = raw.split(b"\n")
    out: list[dict[str, Any]] = []
    good = 0
    for k, line in enumerate(lines):
        if not line.strip():
            good += len(line) + (k < len(lines) - 1)
            continue
        try:
            if k == len(lines) - 1:
                raise ValueError("unterminated line")
            doc = json.loads(line)
            if not isinstance(doc, dict) or not isinstance(doc.get("genome"), list) or len(doc["genome"]) != len(GENE_NAMES):
                raise ValueError("not a robustify record")
            float(doc["objective"])
        except (ValueError, KeyError, TypeError) as exc:
            if k >= len(lines) - 2 and not any(x.strip() for x in lines[k + 1 :]):
                break  # torn tail
            raise DataFileError(path, f"line {k + 1}: {exc}") from None
        out.append(doc)
        good += len(line) + 1
    if good < len(raw):
        with open(path, "r+b") as fh:
            fh.truncate(good)
    return out


def robustify_serve(
    serve: HandServe,
    *,
    context: Any = None,
    task: str | None = None,
    keep_spin: float = 0.9,
    sigma: float = 0.03,
    evaluations: int = 600,
    population: int = 12,
    seed: int = 0,
    run_dir: str | Path | None = None,
    resume: bool = False,
    bounds: GenomeBounds | None = None,
    progress: Callable[[int, int, RobustScore], None] | None = None,
    stop: threading.Event | None = None,
    score: ScoreFn | None = None,
) -> RobustifyResult:
    """Search around ``serve`` for one that is legal on more recorded tosses (module docstring).

    Args:
        serve: the starting serve (its side's tosses are used; its limit scale is kept).
        context: :class:`studio.evaluate.EvaluationContext` (default: the shipped models).
        task: reward task of the mean-reward tie-break (default: the serve's, else
            topspin_velocity).
        keep_spin: fraction in [0, 1] of the starting serve's dominant net spin to keep.
        sigma: CMA-ES initial step on the normalized genome (0, 0.5].
        evaluations: candidates to score (CMA-ES asks ``population`` at a time).
        population: CMA-ES population (>= 4).
        seed: CMA-ES seed.
        run_dir: folder for ``robustify.json`` and ``robustify.jsonl`` (optional).
        resume: continue the search logged in ``run_dir`` (same settings required).
        bounds: genome bounds (default: :func:`studio.optimizer.bounds_for_toss` of the side).
        progress: called after each generation with (evaluations done, budget, best score).
        stop: when set, the search ends after the current generation.
        score: replaces :func:`robust_score` (tests).

    Raises:
        InvalidInputError: a setting out of range (named); DataFileError: a log that does
            not belong to this search.
    """
    import cma

    for name, value, ok in (
        ("keep_spin", keep_spin, 0.0 <= keep_spin <= 1.0),
        ("sigma", sigma, 0.0 < sigma <= 0.5),
        ("evaluations", evaluations, evaluations >= 1),
        ("population", population, population >= 4),
    ):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
            raise InvalidInputError(f"robustify: {name} out of range, got {value!r} (keep_spin in [0, 1], sigma in (0, 0.5], evaluations >= 1, population >= 4)")
    if resume and run_dir is None:
        raise InvalidInputError("robustify: resume needs run_dir")
    task = task or serve.task or "topspin_velocity"
    if score is None:
        if context is None:
            from studio.evaluate import EvaluationContext

            context = EvaluationContext.default()
        ctx = context

        def score(s: HandServe) -> RobustScore:
            return robust_score(s, ctx, task=task)

    if bounds is None:
        from studio.optimizer import bounds_for_toss

        if context is None:
            from studio.toss import load_default_toss_model

            bounds = bounds_for_toss(load_default_toss_model(serve.side))
        else:
            bounds = bounds_for_toss(context.toss_model(serve.side))

    meta = {
        "schema": ROBUST_SCHEMA, "serve": serve.to_json(), "task": task, "keep_spin": keep_spin, "sigma": sigma,
        "population": population, "seed": seed, "bounds": asdict(bounds),
    }  # fmt: skip
    log: list[dict[str, Any]] = []
    log_path: Path | None = None
    if run_dir is not None:
        folder = Path(run_dir)
        folder.mkdir(parents=True, exist_ok=True)
        log_path = folder / LOG_NAME
        meta_path = folder / META_NAME
        if resume and meta_path.exists():
            try:
                old = json.loads(meta_path.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise DataFileError(meta_path, f"not readable JSON ({exc})") from None
            for key, value in json.loads(json.dumps(meta)).items():
                if not isinstance(old, dict) or old.get(key) != value:
                    raise DataFileError(meta_path, f"field {key!r}: the logged search has {old.get(key) if isinstance(old, dict) else old!r}, this call {value!r}")
            log = _read_log(log_path)
        elif log_path.exists() and log_path.stat().st_size > 0:
            raise InvalidInputError(f"{log_path} already holds a search: pass resume=True or use another folder")
        meta_path.write_text(json.dumps(meta, indent=2), encoding="utf-8")

    start_score = score(serve)
    keep = spin_keep(start_score, keep_spin)
    low, high = bounds.lows_highs()
    z0 = np.clip(serve.params.normalize(bounds), 0.0, 1.0)
    # cma's seed 0 means "random": seed + 1 keeps seed 0 reproducible
    es = cma.CMAEvolutionStrategy(z0, sigma, {"popsize": population, "seed": seed + 1, "bounds": [0.0, 1.0], "verbose": -9})
    best_serve, best_score, best_obj = serve, start_score, objective(start_score, keep) if keep.deficit(start_score) == 0 else math.inf
    done = 0
    stopped = False

    def candidate(z: npt.NDArray[np.float64]) -> HandServe:
        return replace(serve, params=ServeParams.from_vector(low + z * (high - low)))

    while done < evaluations:
        if stop is not None and stop.is_set():
            stopped = True
            break
        Z = [np.clip(np.asarray(z, dtype=float), 0.0, 1.0) for z in es.ask()]
        values = []
        for z in Z:
            if done < len(log):  # replay
                rec = log[done]
                if not np.allclose(rec["genome"], z, rtol=0, atol=1e-9):
                    raise DataFileError(log_path, f"line {done + 1}: the logged candidate differs from the replayed one (not this search's log)")
                values.append(float(rec["objective"]))
                sc = RobustScore(**rec["score"])
            else:
                sc = score(candidate(z))
                values.append(objective(sc, keep))
                if log_path is not None:
                    _write_line(log_path, {"index": done, "genome": [float(v) for v in z], "objective": values[-1], "score": asdict(sc)})
            if keep.deficit(sc) == 0 and values[-1] < best_obj:
                best_serve, best_score, best_obj = candidate(z), sc, values[-1]
            done += 1
        es.tell([list(z) for z in Z], values)
        if progress is not None:
            progress(done, evaluations, best_score)

    improved = best_serve is not serve
    if improved:
        note = (
            f"Made robust by robustify (CMA-ES sigma {sigma}, {done} candidates, keeping {keep.describe()}): "
            f"legal on {best_score.legal}/{best_score.tosses} recorded tosses (was {start_score.legal}/{start_score.tosses})."
        )
        best_serve = replace(best_serve, notes=(serve.notes + " " + note).strip())
    return RobustifyResult(best_serve, start_score, best_score, keep, done, stopped, Path(run_dir) if run_dir is not None else None, improved)
