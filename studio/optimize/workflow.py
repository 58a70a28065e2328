"""After an optimization: name its run folder, choose its serve, make it robust, export it.

The steps the command line (``serve-studio optimize``, ``evaluate --export``), the studio
(Optimize tab, *Export to library*) and training (:mod:`studio.optimize.training`) share:

- :func:`new_run_dir`: a new run folder's name, ``<YYYYmmdd-HHMMSS>-<side>-<task>``;
- :func:`chosen_serve`: the run's chosen serve (:attr:`OptimizationResult.best`) named
  for its user;
- :func:`make_robust`: the local robustness search on it, logged in the run folder
  (:func:`studio.optimize.robust.robustify_chosen`), when asked for;
- :func:`hebo_provenance` and :func:`provenance_run`: a library entry's link to its run
  folder, written at export and read back by the dashboard;
- :func:`export_evaluation`: an evaluated plan into a serve library, with the side's
  preparation phase and the effort limits raised on purpose, if any.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from studio.library.store import LibraryEntry, ServeLibrary
    from studio.optimize.optimizer import OptimizationResult
    from studio.serve.evaluate import Evaluation, EvaluationContext
    from studio.serve.params import HandServe

__all__ = [
    "RUN_TIME_FORMAT",
    "new_run_dir",
    "chosen_serve",
    "make_robust",
    "hebo_provenance",
    "provenance_run",
    "export_evaluation",
]

RUN_TIME_FORMAT = "%Y%m%d-%H%M%S"
"""Local start time at the head of a new run folder's name (:func:`time.strftime`)."""


def new_run_dir(runs_root: str | Path, side: str, task: str) -> Path:
    """A new run folder in ``runs_root``: ``<YYYYmmdd-HHMMSS>-<side>-<task>``, started now
    (local time; not created)."""
    return Path(runs_root) / f"{time.strftime(RUN_TIME_FORMAT)}-{side}-{task}"


def chosen_serve(result: OptimizationResult, *, name: str, notes: str | None = None) -> HandServe | None:
    """The run's chosen serve named ``name`` (and annotated ``notes``; ``None``: the
    optimizer's note), or ``None`` when nothing was evaluated."""
    if result.best is None:
        return None
    if notes is None:
        return replace(result.best, name=name)
    return replace(result.best, name=name, notes=notes)


def make_robust(
    serve: HandServe,
    run_dir: str | Path,
    *,
    evaluations: int,
    task: str,
    context: Any = None,
    say: Callable[[str], None] | None = None,
) -> HandServe:
    """``serve`` after ``evaluations`` candidates of the local robustness search around it
    (:func:`studio.optimize.robust.robustify_chosen`: logged in ``run_dir/robustify/`` and
    resumed from there); ``serve`` itself when ``evaluations`` is 0. ``say`` gets a line
    before the search and its summary after it."""
    if not evaluations:
        return serve
    from studio.optimize.robust import robustify_chosen

    if say is not None:
        say(f"robustify: {evaluations} candidates around the chosen serve ...")
    rob = robustify_chosen(serve, run_dir, evaluations=evaluations, task=task, context=context)
    if say is not None:
        say(rob.summary())
    return rob.serve


def hebo_provenance(run_dir: str | Path, seed: int) -> dict[str, Any]:
    """The provenance of a serve chosen by a HEBO run: its run folder (as given) and seed
    (:func:`provenance_run` reads it back)."""
    return {"kind": "hebo", "run": str(run_dir), "seed": seed}


def provenance_run(entry_data: Mapping[str, Any]) -> str | None:
    """The run folder a library entry's provenance names (:func:`hebo_provenance`), as
    written; ``None`` for a serve not from a HEBO run or a malformed provenance."""
    prov = entry_data.get("provenance")
    run = prov.get("run") if isinstance(prov, dict) and prov.get("kind") == "hebo" else None
    return run if isinstance(run, str) and run else None


def export_evaluation(
    library: ServeLibrary | str | Path,
    evaluation: Evaluation,
    *,
    context: EvaluationContext,
    task: str,
    provenance: dict[str, Any],
    effort_limits: Mapping[str, float] | None = None,
) -> LibraryEntry:
    """Add an evaluated plan to ``library`` (a :class:`~studio.library.store.ServeLibrary`
    or its folder) with the preparation phase of its toss side from ``context``.

    ``effort_limits``: joint limits raised on purpose (recorded in the entry); a plan beyond
    the robot's limits otherwise raises :class:`~studio.serve.efforts.EffortLimitError`
    (nothing written). Other errors as :meth:`ServeLibrary.add`.
    """
    from studio.library.store import ServeLibrary

    lib = library if isinstance(library, ServeLibrary) else ServeLibrary(library)
    return lib.add(
        evaluation,
        provenance=provenance,
        task=task,
        preparation=context.preparation(evaluation.serve.side),
        effort_limits=effort_limits,
    )
