"""The serve design studio: a viser app over the core modules.

Thin by design: the GUI callbacks only record the latest control values and hand them
to one :class:`~studio.ui.worker.LatestWorker`, which evaluates the serve with
:func:`studio.serve.evaluate.evaluate_serve` (plan, ball prediction, optional MuJoCo rollout,
ITTF checks, reward) and publishes the result; the scene is built by the pure
:func:`studio.ui.scene.scene_frame` and shown by :class:`~studio.ui.scene.StudioScene`.

Run with ``serve-studio app`` (``./dev studio``). Listens on 127.0.0.1 by default.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from studio.paths import example_serves_dir
from studio.errors import InvalidInputError, StudioError
from studio.serve.evaluate import EffortReport, Evaluation, EvaluationContext, effort_report, evaluate_serve, report_markdown
from studio.serve.reward import TASKS
from studio.ui.scene import StudioScene, scene_frame
from studio.serve.params import LIMIT_SCALE_RANGE, GenomeBounds, HandServe, LimitScale, ServeParams, load_serve, save_serve, serve_from_json
from studio.ui.worker import LatestWorker, WorkResult

if TYPE_CHECKING:
    from studio.optimize.optimizer import RunSummary

NEW_RUN = "(new run)"
"""The Optimize tab's "run" choice that starts a new run."""

EXAMPLES_DIR = example_serves_dir()


@dataclass(frozen=True, slots=True)
class Controls:
    """A snapshot of the studio's controls: what the worker evaluates."""

    serve: HandServe
    """Serve being edited (side and parameters)."""
    task: str
    """Reward task preset."""
    toss_sample: int | None
    """Recorded toss index, or None for the mean toss path."""
    mujoco: bool
    """Also roll the serve out in MuJoCo."""


def safe_name(name: str) -> str:
    """A file-name-safe version of a serve name (letters, digits, '-', '_')."""
    cleaned = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name.strip())[:64].strip("_")
    if not cleaned:
        raise InvalidInputError("serve name must contain at least one letter or digit")
    return cleaned


def list_serves(folder: Path) -> dict[str, Path]:
    """Serve JSON files in ``folder`` by file stem (sorted)."""
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.glob("*.json"))}


def inside(folder: Path, path: Path) -> bool:
    """Whether ``path`` resolves to a location inside ``folder``."""
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


