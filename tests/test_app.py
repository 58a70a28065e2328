"""The studio app without a browser: controls, file helpers, optimization from seeds."""

from __future__ import annotations

import json
import math
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import viser

from studio.errors import InvalidInputError
from studio.serve.evaluate import EvaluationContext
from studio.ui.app import StudioApp, inside, list_serves, safe_name


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_safe_name_and_inside(tmp_path: Path) -> None:
    assert safe_name(" my serve/../x ") == "my_serve____x"
    with pytest.raises(InvalidInputError):
        safe_name("../")
    assert inside(tmp_path, tmp_path / "a.json")
    assert not inside(tmp_path, tmp_path / ".." / "a.json")
    (tmp_path / "b.json").write_text("{}")
    assert list(list_serves(tmp_path)) == ["b"]
    assert list_serves(tmp_path / "missing") == {}


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[StudioApp]:
    folder = tmp_path_factory.mktemp("studio")
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    studio = StudioApp(server, context=EvaluationContext.default(), serves_dir=folder / "serves", library_dir=folder / "lib", watch_open_requests=False)
    assert studio.worker.wait_idle(300)
    # a serve within the effort limits, whichever test a worker runs first (the first
    # example file, backspin heavy right, needs gantry_x at 110 %: its export is refused)
    from studio.serve.params import load_serve
    from studio.ui.app import EXAMPLES_DIR

    studio.load(load_serve(EXAMPLES_DIR / "topspin_right.json"))
    assert studio.worker.wait_idle(300)
    yield studio
    studio.worker.close()
    server.stop()


def test_metrics_tab_shows_the_joint_efforts(app: StudioApp) -> None:
    assert app.worker.wait_idle(120) and app.last is not None
    assert "**Joint efforts" in app.metrics_md.content and "| a2 |" in app.metrics_md.content
    assert "**Joint efforts" in app.checks_md.content and "| a2 |" not in app.checks_md.content  # the verdict line only


def test_non_finite_control_is_rejected_not_evaluated(app: StudioApp) -> None:
    assert app.worker.wait_idle(120)
    kept = app.form.vx.value
    before = app.worker.latest_ticket
    app.form.vx.value = math.nan  # the control's change callback refuses it and puts the last valid value back
    assert "Refused" in app.message_md.content and "v_x" in app.message_md.content and "[-10, 10] m/s" in app.message_md.content
    assert app.form.vx.value == kept
    assert app.worker.latest_ticket == before  # nothing submitted
    app._suspend = True
    app.form.vx._impl.value = math.nan  # around every callback: reading the controls still refuses it
    app._suspend = False
    try:
        app._changed()
        assert "Input rejected" in app.message_md.content and "v_x" in app.message_md.content
        assert app.worker.latest_ticket == before
    finally:
        app.form.vx._impl.value = kept
    app.form.vx.value = 3.0
    assert app.worker.wait_idle(120)


def test_joint_limit_controls_set_the_serves_limit_scale(app: StudioApp) -> None:
    from dataclasses import replace

    from studio.serve.params import LimitScale

    assert app.worker.wait_idle(120)
    before = app.worker.latest_ticket
    app.form.limit_accel.value = math.nan
    assert "Refused" in app.message_md.content and "acceleration limit" in app.message_md.content and "[0.25, 4]" in app.message_md.content
    assert app.worker.latest_ticket == before and math.isfinite(app.form.limit_accel.value)
    scale = LimitScale(velocity=1.2, acceleration=1.5, jerk=3.7)
    app.load(replace(app.last.serve, limit_scale=scale))  # type: ignore[union-attr]
    assert (app.form.limit_speed.value, app.form.limit_accel.value, app.form.limit_jerk.value) == (1.2, 1.5, 3.7)
    assert app.controls().serve.limit_scale == scale
    assert app.worker.wait_idle(120)
    assert app.last is not None and app.last.serve.limit_scale == scale
    app.load(replace(app.last.serve, limit_scale=LimitScale()))
    assert app.controls().serve.limit_scale.is_identity
    assert app.worker.wait_idle(120)


