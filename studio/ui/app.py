"""The serve design studio: a viser app over the core modules.

Thin by design: the GUI callbacks only record the latest control values and hand them
to one :class:`~studio.ui.worker.LatestWorker`, which evaluates the serve with
:func:`studio.serve.evaluate.evaluate_serve` (plan, ball prediction, optional MuJoCo rollout,
ITTF checks, reward) and publishes the result; the scene is built by the pure
:func:`studio.ui.scene.scene_frame` and shown by :class:`~studio.ui.scene.StudioScene`.

:class:`StudioApp` composes the pieces and owns what ties them together (the controls'
change events, the worker, undo/redo and the pinned serve):

- :class:`~studio.ui.overlay.OverlayPanel`: numbers at a glance over the 3D view, camera
  presets (:mod:`studio.ui.camera`), undo/redo (:class:`~studio.ui.history.History`), A/B;
- :class:`~studio.ui.playback.PlaybackPanel`: play, scrub, slow motion, ball size;
- :class:`~studio.ui.controls.ServeForm`: the serve controls of the Serve tab;
- :class:`~studio.ui.files.FilesPanel`: serve files, library, the dashboard's open requests;
- :class:`~studio.ui.jobs.JobRunner`: the Optimize tab (HEBO runs, Make robust);
- :class:`~studio.ui.match_panel.MatchPanel`: the Match tab.

Every control is registered with one :class:`~studio.ui.checks.InputGuard` with its own
range or options, and :func:`studio.ui.wire.gate` puts those checks in front of viser's
message handlers: a value a control does not accept (NaN, 1e300, text for a number, an
unlisted option or file, 24 workers) is refused with a message naming the control and
what it accepts, and never reaches an evaluation or a job.

Run with ``serve-studio app`` (``./dev studio``). Listens on 127.0.0.1 by default.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from studio.errors import DataFileError, StudioError
from studio.serve.efforts import EffortReport, effort_report
from studio.serve.evaluate import Evaluation, EvaluationContext, evaluate_serve, report_markdown
from studio.serve.params import HandServe
from studio.ui import wire
from studio.ui.camera import (
    VIEW_NAMES,
    CameraView,
    apply_camera,
    default_view,
    set_initial_camera,
    view_named,
)
from studio.ui.checks import Choice, InputGuard, choices, shown
from studio.ui.controls import Controls, ServeForm, fallback_serve
from studio.ui.files import EXAMPLES_DIR, FilesPanel, inside, list_serves, load_serve_in, safe_name, serve_files
from studio.ui.history import History, Pin
from studio.ui.jobs import NEW_RUN, JobRunner
from studio.ui.match_panel import MatchPanel
from studio.ui.overlay import CLEAR, PIN, REDO, RESTORE, UNDO, OverlayPanel, serve_numbers
from studio.ui.playback import PlaybackPanel
from studio.ui.scene import SceneFrame, StudioScene, ghost_frame, scene_frame
from studio.ui.worker import LatestWorker, WorkResult

__all__ = ["EXAMPLES_DIR", "NEW_RUN", "Controls", "StudioApp", "inside", "list_serves", "run_app", "safe_name"]


class StudioApp:
    """The studio's GUI, wiring controls to the worker and the scene.

    Args:
        server: a running viser server.
        context: robot, tosses, planner and models shared by all evaluations.
        serves_dir: folder of hand-designed serves (read, and written by "save as seed").
        library_dir: serve library folder for "export".
        watch_open_requests: poll the library's ``open-request.json`` (the dashboard's
            "Open in studio") twice a second; otherwise call ``files.poll_open_request()``.
    """

    def __init__(
        self,
        server: Any,
        *,
        context: EvaluationContext,
        serves_dir: Path,
        library_dir: Path,
        watch_open_requests: bool = True,
    ) -> None:
        self.server = server
        self.context = context
        self.serves_dir = serves_dir
        self.library_dir = library_dir
        self.runs_dir = serves_dir.parent / "runs"
        self.scene = StudioScene(server)
        self.last: Evaluation | None = None
        self.last_efforts: EffortReport | None = None  # of ``last``
        self.last_controls: Controls | None = None  # what ``last`` evaluated
        self.history: History[Controls] = History()
        self.pin: Pin | None = None
        self.view = "default"
        """The camera preset last chosen."""
        self._lock = threading.RLock()  # scene and ``last*``; re-entrant: GUI setters call back synchronously
        self._suspend = False
        self.message_md: Any = None
        self.messages: list[str] = []
        """The messages shown under the tabs, newest last (the latest 200)."""
        self._early_messages: list[str] = []
        self.guard = InputGuard(self.message)
        self.worker: LatestWorker[Controls, Evaluation] = LatestWorker(
            self._compute, self._publish, name="studio-evaluator"
        )
        self._build_gui()
        wire.gate(server, self.guard, self.message)
        self.load(self._first_serve())
        set_initial_camera(server, default_view())
        self.playback.start_loop()
        self.files.poll_open_request(act=False)  # a request older than this studio is not acted on
        if watch_open_requests:
            self.files.watch_open_requests()

    def _first_serve(self) -> HandServe:
        """The first readable serve of the serves folder (else of the examples, else a plain
        push); unreadable files are skipped, and named in the message line."""
        problems: list[str] = []
        for folder in (self.serves_dir, EXAMPLES_DIR):
            listed, unlisted = serve_files(folder)
            problems += unlisted
            for path in listed.values():
                try:
                    serve = load_serve_in(folder, path)
                except (StudioError, OSError) as err:
                    problems.append(str(err) if isinstance(err, DataFileError) else f"{path}: {err}")
                    continue
                if problems:
                    self.message(
                        "**Skipped unreadable serve files:**  \n"
                        + "  \n".join(problems[:10])
                        + (f"  \n... and {len(problems) - 10} more" if len(problems) > 10 else "")
                    )
                return serve
        if problems:
            self.message("**Skipped unreadable serve files:**  \n" + "  \n".join(problems[:10]))
        return fallback_serve()

    # -- GUI construction -----------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        self.overlay = OverlayPanel(gui)
        self.files = FilesPanel(self)
        self.playback = PlaybackPanel(gui, self.scene, self._lock, self.guard)
        tabs = gui.add_tab_group()
        with tabs.add_tab("Serve"):
            self.files.add_picker(gui)
            self.form = ServeForm(gui, self.guard)
            self.files.add_folder(gui)
        with tabs.add_tab("Checks"):
            self.status_md = gui.add_markdown("_evaluating..._")
            self.checks_md = gui.add_markdown("")
        with tabs.add_tab("Metrics"):
            self.metrics_md = gui.add_markdown("")
        with tabs.add_tab("Optimize"):
            self.jobs = JobRunner(self, gui, self.runs_dir)
        with tabs.add_tab("Match"):
            self.match = MatchPanel(
                self, gui, show_entry=self.files.show_library_entry, play=self.playback.play_from_start
            )
        self.message_md = gui.add_markdown("\n\n".join(self._early_messages))
        self._wire()
        self.files.refresh_serve_files()
        self.files.refresh_library()
        self.jobs.refresh_runs()

    def _wire(self) -> None:
        """Connect the controls and the overlay's buttons to the app."""
        guard = self.guard
        for handle in self.form.inputs:

            def changed(_event: Any, key: str = handle.label) -> None:
                self._changed(key=key)

            guard.on_update(handle, changed)
        guard.on_update(self.form.side, lambda _event: self._refresh_toss_options())
        guard.on_update(self.form.side, lambda _event: self.jobs.refresh_runs())
        guard.on_update(self.form.task, lambda _event: self.jobs.refresh_runs())
        ov = self.overlay
        guard.add(ov.view, Choice("View", choices(*VIEW_NAMES)))
        guard.add(ov.history, Choice("Edits", choices(UNDO, REDO)))
        guard.add(ov.ab, Choice("A/B", choices(PIN, RESTORE, CLEAR)))
        guard.on_update(ov.view, lambda event: self.set_view(event.target.value, event.client))
        guard.on_update(ov.history, lambda event: self.undo() if event.target.value == UNDO else self.redo())
        ab = {PIN: self.pin_current, RESTORE: self.restore_pin, CLEAR: self.clear_pin}
        guard.on_update(ov.ab, lambda event: ab[event.target.value]())

    # -- what the panels may ask (studio.ui.host.StudioHost) ---------------------------

    def controls(self) -> Controls:
        """Read the controls into a validated snapshot (InvalidInputError names the control)."""
        return self.form.read()

    def side_and_task(self) -> tuple[str, str]:
        """The toss side and reward task chosen in the controls."""
        return str(self.form.side.value), str(self.form.task.value)

    def message(self, text: str) -> None:
        """Show a Markdown message under the tabs (text that is not valid Unicode escaped)."""
        text = shown(text)
        with self._lock:
            self.messages.append(text)
            del self.messages[:-200]
        if self.message_md is None:  # before the GUI is built
            self._early_messages.append(text)
            return
        self.message_md.content = text

    def latest(self) -> tuple[Evaluation | None, EffortReport | None]:
        """The newest published evaluation and its joint-effort report."""
        with self._lock:
            return self.last, self.last_efforts

    @contextmanager
    def _quiet(self) -> Iterator[None]:
        """Set controls without their change callbacks re-evaluating."""
        self._suspend = True
        try:
            yield
        finally:
            self._suspend = False

    def load(self, serve: HandServe) -> None:
        """Put a serve into the controls and evaluate it (one undo step)."""
        with self._quiet():
            self.form.write(serve)
            self._refresh_toss_options()
        self._changed()

    def _refresh_toss_options(self) -> None:
        self.form.set_toss_options(self.context.toss_model(self.form.side.value).n_tosses)

    # -- changes, undo/redo -------------------------------------------------------------

    def _changed(self, key: str | None = None) -> None:
        """A control changed (``key``: its label; None: a whole serve was loaded)."""
        if self._suspend:
            return
        try:
            controls = self.controls()
        except StudioError as err:
            self.message(f"**Input rejected:** {err}")
            return
        self._submit(controls)
        self.history.record(controls, key=key)
        self._show_history()

    def _submit(self, controls: Controls) -> None:
        self.worker.submit(controls)
        self.status_md.content = "_evaluating..._"
        self.overlay.status.content = "_re-planning ..._"

    def apply(self, controls: Controls, *, record: bool) -> None:
        """Put a whole snapshot into the controls and evaluate it (``record``: as a new undo step)."""
        with self._quiet():
            self.form.write_all(controls, self.context.toss_model(controls.serve.side).n_tosses)
        self._submit(controls)
        if record:
            self.history.record(controls)
        self._show_history()

    def undo(self) -> bool:
        """Put the previous control values back; False if there is none."""
        state = self.history.undo()
        if state is None:
            self.overlay.note.content = "_nothing to undo_"
            return False
        self.apply(state, record=False)
        return True

    def redo(self) -> bool:
        """Put undone control values back; False if there is none."""
        state = self.history.redo()
        if state is None:
            self.overlay.note.content = "_nothing to redo_"
            return False
        self.apply(state, record=False)
        return True

    def _show_history(self) -> None:
        undo, redo = self.history.counts()
        pinned = (
            f"pinned A: `{self.pin.controls.serve.name}` (dashed path)" if self.pin is not None else "nothing pinned"
        )
        self.overlay.note.content = f"{undo} undo / {redo} redo steps · {pinned}"

    # -- A/B ----------------------------------------------------------------------------

    def pin_current(self) -> bool:
        """Pin the newest evaluated serve as "A": its path drawn as a ghost, its numbers
        beside the current ones. False if nothing is evaluated yet."""
        with self._lock:
            if self.last is None or self.last_controls is None:
                self.overlay.note.content = "_nothing evaluated yet to pin_"
                return False
            self.pin = Pin(self.last_controls, self.last, self.last_efforts, self.scene.frame)
            self.scene.show_ghost(ghost_frame(self.pin.frame))
            self._show_numbers()
        self._show_history()
        return True

    def restore_pin(self) -> bool:
        """Put the pinned serve back into the controls (one undo step); False if none."""
        if self.pin is None:
            self.overlay.note.content = "_nothing pinned: press *Pin as A* first_"
            return False
        self.apply(self.pin.controls, record=True)
        return True

    def clear_pin(self) -> None:
        """Forget the pinned serve and remove its ghost."""
        with self._lock:
            self.pin = None
            self.scene.show_ghost(None)
            self._show_numbers()
        self._show_history()

    # -- camera -------------------------------------------------------------------------

    def camera_view(self, name: str) -> CameraView:
        """The preset ``name`` (``default`` frames the current ball path too)."""
        with self._lock:
            frame = self.scene.frame
        path = next((s.points for s in frame.segments if s.name == "flight"), None)
        return view_named(name, path)

    def set_view(self, name: str, client: Any = None) -> None:
        """Move the camera of ``client`` (None: every connected browser) to preset ``name``."""
        view = self.camera_view(name)
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            apply_camera(c, view)
        self.view = name

    # -- worker -----------------------------------------------------------------------

    def _compute(self, controls: Controls) -> Evaluation:
        return evaluate_serve(
            controls.serve, self.context, task=controls.task, toss_sample=controls.toss_sample, mujoco=controls.mujoco
        )

    def _publish(self, result: WorkResult[Controls, Evaluation]) -> None:
        if result.error is not None or result.value is None:
            failed = f"**Evaluation failed** ({type(result.error).__name__}): {result.error}"
            self.status_md.content = failed
            self.overlay.status.content = failed
            return
        evaluation = result.value
        frame = scene_frame(evaluation, self.context)
        efforts = effort_report(evaluation.motion, self.context.robot)  # the worker's thread, as the frame
        status, checks, metrics = report_markdown(evaluation)
        first = self.last is None
        with self._lock:
            self.last, self.last_efforts, self.last_controls = evaluation, efforts, result.inputs
            self.scene.show(frame)
            self.status_md.content = status + f"\n\n_evaluated in {1000 * result.seconds:.0f} ms_"
            self.checks_md.content = checks + (
                f"\n\n{efforts.headline()} (table in Metrics)" if efforts is not None else ""
            )
            self.metrics_md.content = metrics + (f"\n\n{efforts.markdown()}" if efforts is not None else "")
            self._show_numbers(result.seconds)
            self.playback.new_frame(frame)
        if first:
            set_initial_camera(self.server, self._default_view(frame))

    def _show_numbers(self, seconds: float | None = None) -> None:
        """The overlay's table for ``last`` (and the pin), with the lock held."""
        if self.last is None:
            return
        toss = (
            "mean toss"
            if self.last_controls is None or self.last_controls.toss_sample is None
            else f"recorded toss {self.last_controls.toss_sample + 1}"
        )
        timing = f", evaluated in {1000 * seconds:.0f} ms" if seconds is not None else ""
        pinned = serve_numbers(self.pin.evaluation, self.pin.efforts) if self.pin is not None else None
        self.overlay.show(
            serve_numbers(self.last, self.last_efforts), pinned,
            status=f"`{self.last.serve.name}` on the {toss}{timing}",
            efforts_line=self.last_efforts.headline() if self.last_efforts is not None else "",
        )  # fmt: skip

    @staticmethod
    def _default_view(frame: SceneFrame) -> CameraView:
        path = next((s.points for s in frame.segments if s.name == "flight"), None)
        return default_view(path)


def run_app(
    *, host: str = "127.0.0.1", port: int = 8080, serves_dir: str | None = None, library_dir: str | None = None
) -> None:
    """Start the studio and serve until interrupted."""
    import viser

    print("serve-studio: loading robot, tosses and planner ...", flush=True)
    context = EvaluationContext.default()
    serves = Path(serves_dir) if serves_dir else Path.cwd() / "serves"
    library = Path(library_dir) if library_dir else Path.cwd() / "serve-library"
    from studio.ui.origin_guard import install as refuse_foreign_origins

    refuse_foreign_origins()  # before the server starts: no foreign page may drive the studio
    server = viser.ViserServer(host=host, port=port)
    StudioApp(server, context=context, serves_dir=serves, library_dir=library)
    print(f"serve-studio: open http://{host}:{port} (Ctrl+C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