class StudioApp:
    """The studio's GUI, wiring controls to the worker and the scene.

    Args:
        server: a running viser server.
        context: robot, tosses, planner and models shared by all evaluations.
        serves_dir: folder of hand-designed serves (read, and written by "save as seed").
        library_dir: serve library folder for "export".
        watch_open_requests: poll the library's ``open-request.json`` (the dashboard's
            "Open in studio") twice a second; otherwise call :meth:`poll_open_request`.
    """

    def __init__(self, server: Any, *, context: EvaluationContext, serves_dir: Path, library_dir: Path, watch_open_requests: bool = True) -> None:
        self.server = server
        self.context = context
        self.serves_dir = serves_dir
        self.library_dir = library_dir
        self.scene = StudioScene(server)
        self.last: Evaluation | None = None
        self.last_efforts: EffortReport | None = None  # of ``last``
        self._lock = threading.Lock()
        self._suspend = False
        self._playing = False
        self._bounds = GenomeBounds()
        self._stop_event = threading.Event()
        self._match_serve: str | None = None  # library id of the robot's current match serve
        self._robust_context: EvaluationContext | None = None  # robustify's own (built on first use)
        self._busy_lock = threading.Lock()
        self._runs: dict[str, RunSummary] = {}
        self._optimizing = False
        self.runs_dir = serves_dir.parent / "runs"
        self.worker: LatestWorker[Controls, Evaluation] = LatestWorker(self._compute, self._publish, name="studio-evaluator")
        self._build_gui()
        serves = list_serves(serves_dir) or list_serves(EXAMPLES_DIR)
        first = next(iter(serves.values()), None)
        initial = load_serve(first) if first is not None else self._fallback_serve()
        self.load(initial)
        server.initial_camera.position = (-3.9, -2.4, 1.3)
        server.initial_camera.look_at = (-0.8, 0.0, 0.0)
        threading.Thread(target=self._playback_loop, name="studio-playback", daemon=True).start()
        self._open_nonce: str | None = None
        self._open_lock = threading.Lock()
        self.poll_open_request(act=False)  # a request older than this studio is not acted on
        if watch_open_requests:
            threading.Thread(target=self._open_request_loop, name="studio-open-requests", daemon=True).start()

    # -- GUI construction -----------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        tabs = gui.add_tab_group()
        with tabs.add_tab("Serve"):
            self.serve_file = gui.add_dropdown("Serve file", options=["(current)"], initial_value="(current)")
            self.name = gui.add_text("Name", initial_value="my serve")
            self.side = gui.add_dropdown("Toss side", options=["right", "left"], initial_value="right")
            self.toss = gui.add_dropdown("Toss", options=["mean path"], initial_value="mean path")
            self.task = gui.add_dropdown("Task", options=list(TASKS), initial_value="topspin_velocity")
            b = self._bounds
            with gui.add_folder("Contact"):
                self.tau = gui.add_slider("tau [s]", min=b.tau[0], max=b.tau[1], step=0.005, initial_value=0.8)
                self.t_return = gui.add_slider("return [s]", min=b.t_return[0], max=b.t_return[1], step=0.01, initial_value=0.7)
            with gui.add_folder("Racket velocity [m/s]"):
                self.vx = gui.add_slider("v_x", min=-b.velocity[0], max=b.velocity[0], step=0.05, initial_value=4.0)
                self.vy = gui.add_slider("v_y", min=-b.velocity[1], max=b.velocity[1], step=0.05, initial_value=0.0)
                self.vz = gui.add_slider("v_z", min=-b.velocity[2], max=b.velocity[2], step=0.05, initial_value=0.0)
            with gui.add_folder("Racket normal [deg]"):
                self.yaw = gui.add_slider("yaw", min=math.degrees(b.yaw[0]), max=math.degrees(b.yaw[1]), step=0.5, initial_value=90.0)
                self.roll = gui.add_slider("roll", min=-180.0, max=180.0, step=0.5, initial_value=0.0)
            with gui.add_folder("Contact offset [m]", expand_by_default=False):
                self.dpx = gui.add_slider("dp_x", min=-b.offset, max=b.offset, step=0.002, initial_value=0.0)
                self.dpy = gui.add_slider("dp_y", min=-b.offset, max=b.offset, step=0.002, initial_value=0.0)
                self.dpz = gui.add_slider("dp_z", min=-b.offset, max=b.offset, step=0.002, initial_value=0.0)
            with gui.add_folder("Joint limits [x robot's]", expand_by_default=False):
                lo, hi = LIMIT_SCALE_RANGE
                self.limit_speed = gui.add_slider("speed", min=lo, max=hi, step=0.05, initial_value=1.0)
                self.limit_accel = gui.add_slider("acceleration", min=lo, max=hi, step=0.05, initial_value=1.0)
                self.limit_jerk = gui.add_slider("jerk", min=lo, max=hi, step=0.05, initial_value=1.0)
            self.mujoco = gui.add_checkbox("MuJoCo rollout", initial_value=False)
            with gui.add_folder("Files"):
                self.save_button = gui.add_button("Save as seed")
                self.download_button = gui.add_button("Download JSON")
                self.upload_button = gui.add_upload_button("Upload JSON", mime_type="application/json")
                self.export_button = gui.add_button("Export to library")
                self.export_beyond = gui.add_checkbox(
                    "Export beyond effort limits", initial_value=False,
                    hint="Raise each exceeded joint's effort limit to the plan's peak for this export (recorded in the entry)",
                )  # fmt: skip
                self.library_pick = gui.add_dropdown("Library serve", options=["(none)"], initial_value="(none)")
        with tabs.add_tab("Checks"):
            self.status_md = gui.add_markdown("_evaluating..._")
            self.checks_md = gui.add_markdown("")
        with tabs.add_tab("Metrics"):
            self.metrics_md = gui.add_markdown("")
        with tabs.add_tab("Optimize"):
            gui.add_markdown(
                "HEBO over the genome for the current task and toss side, seeded with the current "
                "serve and the saved seeds of that side. Every evaluation is logged to the run folder."
            )
            self.opt_iterations = gui.add_number("iterations", initial_value=10, min=1, max=100, step=1)
            self.opt_population = gui.add_number("population", initial_value=20, min=2, max=50, step=1)
            self.opt_workers = gui.add_number("workers", initial_value=2, min=1, max=16, step=1)
            self.opt_tosses = gui.add_number("tosses per evaluation", initial_value=5, min=1, max=20, step=1)
            self.opt_seed = gui.add_number("seed", initial_value=0, min=0, max=2**31 - 1, step=1)
            self.opt_run = gui.add_dropdown("run", options=[NEW_RUN], initial_value=NEW_RUN, hint="a new run, or an earlier run of this side and task to continue")
            self.opt_follow = gui.add_checkbox("show best so far", initial_value=True)
            self.opt_start = gui.add_button("Optimize from seeds")
            self.rob_evaluations = gui.add_number("robust candidates", initial_value=600, min=12, max=10000, step=12)
            self.rob_start = gui.add_button("Make robust", hint="local search around the current serve for one legal on more recorded tosses, keeping 90 % of its spin at the net")
            self.opt_stop = gui.add_button("Stop", disabled=True)
            self.opt_progress = gui.add_progress_bar(0.0, animated=False)
            self.opt_md = gui.add_markdown("")
            self.opt_plot = gui.add_uplot(
                data=(np.zeros(1), np.zeros(1)),
                series=({"label": "evaluations"}, {"label": "best reward", "stroke": "green", "width": 2}),
                title="convergence",
                scales={"x": {"time": False}},  # evaluations, not a date axis
                aspect=1.6,
            )
        with tabs.add_tab("Match"):
            gui.add_markdown(
                "Serve a match from the library: the next serve follows the paper's strategy (the least-used "
                "legal serve of another spin cluster than the previous one); record each point to the "
                "library's match log (`matches.jsonl`), which keeps the usage counters and the statistics."
            )
            self.match_next = gui.add_button("Next serve")
            self.match_play = gui.add_checkbox("play it", initial_value=True)
            self.match_opponent = gui.add_text("opponent", initial_value="")
            self.match_robot = gui.add_button_group("robot served", options=["won", "ace", "lost"])
            self.match_receive = gui.add_button_group("opponent served", options=["robot won", "robot lost"])
            self.match_md = gui.add_markdown("_no serve selected yet_")
            self.match_stats_md = gui.add_markdown("")
        with gui.add_folder("Playback"):
            self.play = gui.add_button("Play")
            self.time = gui.add_slider("time [s]", min=0.0, max=2.5, step=0.005, initial_value=0.0)
            self.speed = gui.add_dropdown("speed", options=["0.1x", "0.25x", "0.5x", "1x"], initial_value="0.25x")
        self.message_md = gui.add_markdown("")

        controls = (self.side, self.toss, self.task, self.tau, self.t_return, self.vx, self.vy, self.vz, self.yaw, self.roll, self.dpx, self.dpy, self.dpz, self.limit_speed, self.limit_accel, self.limit_jerk, self.mujoco)
        for handle in controls:
            handle.on_update(lambda _event: self._changed())
        self.side.on_update(lambda _event: self._refresh_toss_options())
        self.side.on_update(lambda _event: self.refresh_runs())
        self.task.on_update(lambda _event: self.refresh_runs())
        self.serve_file.on_update(lambda _event: self._load_selected())
        self.save_button.on_click(lambda event: self._save_seed(event))
        self.download_button.on_click(lambda event: self._download(event))
        self.upload_button.on_upload(lambda event: self._upload(event))
        self.export_button.on_click(lambda _event: self._export())
        self.library_pick.on_update(lambda _event: self._load_library_serve())
        self.play.on_click(lambda _event: self._toggle_play())
        self.opt_start.on_click(lambda _event: self._start_optimization())
        self.rob_start.on_click(lambda _event: self.start_robustify())
        self.opt_stop.on_click(lambda _event: self._stop_event.set())
        self.match_next.on_click(lambda _event: self.next_match_serve())
        self.match_robot.on_click(lambda event: self.record_match_point("robot", event.target.value))
        self.match_receive.on_click(lambda event: self.record_match_point("opponent", event.target.value))
        self.time.on_update(lambda _event: None if self._playing else self.scene.show_time(self.time.value))
        self._refresh_serve_files()
        self._refresh_library()
        self.refresh_match_stats()
        self.refresh_runs()

    # -- controls <-> serve -----------------------------------------------------------

    def _fallback_serve(self) -> HandServe:
        return HandServe(name="my serve", side="right", params=ServeParams(tau=0.8, velocity=(4.0, 0.0, 0.0), yaw=math.pi / 2, roll=0.0))

    def controls(self) -> Controls:
        """Read the controls into a validated snapshot (InvalidInputError names the control)."""
        values = {
            "tau": self.tau.value,
            "return": self.t_return.value,
            "v_x": self.vx.value,
            "v_y": self.vy.value,
            "v_z": self.vz.value,
            "yaw": self.yaw.value,
            "roll": self.roll.value,
            "dp_x": self.dpx.value,
            "dp_y": self.dpy.value,
            "dp_z": self.dpz.value,
            "speed limit": self.limit_speed.value,
            "acceleration limit": self.limit_accel.value,
            "jerk limit": self.limit_jerk.value,
        }
        for key, value in values.items():
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InvalidInputError(f"control {key!r} must be a finite number, got {value!r}")
        params = ServeParams(
            tau=float(values["tau"]),
            velocity=(float(values["v_x"]), float(values["v_y"]), float(values["v_z"])),
            yaw=math.radians(values["yaw"]),
            roll=math.radians(values["roll"]),
            t_return=float(values["return"]),
            offset=(float(values["dp_x"]), float(values["dp_y"]), float(values["dp_z"])),
        )
        try:
            scale = LimitScale(velocity=float(values["speed limit"]), acceleration=float(values["acceleration limit"]), jerk=float(values["jerk limit"]))
        except InvalidInputError as err:
            raise InvalidInputError(f"joint limits control: {err}") from None
        serve = HandServe(name=self.name.value.strip() or "my serve", side=self.side.value, params=params, task=self.task.value, limit_scale=scale)
        toss = None if self.toss.value == "mean path" else int(self.toss.value.split()[-1]) - 1
        return Controls(serve=serve, task=self.task.value, toss_sample=toss, mujoco=bool(self.mujoco.value))

    def load(self, serve: HandServe) -> None:
        """Put a serve into the controls and evaluate it."""
        p = serve.params
        self._suspend = True
        try:
            self.name.value = serve.name
            self.side.value = serve.side
            if serve.task in TASKS:
                self.task.value = serve.task
            self.tau.value = float(np.clip(p.tau, self.tau.min, self.tau.max))
            self.t_return.value = float(np.clip(p.t_return, self.t_return.min, self.t_return.max))
            for handle, value in ((self.vx, p.velocity[0]), (self.vy, p.velocity[1]), (self.vz, p.velocity[2]), (self.dpx, p.offset[0]), (self.dpy, p.offset[1]), (self.dpz, p.offset[2])):
                handle.value = float(np.clip(value, handle.min, handle.max))
            self.yaw.value = float(np.clip(math.degrees(p.yaw), self.yaw.min, self.yaw.max))
            self.roll.value = float(np.clip(math.degrees(p.roll), self.roll.min, self.roll.max))
            scale = serve.limit_scale  # the sliders span LIMIT_SCALE_RANGE: every valid scale fits
            self.limit_speed.value, self.limit_accel.value, self.limit_jerk.value = scale.velocity, scale.acceleration, scale.jerk
            self._refresh_toss_options()
        finally:
            self._suspend = False
        self._changed()

    def _refresh_toss_options(self) -> None:
        n = self.context.toss_model(self.side.value).n_tosses
        options = ["mean path", *(f"recorded {i + 1}" for i in range(n))]
        current = self.toss.value if self.toss.value in options else "mean path"
        self.toss.options = options
        self.toss.value = current

    def _refresh_serve_files(self) -> None:
        names = ["(current)", *list_serves(self.serves_dir), *(f"example/{k}" for k in list_serves(EXAMPLES_DIR) if self.serves_dir.resolve() != EXAMPLES_DIR.resolve())]
        self._suspend = True
        try:
            self.serve_file.options = names
            self.serve_file.value = "(current)"
        finally:
            self._suspend = False

    # -- events -----------------------------------------------------------------------

    def _changed(self) -> None:
        if self._suspend:
            return
        try:
            self.worker.submit(self.controls())
            self.status_md.content = "_evaluating..._"
        except StudioError as err:
            self._message(f"**Input rejected:** {err}")

    def _load_selected(self) -> None:
        if self._suspend or self.serve_file.value == "(current)":
            return
        key = self.serve_file.value
        folder, stem = (EXAMPLES_DIR, key.split("/", 1)[1]) if key.startswith("example/") else (self.serves_dir, key)
        try:
            self.load(load_serve(folder / f"{stem}.json"))
            self._message(f"Loaded `{stem}`.")
        except StudioError as err:
            self._message(f"**Cannot load {stem}:** {err}")

    def _save_seed(self, _event: Any) -> None:
        try:
            serve = self.controls().serve
            self.serves_dir.mkdir(parents=True, exist_ok=True)
            path = self.serves_dir / f"{safe_name(serve.name)}.json"
            if not inside(self.serves_dir, path):
                raise InvalidInputError(f"serve name {serve.name!r} leaves the serves folder")
            save_serve(path, serve)
            self._refresh_serve_files()
            self._message(f"Saved seed `{path.name}` in `{self.serves_dir}`.")
        except (StudioError, OSError) as err:
            self._message(f"**Save failed:** {err}")

    def _download(self, event: Any) -> None:
        try:
            serve = self.controls().serve
            data = (json.dumps(serve.to_json(), indent=2) + "\n").encode()
            if event.client is not None:
                event.client.send_file_download(f"{safe_name(serve.name)}.json", data)
        except StudioError as err:
            self._message(f"**Download failed:** {err}")

    def _upload(self, event: Any) -> None:
        file = self.upload_button.value
        try:
            data = json.loads(file.content.decode("utf-8"))
            self.load(serve_from_json(data, source=file.name))
            self._message(f"Loaded upload `{file.name}`.")
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            self._message(f"**Upload rejected:** {file.name}: not valid JSON ({err})")
        except StudioError as err:
            self._message(f"**Upload rejected:** {err}")

    def _refresh_library(self) -> None:
        """List the library's serves in the "Library serve" dropdown (errors go to the message)."""
        from studio.library.store import ServeLibrary

        try:
            entries = ServeLibrary(self.library_dir).entries()
        except StudioError as err:
            entries = []
            self._message(f"**Library unreadable:** {err}")
        self._library_ids = {f"{e.data['name']} [{e.id}]": e.id for e in entries}
        self._suspend = True
        try:
            self.library_pick.options = ["(none)", *self._library_ids]
            self.library_pick.value = "(none)"
        finally:
            self._suspend = False

    def _load_library_serve(self) -> None:
        from studio.library.store import ServeLibrary

        if self._suspend or self.library_pick.value == "(none)":
            return
        try:
            entry = ServeLibrary(self.library_dir).get(self._library_ids[self.library_pick.value])
            self.load(entry.serve)
            self._message(f"Loaded library serve `{entry.id}`.")
        except (StudioError, KeyError) as err:
            self._message(f"**Cannot load library serve:** {err}")

    def poll_open_request(self, *, act: bool = True) -> bool:
        """Load the serve a dashboard asked for (``open-request.json`` in the library
        folder, :func:`studio.library.store.request_open`), once per request. True if loaded."""
        with self._open_lock:
            return self._poll_open_request(act)

    def _poll_open_request(self, act: bool) -> bool:
        from studio.library.store import ServeLibrary, read_open_request

        try:
            req = read_open_request(self.library_dir)
        except StudioError as err:
            if act:
                self._message(f"**Open request ignored:** {err}")
            return False
        if req is None or req.nonce == self._open_nonce:
            return False
        self._open_nonce = req.nonce
        if not act:
            return False
        try:
            entry = ServeLibrary(self.library_dir).get(req.id)
        except StudioError as err:
            self._message(f"**Cannot open library serve** `{req.id}`: {err}")
            return False
        self._show_library_entry(entry)
        self._message(f"Opened library serve `{entry.id}` ({entry.data['name']}) from the dashboard.")
        return True

    def _show_library_entry(self, entry: Any) -> None:
        """Load a library entry into the controls and select it in the "Library serve" list."""
        self._refresh_library()
        label = next((k for k, v in self._library_ids.items() if v == entry.id), None)
        self._suspend = True
        try:
            if label is not None:
                self.library_pick.value = label
        finally:
            self._suspend = False
        self.load(entry.serve)

    def _open_request_loop(self) -> None:
        while True:
            time.sleep(0.5)
            self.poll_open_request()

    def _export(self) -> None:
        from studio.library.store import ServeLibrary

        with self._lock:
            evaluation, efforts = self.last, self.last_efforts
        if evaluation is None:
            self._message("**Export failed:** nothing evaluated yet")
            return
        raised = efforts.raised_to_peaks() if efforts is not None and self.export_beyond.value else None
        limits = {n: float(lim) for n, lim in zip(raised.names, raised.limit) if n in raised.raised} if raised is not None else {}
        try:
            entry = ServeLibrary(self.library_dir).add(
                evaluation, provenance={"kind": "hand-designed", "tool": "studio"}, task=self.task.value, preparation=self.context.preparation(evaluation.serve.side),
                effort_limits=limits,
            )
            verdict = "legal" if evaluation.legal else f"NOT legal ({evaluation.reason})"
            beyond = f" Effort limits raised on purpose: {', '.join(f'{n} {v:g}' for n, v in limits.items())}." if limits else ""
            self._message(f"Exported `{evaluation.serve.name}` ({verdict}) to `{self.library_dir}` as `{entry.id}`.{beyond}")
            self._refresh_library()
        except (StudioError, OSError) as err:
            self._message(f"**Export failed:** {err}")

    def _message(self, text: str) -> None:
        self.message_md.content = text

    # -- worker -----------------------------------------------------------------------

    def _compute(self, controls: Controls) -> Evaluation:
        return evaluate_serve(
            controls.serve,
            self.context,
            task=controls.task,
            toss_sample=controls.toss_sample,
            mujoco=controls.mujoco,
        )

    def _publish(self, result: WorkResult[Controls, Evaluation]) -> None:
        if result.error is not None or result.value is None:
            self.status_md.content = f"**Evaluation failed** ({type(result.error).__name__}): {result.error}"
            return
        evaluation = result.value
        frame = scene_frame(evaluation, self.context)
        efforts = effort_report(evaluation.motion, self.context.robot)  # the worker's thread, as the frame
        with self._lock:
            self.last = evaluation
            self.last_efforts = efforts
            self.scene.show(frame)
            status, checks, metrics = report_markdown(evaluation)
            self.status_md.content = status + f"\n\n_evaluated in {1000 * result.seconds:.0f} ms_"
            self.checks_md.content = checks + (f"\n\n{efforts.headline()} (table in Metrics)" if efforts is not None else "")
            self.metrics_md.content = metrics + (f"\n\n{efforts.markdown()}" if efforts is not None else "")
            pb = frame.playback
            if pb is not None and len(pb.t):
                self.time.max = float(pb.t[-1])
                self.time.min = float(pb.t[0])
                self.time.value = float(np.clip(self.time.value, pb.t[0], pb.t[-1]))
                self.scene.show_time(self.time.value)

    # -- optimization -----------------------------------------------------------------

    def seeds_for(self, side: str) -> list[HandServe]:
        """The current serve plus every saved seed and example of ``side`` (valid files only)."""
        seeds = [self.controls().serve]
        for folder in (self.serves_dir, EXAMPLES_DIR):
            for path in list_serves(folder).values():
                try:
                    serve = load_serve(path)
                except StudioError:
                    continue
                if serve.side == side and all(serve.params != s.params for s in seeds):
                    seeds.append(serve)
        return seeds

    def refresh_runs(self) -> None:
        """List the runs of the current side and task in ``runs_dir`` in the "run" dropdown
        (unreadable run folders are reported in the Optimize tab)."""
        from studio.optimize.optimizer import list_runs

        runs, problems = list_runs(self.runs_dir, side=self.side.value, task=self.task.value)
        chosen = self._runs[self.opt_run.value].run_dir.name if self.opt_run.value in self._runs else None
        self._runs = {r.label(): r for r in runs}
        self.opt_run.options = [NEW_RUN, *self._runs]
        # the labels carry the progress: the choice follows its folder
        self.opt_run.value = next((k for k, r in self._runs.items() if r.run_dir.name == chosen), NEW_RUN)
        if problems and not self._optimizing:
            self.opt_md.content = "**Unreadable run folders (not listed):**  \n" + "  \n".join(problems)

    def _start_optimization(self) -> None:
        try:
            controls = self.controls()
            iterations, population, workers, tosses, seed = (
                int(h.value) for h in (self.opt_iterations, self.opt_population, self.opt_workers, self.opt_tosses, self.opt_seed)
            )
            if min(iterations, population, workers, tosses) < 1 or seed < 0:
                raise InvalidInputError("iterations, population, workers and tosses must be >= 1 and the seed >= 0")
            run = None if self.opt_run.value == NEW_RUN else self._runs.get(self.opt_run.value)
            if self.opt_run.value != NEW_RUN and run is None:
                raise InvalidInputError(f"run {self.opt_run.value!r} is no longer listed")
        except (StudioError, TypeError, ValueError, OverflowError) as err:
            self.opt_md.content = f"**Cannot start:** {err}"
            return
        if not self._claim_busy():
            return
        threading.Thread(
            target=self._run_optimization,
            args=(controls, iterations, population, workers, tosses, seed, run),
            name="studio-optimizer",
            daemon=True,
        ).start()

    def _run_optimization(self, controls: Controls, iterations: int, population: int, workers: int, tosses: int, seed: int, run: RunSummary | None = None) -> None:
        """A new HEBO run from the seeds, or with ``run`` the continuation of that run (its own
        seeds, seed, population, tosses and limits; at least its own iterations)."""
        from studio.optimize.optimizer import optimize_serve

        side, task = controls.serve.side, controls.task
        run_dir = self.runs_dir / f"{time.strftime('%Y%m%d-%H%M%S')}-{side}-{task}"
        scale = controls.serve.limit_scale
        if run is not None:
            side, task, run_dir, population, tosses, seed, scale = run.side, run.task, run.run_dir, run.population, run.tosses, run.seed, run.limit_scale
            iterations = max(iterations, run.iterations)
        xs: list[float] = []
        ys: list[float] = []
        last_best: list[ServeParams | None] = [None]

        def progress(done: int, total: int, best: float, params: ServeParams | None) -> None:
            self.opt_progress.value = 100.0 * done / max(total, 1)
            xs.append(float(done))
            ys.append(float(best))
            self.opt_plot.data = (np.array(xs), np.array(ys))
            self.opt_md.content = f"{done} / {total} evaluations, best reward {best:+.3f}  \nrun folder `{run_dir}`"
            if params is not None and params != last_best[0] and self.opt_follow.value:
                last_best[0] = params
                self.load(HandServe(name=f"{task} best so far", side=side, params=params, task=task, limit_scale=scale))

        try:
            seeds = [] if run is not None else self.seeds_for(side)  # a resumed run takes its own from run.json
            self.opt_md.content = f"resuming `{run_dir.name}` ({run.evaluations} evaluations logged) ..." if run is not None else f"evaluating {len(seeds)} seed(s) ..."
            result = optimize_serve(
                side=side,
                task=task,
                run_dir=run_dir,
                seeds=seeds,
                iterations=iterations,
                population=population,
                workers=workers,
                tosses=tosses,
                seed=seed,
                progress=progress,
                stop=self._stop_event,
                limit_scale=scale,
                resume=run is not None,
            )
            if result.best is not None and result.summary is not None:
                best = replace(result.best, name=f"{task} optimized", task=task, notes=f"HEBO run {run_dir.name}, seed {seed}")
                self.load(best)
                s = result.summary
                self.opt_md.content = (
                    f"**{'Stopped' if result.stopped else 'Done'}:** {result.evaluations} evaluations in {result.timings.get('total', 0):.0f} s. "
                    f"Chosen serve: mean reward {s.mean_reward:+.3f} over {len(s.rewards)} fresh tosses, legal on {100 * s.legal_fraction:.0f} %. "
                    f"It is now in the controls: export it to the library with *Export to library*.  \nrun folder `{run_dir}`"
                )
            else:
                self.opt_md.content = "**Nothing evaluated.**"
        except Exception as err:  # noqa: BLE001 - shown in the panel, the studio keeps running
            self.opt_md.content = f"**Optimization failed:** {type(err).__name__}: {err}  \n(evaluations so far are kept in `{run_dir}`)"
        finally:
            self.refresh_runs()  # before the busy flag drops: unreadable folders do not hide the result
            self._set_busy(False)

    def start_robustify(self) -> None:
        """Run :func:`studio.optimize.robust.robustify_serve` on the current serve in the background
        (progress and Stop as an optimization); the result lands in the controls."""
        try:
            controls = self.controls()
            value = self.rob_evaluations.value
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 1 and float(value).is_integer()):
                raise InvalidInputError(f"robust candidates must be a whole number >= 1, got {value!r}")
            evaluations = int(value)
        except StudioError as err:
            self.opt_md.content = f"**Cannot start:** {err}"
            return
        if not self._claim_busy():
            return
        threading.Thread(target=self._run_robustify, args=(controls, evaluations), name="studio-robustify", daemon=True).start()

    def _claim_busy(self) -> bool:
        """Mark the studio busy with one long job (optimization or robustify); False if one runs."""
        with self._busy_lock:
            if self._optimizing:
                return False
            self._set_busy(True)
            return True

    def _set_busy(self, busy: bool) -> None:
        self._optimizing = busy
        if busy:
            self._stop_event.clear()
        self.opt_start.disabled = busy
        self.rob_start.disabled = busy
        self.opt_stop.disabled = not busy

    def _run_robustify(self, controls: Controls, evaluations: int) -> None:
        from studio.optimize.robust import RobustScore, robustify_serve

        start = time.perf_counter()

        def progress(done: int, total: int, best: RobustScore) -> None:
            self.opt_progress.value = 100.0 * done / max(total, 1)
            self.opt_md.content = f"robustify: {done} / {total} candidates, best legal on {best.legal}/{best.tosses} recorded tosses ({time.perf_counter() - start:.0f} s)"

        try:
            if self._robust_context is None:  # the live evaluation's context is not shared between threads
                self.opt_md.content = "robustify: loading models ..."
                self._robust_context = EvaluationContext.default()
            res = robustify_serve(controls.serve, context=self._robust_context, task=controls.task, evaluations=evaluations, progress=progress, stop=self._stop_event)
            if res.improved:
                self.load(replace(res.serve, name=f"{controls.serve.name} robust"))
            self.opt_md.content = f"**{res.summary()}**" + (" The serve is now in the controls." if res.improved else "") + f" ({time.perf_counter() - start:.0f} s)"
        except Exception as err:  # noqa: BLE001 - shown in the panel, the studio keeps running
            self.opt_md.content = f"**Robustify failed:** {type(err).__name__}: {err}"
        finally:
            self._set_busy(False)

    # -- match ------------------------------------------------------------------------

    def next_match_serve(self) -> None:
        """Select the robot's next serve (:func:`studio.library.match.next_serve`), load it and play it."""
        from studio.library.store import ServeLibrary
        from studio.library.match import next_serve
        from studio.library.selection import serve_cluster, usage_count

        try:
            entry = next_serve(ServeLibrary(self.library_dir), self._match_serve)  # a pruned previous serve counts as none
        except StudioError as err:
            self.match_md.content = f"**No serve:** {err}"
            return
        previous = self._match_serve
        self._match_serve = entry.id
        self._show_library_entry(entry)
        self.match_md.content = (
            f"**Serve `{entry.data['name']}`** ({entry.id}): cluster {serve_cluster(entry)}, used {usage_count(entry)} times before"
            + (f"; previous `{previous}`" if previous else "")
            + ".  \nRecord the point when it is over."
        )
        if self.match_play.value and not self._playing:
            self.time.value = self.time.min
            self._toggle_play()

    def record_match_point(self, server: str, outcome: str) -> None:
        """Record a point in the library's match log (:func:`studio.library.match.record_point`):
        ``server`` "robot" with outcome won/ace/lost of the current match serve, or
        "opponent" with robot won/robot lost."""
        from studio.library.store import ServeLibrary
        from studio.library.match import record_point

        won = outcome in ("won", "ace", "robot won")
        try:
            points = record_point(
                ServeLibrary(self.library_dir), server=server, winner="robot" if won else "opponent",
                serve=self._match_serve if server == "robot" else None, ace=outcome == "ace", opponent=self.match_opponent.value.strip(),
            )  # fmt: skip
        except StudioError as err:
            self.match_md.content = f"**Point not recorded:** {err}" + (" Press *Next serve* first." if server == "robot" and self._match_serve is None else "")
            return
        self.match_md.content = f"Point {len(points)} recorded: {server} served, {'robot' if won else 'opponent'} won{' (ace)' if outcome == 'ace' else ''}."
        self.refresh_match_stats()

    def refresh_match_stats(self) -> None:
        """Show the Table I statistics and the per-serve records of the library's match log."""
        from studio.library.store import ServeLibrary
        from studio.library.match import MATCH_LOG, load_points, stats_report

        lib = ServeLibrary(self.library_dir)
        try:
            self.match_stats_md.content = stats_report(lib.entries(), load_points(lib.folder / MATCH_LOG), compact=True)
        except StudioError as err:
            self.match_stats_md.content = f"**Match log unreadable:** {err}"

    # -- playback ---------------------------------------------------------------------

    def _toggle_play(self) -> None:
        self._playing = not self._playing
        self.play.label = "Pause" if self._playing else "Play"

    def _playback_loop(self) -> None:
        last = time.perf_counter()
        while True:
            time.sleep(1 / 30)
            now = time.perf_counter()
            dt, last = now - last, now
            if not self._playing:
                continue
            speed = float(self.speed.value.rstrip("x"))
            t_new = self.time.value + dt * speed
            if t_new > self.time.max:
                t_new = self.time.min
            self.time.value = t_new
            with self._lock:
                self.scene.show_time(t_new)


def run_app(*, host: str = "127.0.0.1", port: int = 8080, serves_dir: str | None = None, library_dir: str | None = None) -> None:
    """Start the studio and serve until interrupted."""
    import viser

    print("serve-studio: loading robot, tosses and planner ...", flush=True)
    context = EvaluationContext.default()
    serves = Path(serves_dir) if serves_dir else Path.cwd() / "serves"
    library = Path(library_dir) if library_dir else Path.cwd() / "serve-library"
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

