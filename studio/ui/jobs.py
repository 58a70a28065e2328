"""The studio's long jobs: HEBO optimization from seeds and "Make robust", one at a time.

:class:`JobRunner` builds the Optimize tab and runs each job in a daemon thread, with a
progress bar, a convergence plot (best reward so far against evaluations), a Stop button
and a Markdown report; the job's result lands in the controls through the host's
``load``. Run folders go to ``<serves_dir>/../runs`` (``runs_dir``).

Each number is checked against its own range on every change and again when a job
starts (:data:`LIMITS`; :mod:`studio.ui.checks`): a value outside it (24 workers, 10^12
tosses, NaN iterations) is refused with a message and starts nothing.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from studio.errors import InvalidInputError, StudioError
from studio.optimize.workflow import chosen_serve, new_run_dir
from studio.serve.evaluate import EvaluationContext
from studio.serve.params import HandServe, ServeParams
from studio.ui.checks import Choice, Flag, InputRefused, Number, Press, shown
from studio.ui.controls import Controls
from studio.ui.files import EXAMPLES_DIR, list_serves, load_serve_in
from studio.ui.host import StudioHost

if TYPE_CHECKING:
    from studio.optimize.optimizer import OptimizationResult, RunSummary
    from studio.toss.primitive import TossSide

NEW_RUN = "(new run)"
"""The Optimize tab's "run" choice that starts a new run."""

LIMITS: dict[str, tuple[int, int, int]] = {
    "iterations": (1, 100, 10),
    "population": (2, 50, 20),
    "workers": (1, 16, 2),
    "tosses per evaluation": (1, 20, 5),
    "seed": (0, 2**31 - 1, 0),
    "robust candidates": (12, 10000, 600),
}
"""(lowest, highest, initial) of each number of the Optimize tab: at most 16 worker
processes, 20 tosses per evaluation, 100 iterations, 10,000 robustness candidates."""