def test_corrupt_upload_is_reported(app: StudioApp) -> None:
    class File:
        name = "bad.json"
        content = b'{"name": "x", "side": "up"}'

    app.files.upload(File())  # what the upload button hands over
    assert "Upload rejected" in app.message_md.content and "side" in app.message_md.content


def test_optimize_from_seeds_runs_and_loads_the_best(app: StudioApp) -> None:
    app.jobs.opt_iterations.value = 1
    app.jobs.opt_population.value = 2
    app.jobs.opt_workers.value = 1
    app.jobs.opt_tosses.value = 2
    seeds = app.jobs.seeds_for(app.form.side.value)
    assert len(seeds) >= 3  # current serve + the shipped examples of that side
    app.jobs.start_optimization()
    deadline = time.monotonic() + 600
    while app.jobs.busy and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not app.jobs.busy
    assert "Done" in app.jobs.opt_md.content, app.jobs.opt_md.content
    runs = list(app.runs_dir.iterdir())
    assert len(runs) == 1
    lines = (runs[0] / "evaluations.jsonl").read_text().splitlines()
    assert len(lines) >= len(seeds) + 2
    assert all(math.isfinite(json.loads(line)["reward"]) for line in lines)
    assert app.jobs.opt_progress.value == pytest.approx(100.0)
    assert app.worker.wait_idle(120)
    assert app.last is not None and app.last.serve.name.endswith("optimized")


def test_export_beyond_the_effort_limits_needs_the_checkbox(app: StudioApp) -> None:
    """backspin_heavy_right (limits x2) exceeds gantry_x: Checks says so, Export refuses; with
    "Export beyond effort limits" it exports and the entry records the raised limit."""
    from studio.library.store import ServeLibrary
    from studio.serve.params import load_serve

    before = len(ServeLibrary(app.library_dir).entries()) if (app.library_dir / "index.json").exists() else 0
    assert app.worker.wait_idle(120) and app.last is not None
    previous = app.last.serve
    app.load(load_serve(Path(__file__).resolve().parent.parent / "examples" / "serves" / "backspin_heavy_right.json"))
    assert app.worker.wait_idle(120) and app.last is not None and app.last.serve.name.startswith("backspin")
    assert "EXCEED" in app.checks_md.content and "gantry_x" in app.checks_md.content
    app.files.export()
    assert "Export failed" in app.message_md.content and "gantry_x" in app.message_md.content
    assert (len(ServeLibrary(app.library_dir).entries()) if (app.library_dir / "index.json").exists() else 0) == before
    app.files.export_beyond.value = True
    try:
        app.files.export()
    finally:
        app.files.export_beyond.value = False
    assert "Exported" in app.message_md.content and "raised on purpose: gantry_x" in app.message_md.content
    newest = ServeLibrary(app.library_dir).entries()[-1]
    assert newest.data["robot"]["efforts"]["raised"] == ["gantry_x"] and newest.data["robot"]["efforts"]["within"]
    app.load(previous)  # the module's app goes on with its own serve
    assert app.worker.wait_idle(120)


def test_export_then_load_library_serve(app: StudioApp) -> None:
    from studio.library.store import ServeLibrary

    assert app.worker.wait_idle(120)
    app.files.export()
    assert "Exported" in app.message_md.content
    newest = ServeLibrary(app.library_dir).entries()[-1]
    assert newest.data["robot"]["efforts"]["names"] == list(app.context.robot.joint_names)  # the evaluation's own report
    labels = [o for o in app.files.library_pick.options if o != "(none)"]
    assert labels
    exported = app.last.serve.params  # type: ignore[union-attr]
    app._suspend = True
    app.form.vx.value = app.form.vx.value + 0.5
    app._suspend = False
    app.files.library_pick.value = labels[-1]
    app.files.load_library_serve()
    assert "Loaded library serve" in app.message_md.content
    assert app.controls().serve.params.velocity[0] == pytest.approx(exported.velocity[0], abs=0.051)


def test_open_request_from_the_dashboard_loads_the_serve_once(app: StudioApp) -> None:
    from studio.library.store import OPEN_REQUEST_NAME, ServeLibrary, request_open

    app.files.export()  # make sure the library holds a serve
    entries = ServeLibrary(app.library_dir).entries()
    target = entries[-1]
    app._suspend = True
    app.form.vx.value = app.form.vx.value + 0.7  # move away from it
    app._suspend = False
    app._changed()
    assert not app.files.poll_open_request()  # no new request: nothing happens
    request_open(app.library_dir, target.id)
    assert app.files.poll_open_request()
    assert target.id in app.message_md.content and "Opened library serve" in app.message_md.content
    assert app.controls().serve.params.velocity[0] == pytest.approx(target.serve.params.velocity[0], abs=0.051)
    assert app.files.library_pick.value.endswith(f"[{target.id}]")
    assert not app.files.poll_open_request()  # each request is acted on once
    assert app.worker.wait_idle(120)
    # a corrupt request file is reported, not raised
    (app.library_dir / OPEN_REQUEST_NAME).write_text("{not json")
    assert not app.files.poll_open_request()
    assert "Open request ignored" in app.message_md.content and OPEN_REQUEST_NAME in app.message_md.content
    (app.library_dir / OPEN_REQUEST_NAME).write_text(json.dumps({"schema": "serve-studio/open-request@1", "id": "../x", "nonce": "n1"}))
    assert not app.files.poll_open_request()
    assert "id" in app.message_md.content and "../x" in app.message_md.content  # the bad field is named
    with pytest.raises(InvalidInputError):
        request_open(app.library_dir, "no-such-serve")


def test_dashboard_open_in_studio_reaches_the_studio(app: StudioApp) -> None:
    from studio.ui.dashboard import LibraryDashboard

    app.files.export()
    dash = LibraryDashboard(app.library_dir, studio_url="http://127.0.0.1:8080")
    first = str(dash.tabulator.value["id"].iloc[0])
    assert dash.selected_id == first and not dash.open_button.disabled
    assert dash.open_in_studio() and dash.status.alert_type == "success"
    assert app.files.poll_open_request() and first in app.message_md.content
    assert app.worker.wait_idle(120)


def test_match_tab_selects_records_and_shows_statistics(app: StudioApp) -> None:
    from studio.library.match import MATCH_LOG, load_points
    from studio.library.selection import serve_cluster
    from studio.library.store import ServeLibrary
    from studio.serve.evaluate import evaluate_serve
    from studio.serve.params import load_serve

    lib = ServeLibrary(app.library_dir)
    examples = Path(__file__).resolve().parent.parent / "examples" / "serves"
    for name in ("topspin_right", "backspin_right"):
        lib.add(evaluate_serve(load_serve(examples / f"{name}.json"), app.context))
    app.match.current = None
    app.match.record_point("robot", "won")  # nothing served yet
    assert "Point not recorded" in app.match.match_md.content and "Next serve" in app.match.match_md.content
    assert not (app.library_dir / MATCH_LOG).exists()
    app.match.match_play.value = False
    app.match.next_serve()
    first = app.match.current
    assert first is not None and "Serve" in app.match.match_md.content
    assert app.worker.wait_idle(120) and app.last is not None
    assert app.last.serve.params == lib.get(first).serve.params  # the selected serve is in the controls
    app.match.match_opponent.value = "M. Test"
    app.match.record_point("robot", "ace")
    app.match.next_serve()
    second = app.match.current
    clusters = {e.id: serve_cluster(e) for e in lib.entries()}
    if len(set(clusters.values())) > 1:
        assert clusters[second] != clusters[first]  # the strategy changes the spin cluster
    app.match.record_point("opponent", "robot lost")
    points = load_points(app.library_dir / MATCH_LOG)
    assert [(p.server, p.serve, p.winner, p.ace, p.opponent) for p in points] == [("robot", first, "robot", True, "M. Test"), ("opponent", None, "opponent", False, "M. Test")]
    assert lib.get(first).data["usage"] == {"used": 1, "won": 1, "lost": 0, "aces": 1}
    stats = app.match.match_stats_md.content
    assert "serving: robot won 100.0 % of 1" in stats and "receiving: robot won 0.0 % of 1" in stats
    assert "aces: 1 (100.0 % of robot serves); opponents: M. Test" in stats
    # a corrupt log: the point is refused with file and line, nothing is appended
    with open(app.library_dir / MATCH_LOG, "a") as fh:
        fh.write("{not json\n")
    app.match.record_point("robot", "lost")
    assert "Point not recorded" in app.match.match_md.content and "line 3" in app.match.match_md.content
    assert (app.library_dir / MATCH_LOG).read_text().count("\n") == 3
    assert app.worker.wait_idle(120)