class JobRunner:
    """The Optimize tab and its background jobs.

    Args:
        host: the app (controls, load, context).
        gui: the server's ``gui`` API; the tab's handles are added to its current container.
        runs_dir: folder of the HEBO run folders.
    """

    def __init__(self, host: StudioHost, gui: Any, runs_dir: Path) -> None:
        self.host = host
        self.runs_dir = runs_dir
        self.stop_event = threading.Event()
        self._busy = False
        self._busy_lock = threading.Lock()
        self._runs: dict[str, RunSummary] = {}
        self._robust_context: EvaluationContext | None = None  # robustify's own (built on first use)
        self._build(gui)

    def _build(self, gui: Any) -> None:
        gui.add_markdown(
            "HEBO over the genome for the current task and toss side, seeded with the current "
            "serve and the saved seeds of that side. Every evaluation is logged to the run folder."
        )

        def number(label: str, step: int = 1) -> Any:
            lo, hi, initial = LIMITS[label]
            handle = gui.add_number(label, initial_value=initial, min=lo, max=hi, step=step)
            return self.host.guard.add(handle, Number(label, lo, hi, integer=True))

        self.opt_iterations = number("iterations")
        self.opt_population = number("population")
        self.opt_workers = number("workers")
        self.opt_tosses = number("tosses per evaluation")
        self.opt_seed = number("seed")
        self.opt_run = gui.add_dropdown(
            "run",
            options=[NEW_RUN],
            initial_value=NEW_RUN,
            hint="a new run, or an earlier run of this side and task to continue",
        )
        self.opt_follow = gui.add_checkbox("show best so far", initial_value=True)
        self.opt_start = gui.add_button("Optimize from seeds")
        self.rob_evaluations = number("robust candidates", step=12)
        self.rob_start = gui.add_button(
            "Make robust",
            hint="local search around the current serve for one legal on more recorded tosses, keeping 90 % of its spin at the net",
        )
        self.opt_stop = gui.add_button("Stop", disabled=True)
        guard = self.host.guard
        guard.add(self.opt_run, Choice("run", lambda: [NEW_RUN, *self._runs]))
        guard.add(self.opt_follow, Flag("show best so far"))
        for button in (self.opt_start, self.rob_start, self.opt_stop):
            guard.add(button, Press(button.label))
        self.opt_progress = guard.add(
            gui.add_progress_bar(0.0, animated=False), Number("progress", 0.0, 100.0, "%", client_settable=False)
        )
        self.opt_md = gui.add_markdown("")
        self.opt_plot = gui.add_uplot(
            data=(np.zeros(1), np.zeros(1)),
            series=({"label": "evaluations"}, {"label": "best reward", "stroke": "green", "width": 2}),
            title="convergence",
            scales={"x": {"time": False}},  # evaluations, not a date axis
            aspect=1.6,
        )
        guard.on_update(self.opt_start, lambda _event: self.start_optimization())
        guard.on_update(self.rob_start, lambda _event: self.start_robustify())
        guard.on_update(self.opt_stop, lambda _event: self.stop_event.set())

    @property
    def busy(self) -> bool:
        """Whether a job runs."""
        return self._busy

    @property
    def runs(self) -> dict[str, RunSummary]:
        """The listed runs by their "run" dropdown label."""
        return dict(self._runs)

    # -- seeds and runs ---------------------------------------------------------------

    def seeds_for(self, side: str) -> list[HandServe]:
        """The current serve plus every saved seed and example of ``side`` (valid files only)."""
        seeds = [self.host.controls().serve]
        for folder in (self.host.serves_dir, EXAMPLES_DIR):
            for path in list_serves(folder).values():
                try:
                    serve = load_serve_in(folder, path)
                except (StudioError, OSError):
                    continue
                if serve.side == side and all(serve.params != s.params for s in seeds):
                    seeds.append(serve)
        return seeds

    def refresh_runs(self) -> None:
        """List the runs of the controls' side and task in ``runs_dir`` in the "run"
        dropdown (unreadable run folders are reported in the Optimize tab)."""
        from studio.optimize.optimizer import list_runs

        side, task = self.host.side_and_task()
        runs, problems = list_runs(self.runs_dir, side=side, task=task)
        chosen = self._runs[self.opt_run.value].run_dir.name if self.opt_run.value in self._runs else None
        listed = {shown(r.label()): r for r in runs}
        self._runs = {**self._runs, **listed}  # old and new entries valid while the list changes
        self.opt_run.options = [NEW_RUN, *listed]
        # the labels carry the progress: the choice follows its folder
        self.opt_run.value = next((k for k, r in listed.items() if r.run_dir.name == chosen), NEW_RUN)
        self._runs = listed
        if problems and not self._busy:
            self.opt_md.content = shown("**Unreadable run folders (not listed):**  \n" + "  \n".join(problems))

    # -- busy flag ----------------------------------------------------------------------

    def _claim(self) -> bool:
        """Mark the runner busy with one job; False if one runs already."""
        with self._busy_lock:
            if self._busy:
                return False
            self._set_busy(True)
            return True

    def _set_busy(self, busy: bool) -> None:
        self._busy = busy
        if busy:
            self.stop_event.clear()
        self.opt_start.disabled = busy
        self.rob_start.disabled = busy
        self.opt_stop.disabled = not busy

    # -- optimization -------------------------------------------------------------------

    def start_optimization(self) -> None:
        """Start HEBO from the seeds (or continue the chosen run) in the background."""
        guard = self.host.guard
        try:
            controls = self.host.controls()
            iterations, population, workers, tosses, seed = (
                int(guard.check(h))
                for h in (self.opt_iterations, self.opt_population, self.opt_workers, self.opt_tosses, self.opt_seed)
            )
            choice = guard.check(self.opt_run)
            run = None if choice == NEW_RUN else self._runs.get(choice)
            if choice != NEW_RUN and run is None:
                raise InvalidInputError(f"run {shown(choice)!r} is no longer listed")
        except StudioError as err:
            self._cannot_start(err)
            return
        if not self._claim():
            return
        args = (controls, iterations, population, workers, tosses, seed, run)
        threading.Thread(target=self._run_optimization, args=args, name="studio-optimizer", daemon=True).start()

    def _cannot_start(self, err: StudioError) -> None:
        """Say in the tab and in the message line why a job did not start."""
        text = str(err).removeprefix("**Refused:** ") if isinstance(err, InputRefused) else shown(str(err))
        self.opt_md.content = f"**Cannot start:** {text}"
        self.host.message(f"**Cannot start:** {text}")

    def _progress(
        self, run_dir: Path, side: TossSide, task: str, scale: Any
    ) -> Callable[[int, int, float, ServeParams | None], None]:
        """The optimizer's progress callback: bar, plot, text, and the best serve so far
        into the controls when "show best so far" is ticked."""
        xs: list[float] = []
        ys: list[float] = []
        last_best: list[ServeParams | None] = [None]

        def progress(done: int, total: int, best: float, params: ServeParams | None) -> None:
            self.opt_progress.value = min(100.0, max(0.0, 100.0 * done / max(total, 1)))
            xs.append(float(done))
            ys.append(float(best))
            self.opt_plot.data = (np.array(xs), np.array(ys))
            self.opt_md.content = f"{done} / {total} evaluations, best reward {best:+.3f}  \nrun folder `{run_dir}`"
            if params is not None and params != last_best[0] and self.opt_follow.value:
                last_best[0] = params
                self.host.load(
                    HandServe(name=f"{task} best so far", side=side, params=params, task=task, limit_scale=scale)
                )

        return progress

    def _run_optimization(
        self,
        controls: Controls,
        iterations: int,
        population: int,
        workers: int,
        tosses: int,
        seed: int,
        run: RunSummary | None = None,
    ) -> None:
        """A new HEBO run from the seeds, or with ``run`` the continuation of that run (its own
        seeds, seed, population, tosses and limits; at least its own iterations)."""
        from studio.optimize.optimizer import OptimizeOptions, optimize_serve

        side, task = controls.serve.side, controls.task
        run_dir = new_run_dir(self.runs_dir, side, task)
        scale = controls.serve.limit_scale
        if run is not None:
            side, task, run_dir, population, tosses, seed, scale = (
                run.side,
                run.task,
                run.run_dir,
                run.population,
                run.tosses,
                run.seed,
                run.limit_scale,
            )
            iterations = max(iterations, run.iterations)
        try:
            seeds = [] if run is not None else self.seeds_for(side)  # a resumed run takes its own from run.json
            self.opt_md.content = (
                f"resuming `{run_dir.name}` ({run.evaluations} evaluations logged) ..."
                if run is not None
                else f"evaluating {len(seeds)} seed(s) ..."
            )
            options = OptimizeOptions(
                side=side,
                task=task,
                iterations=iterations,
                population=population,
                workers=workers,
                tosses=tosses,
                seed=seed,
                limit_scale=scale,
            )
            progress = self._progress(run_dir, side, task, scale)
            result = optimize_serve(
                options, run_dir=run_dir, seeds=seeds, resume=run is not None, stop=self.stop_event, progress=progress
            )
            self._report_optimization(result, run_dir, task, seed)
        except Exception as err:  # noqa: BLE001 - shown in the panel, the studio keeps running
            self.opt_md.content = (
                f"**Optimization failed:** {type(err).__name__}: {err}  \n(evaluations so far are kept in `{run_dir}`)"
            )
        finally:
            self.refresh_runs()  # before the busy flag drops: unreadable folders do not hide the result
            self._set_busy(False)

    def _report_optimization(self, result: OptimizationResult, run_dir: Path, task: str, seed: int) -> None:
        """Load the chosen serve and say how it did."""
        chosen = chosen_serve(result, name=f"{task} optimized", notes=f"HEBO run {run_dir.name}, seed {seed}")
        if chosen is None or result.summary is None:
            self.opt_md.content = "**Nothing evaluated.**"
            return
        self.host.load(chosen)
        s = result.summary
        self.opt_md.content = (
            f"**{'Stopped' if result.stopped else 'Done'}:** {result.evaluations} evaluations in {result.timings.get('total', 0):.0f} s. "
            f"Chosen serve: mean reward {s.mean_reward:+.3f} over {len(s.rewards)} fresh tosses, legal on {100 * s.legal_fraction:.0f} %. "
            f"It is now in the controls: export it to the library with *Export to library*.  \nrun folder `{run_dir}`"
        )

    # -- robustify ----------------------------------------------------------------------

    def start_robustify(self) -> None:
        """Run :func:`studio.optimize.robust.robustify_serve` on the current serve in the background
        (progress and Stop as an optimization); the result lands in the controls."""
        try:
            controls = self.host.controls()
            evaluations = int(self.host.guard.check(self.rob_evaluations))
        except StudioError as err:
            self._cannot_start(err)
            return
        if not self._claim():
            return
        threading.Thread(
            target=self._run_robustify, args=(controls, evaluations), name="studio-robustify", daemon=True
        ).start()

    def _run_robustify(self, controls: Controls, evaluations: int) -> None:
        from studio.optimize.robust import RobustifyOptions, RobustScore, robustify_serve

        start = time.perf_counter()

        def progress(done: int, total: int, best: RobustScore) -> None:
            self.opt_progress.value = min(100.0, max(0.0, 100.0 * done / max(total, 1)))
            self.opt_md.content = f"robustify: {done} / {total} candidates, best legal on {best.legal}/{best.tosses} recorded tosses ({time.perf_counter() - start:.0f} s)"

        try:
            if self._robust_context is None:  # the live evaluation's context is not shared between threads
                self.opt_md.content = "robustify: loading models ..."
                self._robust_context = EvaluationContext.default()
            res = robustify_serve(
                controls.serve,
                RobustifyOptions(task=controls.task, evaluations=evaluations),
                context=self._robust_context,
                progress=progress,
                stop=self.stop_event,
            )
            if res.improved:
                self.host.load(replace(res.serve, name=f"{controls.serve.name} robust"))
            self.opt_md.content = (
                f"**{res.summary()}**"
                + (" The serve is now in the controls." if res.improved else "")
                + f" ({time.perf_counter() - start:.0f} s)"
            )
        except Exception as err:  # noqa: BLE001 - shown in the panel, the studio keeps running
            self.opt_md.content = f"**Robustify failed:** {type(err).__name__}: {err}"
        finally:
            self._set_busy(False)