def _optimize_and_wait(app: StudioApp) -> None:
    app.jobs.start_optimization()
    deadline = time.monotonic() + 600
    while app.jobs.busy and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not app.jobs.busy and "Done" in app.jobs.opt_md.content, app.jobs.opt_md.content


def test_an_earlier_run_is_listed_and_resumed_without_repeating_evaluations(app: StudioApp) -> None:
    from studio.ui.app import NEW_RUN

    app.jobs.opt_iterations.value = 1
    app.jobs.opt_population.value = 2
    app.jobs.opt_workers.value = 1
    app.jobs.opt_tosses.value = 1
    app.jobs.opt_run.value = NEW_RUN
    before = set(app.runs_dir.iterdir()) if app.runs_dir.exists() else set()
    _optimize_and_wait(app)
    (run_dir,) = set(app.runs_dir.iterdir()) - before
    first = (run_dir / "evaluations.jsonl").read_text().splitlines()
    label = next(k for k, r in app.jobs.runs.items() if r.run_dir == run_dir)  # listed after the run
    assert label in app.jobs.opt_run.options and f"{len(first)}/{len(first)} evaluations" in label
    app.jobs.opt_run.value = label
    app.jobs.opt_iterations.value = 2
    app.jobs.opt_population.value = 7  # ignored: a resumed run keeps its own population
    _optimize_and_wait(app)
    lines = (run_dir / "evaluations.jsonl").read_text().splitlines()
    assert lines[: len(first)] == first and len(lines) == len(first) + 2  # one more batch of the run's 2
    assert set(app.runs_dir.iterdir()) - before == {run_dir}  # no new folder
    assert json.loads((run_dir / "run.json").read_text())["iterations"] == 2
    app.jobs.opt_run.value = NEW_RUN


def test_make_robust_runs_in_the_background_and_reports(app: StudioApp) -> None:
    app.jobs.rob_evaluations.value = 12
    app.jobs.start_robustify()
    assert app.jobs.busy and app.jobs.rob_start.disabled and app.jobs.opt_start.disabled
    deadline = time.monotonic() + 600
    while app.jobs.busy and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not app.jobs.busy and not app.jobs.rob_start.disabled
    text = app.jobs.opt_md.content
    assert "Done" in text and "after 12 candidates" in text, text
    assert ("now in the controls" in text) or ("No candidate beat it" in text)
    assert app.worker.wait_idle(120)


def test_mujoco_rollout_checkbox_shows_the_rollouts_verdict(app: StudioApp) -> None:
    """Ticking "MuJoCo rollout" evaluates the serve with the rollout (it used to fail:
    "rollout: X covers ... samples, t_end = ... needs ..."); a recorded toss cannot be
    replayed by it, which the studio says instead of mislabelling the rollout's toss."""
    from studio.serve.evaluate import evaluate_serve
    from studio.serve.params import load_serve
    from studio.ui.app import EXAMPLES_DIR

    def settle(what: str) -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (app.worker.wait_idle(1) and "_evaluating..._" not in app.status_md.content):
            time.sleep(0.05)
        assert app.worker.wait_idle(1), what

    app.load(load_serve(EXAMPLES_DIR / "topspin_right.json"))
    app.form.toss.value = "mean path"
    settle("analytic evaluation")
    app.form.mujoco.value = True
    try:
        settle("MuJoCo evaluation")
        ev = app.last
        assert ev is not None and ev.rollout is not None, app.status_md.content
        assert "Evaluation failed" not in app.status_md.content
        assert ev.rollout.end_reason == "floor" and ev.rollout.t[-1] > ev.t[-1]  # type: ignore[index]
        analytic = evaluate_serve(ev.serve, app.context, task=app.form.task.value)
        assert ev.status == analytic.status == "legal" and "LEGAL" in app.status_md.content
        assert abs(ev.reward.total - analytic.reward.total) < 0.05
        assert "time: mujoco" in app.metrics_md.content
        app.form.toss.value = "recorded 1"
        settle("refused recorded toss")
        assert "Evaluation failed" in app.status_md.content and "cannot replay recorded toss 1" in app.status_md.content
    finally:
        app.form.toss.value = "mean path"
        app.form.mujoco.value = False
        settle("back to the analytic evaluation")
    assert app.last is not None and app.last.rollout is None


def test_overlay_undo_redo_and_the_pinned_serve(app: StudioApp) -> None:
    """The overlay shows the evaluation's numbers after each re-plan; a pinned legal serve
    stays beside a broken one (numbers and dashed ghost); undo walks back one control at a
    time, redo forward, and "Restore A" brings the pinned serve back in one step."""
    from studio.serve.params import load_serve
    from studio.ui.app import EXAMPLES_DIR

    app.load(load_serve(EXAMPLES_DIR / "topspin_right.json"))
    assert app.worker.wait_idle(120) and app.last is not None and app.last.legal
    good = app.controls()
    net = app.last.metrics.net
    table = app.overlay.table.content
    assert f"| net: speed | {net['speed']:.2f} m/s |" in table and f"| reward F | {app.last.reward.total:+.3f} |" in table
    assert f"topspin {net['topspin']:.0f} rad/s" in table and app.last_efforts is not None and app.overlay.efforts.content == app.last_efforts.headline()
    assert app.pin_current() and app.pin is not None and app.pin.controls == good
    assert "/ghost/flight" in app.scene.ghost_nodes
    app.form.vz.value = 4.5  # break it: two changes of two controls, two undo steps
    assert app.worker.wait_idle(120)
    app.form.roll.value = 60.0
    assert app.worker.wait_idle(120) and app.last is not None and not app.last.legal
    table = app.overlay.table.content
    assert table.splitlines()[0] == "| | now | pinned A |" and "| verdict | **" in table and "| **LEGAL** |" in table
    assert f"{net['speed']:.2f} m/s" in table  # the pinned serve's numbers stay beside
    assert app.history.counts()[0] >= 2
    assert app.undo() and app.worker.wait_idle(120)
    assert app.form.roll.value == pytest.approx(math.degrees(good.serve.params.roll), abs=0.5) and app.form.vz.value == 4.5
    assert app.undo() and app.worker.wait_idle(120)
    assert app.controls() == good and app.last is not None and app.last.legal
    assert app.redo() and app.worker.wait_idle(120) and app.form.vz.value == 4.5
    assert app.restore_pin() and app.worker.wait_idle(120)
    assert app.controls() == good and app.last is not None and app.last.legal and app.last.serve.params == good.serve.params
    assert app.undo() and app.worker.wait_idle(120) and app.form.vz.value == 4.5  # the restore is an undo step itself
    app.clear_pin()
    assert app.pin is None and app.scene.ghost_nodes == () and "pinned A" not in app.overlay.table.content
    app.set_view("receiver")  # no browser connected: nothing to move, no error
    assert app.view == "receiver"
