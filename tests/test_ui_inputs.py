"""Server-side checks of the studio's controls and uploads (issue #18, studio.ui.checks and
studio.ui.wire): every value a control does not accept is refused with a message naming
the control and what it accepts, nothing is evaluated or started with it, and nothing
ends in a traceback.

Two ways in: the controls' change callbacks (a value set on the server, as viser does
after applying a client's message) and a raw WebSocket client speaking viser's protocol
(what any page or script on the machine can do), whose messages are judged before viser
applies them.
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest
import viser

from studio.serve.evaluate import EvaluationContext
from studio.storage.jsonfile import lone_surrogate
from studio.ui.app import EXAMPLES_DIR, StudioApp
from studio.ui.checks import Choice, InputGuard, Number, Text, shown, value_text


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(predicate: Callable[[], bool], timeout: float = 30.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def _start(folder: Path) -> tuple[viser.ViserServer, StudioApp]:
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    app = StudioApp(server, context=EvaluationContext.default(), serves_dir=folder / "serves", library_dir=folder / "lib", watch_open_requests=False)
    assert app.worker.wait_idle(300)
    return server, app


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[viser.ViserServer, StudioApp]]:
    from studio.serve.params import load_serve

    server, app = _start(tmp_path_factory.mktemp("inputs"))
    app.load(load_serve(EXAMPLES_DIR / "topspin_right.json"))
    assert app.worker.wait_idle(300)
    yield server, app
    app.worker.close()
    server.stop()


@pytest.fixture
def app(studio: tuple[viser.ViserServer, StudioApp]) -> StudioApp:
    assert studio[1].worker.wait_idle(120)
    return studio[1]


class RawClient:
    """A WebSocket client speaking viser's protocol without a browser (msgpack messages),
    as any page or script on the machine can; it reports a camera first, as a browser
    does, so that viser treats it as a connected client."""

    def __init__(self, port: int) -> None:
        from websockets.sync.client import connect

        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        self.frames = 0
        self.closed: BaseException | None = None
        threading.Thread(target=self._drain, daemon=True).start()
        self.send({
            "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [3.0, 0.0, 1.0], "fov": 1.0,
            "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 800, "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, 0.0, 1.0],
        })  # fmt: skip

    def _drain(self) -> None:
        try:
            while True:
                self.ws.recv()
                self.frames += 1
        except Exception as err:  # noqa: BLE001 - the connection ended: recorded
            self.closed = err

    def send(self, message: dict[str, Any]) -> None:
        self.ws.send(msgspec.msgpack.encode(message))

    def set(self, handle: Any, value: Any) -> None:
        """What a browser sends when the user changes a control."""
        self.send({"type": "GuiUpdateMessage", "uuid": handle._impl.uuid, "updates": {"value": value}})

    def close(self) -> None:
        self.ws.close()


@pytest.fixture
def raw(studio: tuple[viser.ViserServer, StudioApp]) -> Iterator[RawClient]:
    server, _ = studio
    client = RawClient(server.get_port())
    _wait(lambda: len(server.get_clients()) >= 1, 10, "the raw client to count as connected")
    yield client
    client.close()


@pytest.fixture
def no_traceback(caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]) -> Iterator[None]:
    """The test logs no traceback: neither a log record with exception info (viser's
    event loop, websockets) nor a printed traceback on stderr (thread pools)."""
    caplog.set_level(logging.WARNING)
    yield
    err = capfd.readouterr().err
    assert "Traceback" not in err, err
    tracebacks = [r.getMessage() for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]
    assert not tracebacks, tracebacks


def _refusal_after(app: StudioApp, count: int, timeout: float = 10.0) -> str:
    _wait(lambda: len(app.guard.refusals) > count, timeout, "the refusal")
    return app.guard.refusals[-1]


# -- the rules ------------------------------------------------------------------------


def test_rules_accept_their_range_and_refuse_everything_else() -> None:
    vx = Number("v_x", -10.0, 10.0, "m/s")
    assert vx.refusal(3.5) is None and vx.refusal(-10.0) is None and vx.refusal(10) is None
    for bad in (math.nan, math.inf, -math.inf, 1e300, -10.5, "3", None, True, [1.0], 10**400):
        why = vx.refusal(bad)
        assert why is not None and "[-10, 10] m/s" in why, (bad, why)
    workers = Number("workers", 1, 16, integer=True)
    assert workers.refusal(16) is None and workers.refusal(2.0) is None
    assert workers.refusal(24) == workers.refusal(2.5) == "must be a whole number in [1, 16]"
    side = Choice("Toss side", lambda: ("right", "left"))
    assert side.refusal("left") is None and side.refusal("up") == "must be one of 'right', 'left'"
    name = Text("Name", 200)
    assert name.refusal("my serve") is None
    assert "lone surrogate" in (name.refusal("a\ud800") or "") and "201 characters" in (name.refusal("x" * 201) or "")
    assert "control character" in (name.refusal("a\nb") or "")
    assert shown("a\ud800b") == "a\\ud800b" and lone_surrogate(value_text("\udcff")) is None


def test_every_control_of_the_studio_has_a_rule(app: StudioApp) -> None:
    inputs = app.server.gui._gui_input_handle_from_uuid
    missing = [type(inputs[u]).__name__ for u in set(inputs) - app.guard.registered()]
    assert not missing  # a control added without a rule would take any value a client sends


# -- the change callbacks: a value set on the server ------------------------------------

SLIDER_CASES = [
    ("vx", math.nan, "v_x", "[-10, 10] m/s"),
    ("vx", math.inf, "v_x", "[-10, 10] m/s"),
    ("vy", -math.inf, "v_y", "[-5, 5] m/s"),
    ("vz", 1e300, "v_z", "[-5, 5] m/s"),
    ("tau", -1.0, "tau", "[0.55, 1.05] s"),
    ("t_return", 1e6, "return", "[0.4, 1.2] s"),
    ("roll", 400.0, "roll", "[-180, 180] deg"),
    ("yaw", math.nan, "yaw", "[-90, 270] deg"),
    ("dpx", 0.5, "dp_x", "[-0.07, 0.07] m"),
    ("limit_jerk", 10.0, "jerk limit", "[0.25, 4]"),
    ("limit_speed", -1.0, "speed limit", "[0.25, 4]"),
]


@pytest.mark.parametrize(("attr", "value", "label", "allowed"), SLIDER_CASES, ids=[f"{c[0]}={c[1]}" for c in SLIDER_CASES])
def test_a_slider_value_outside_its_range_is_refused_and_the_last_valid_value_kept(app: StudioApp, attr: str, value: float, label: str, allowed: str, no_traceback: None) -> None:
    handle = getattr(app.form, attr)
    kept = handle.value
    ticket = app.worker.latest_ticket
    handle.value = value  # viser calls the control's callbacks as it does after a client's change
    text = app.message_md.content
    assert text.startswith(f"**Refused:** {label} = ") and f"must be a number in {allowed}" in text, text
    assert handle.value == kept  # the last valid value is back
    assert app.worker.latest_ticket == ticket  # nothing was evaluated


def test_unknown_options_and_bad_text_are_refused_with_the_allowed_ones(app: StudioApp, no_traceback: None) -> None:
    ticket = app.worker.latest_ticket
    cases = [
        (app.form.side, "up", "Toss side", "one of 'right', 'left'"),
        (app.form.task, "no_such_task", "Task", "one of 'aiming', 'topspin_velocity'"),
        (app.form.toss, "recorded 999", "Toss", "must be one of"),
        (app.form.name, "x" * 300, "Name", "text of at most 200 characters"),
        (app.form.name, "evil\ud800", "Name", "not valid Unicode"),
        (app.playback.speed, "100x", "speed", "one of '0.02x'"),
    ]
    for handle, value, label, allowed in cases:
        kept = handle.value
        handle._impl.value = value  # as viser stores a client's value (its options are not checked there)
        app.guard._changed(handle._impl.uuid, None)  # then calls the control's callback
        text = app.message_md.content
        assert text.startswith(f"**Refused:** {label} = ") and allowed in text, text
        assert handle.value == kept and lone_surrogate(text) is None
    assert app.worker.latest_ticket == ticket


# -- a raw client: messages judged before viser applies them -------------------------------

RAW_CASES = [
    ("form.vx", "abc", "v_x", "must be a number in [-10, 10] m/s"),
    ("form.vx", None, "v_x", "must be a number in [-10, 10] m/s"),
    ("form.vx", 1e300, "v_x", "must be a number in [-10, 10] m/s"),
    ("form.vx", -50.0, "v_x", "must be a number in [-10, 10] m/s"),
    ("form.t_return", 1e6, "return", "must be a number in [0.4, 1.2] s"),
    ("form.tau", math.nan, "tau", "must be a number in [0.55, 1.05] s"),
    ("form.side", "up", "Toss side", "must be one of 'right', 'left'"),
    ("form.task", "win_everything", "Task", "must be one of"),
    ("form.toss", "recorded 0", "Toss", "must be one of"),
    ("form.mujoco", "yes", "MuJoCo rollout", "must be true or false"),
    ("form.name", 12, "Name", "must be text of at most 200 characters"),
    ("files.serve_file", "../../etc/passwd", "Serve file", "must be one of"),
    ("files.serve_file", "example/../../../secret", "Serve file", "must be one of"),
    ("files.library_pick", "anything [abc]", "Library serve", "must be one of"),
    ("files.upload_button", {"name": "x.json"}, "Upload JSON", "set only by uploading a file"),
    ("jobs.opt_workers", 24, "workers", "must be a whole number in [1, 16]"),
    ("jobs.opt_iterations", math.nan, "iterations", "must be a whole number in [1, 100]"),
    ("jobs.opt_iterations", "ten", "iterations", "must be a whole number in [1, 100]"),
    ("jobs.opt_tosses", 10**12, "tosses per evaluation", "must be a whole number in [1, 20]"),
    ("jobs.opt_population", 2.5, "population", "must be a whole number in [2, 50]"),
    ("jobs.rob_evaluations", -12, "robust candidates", "must be a whole number in [12, 10000]"),
    ("jobs.opt_run", "../../runs/x", "run", "must be one of '(new run)'"),
    ("jobs.opt_progress", 50.0, "progress", "shown by the studio, not set by a browser"),
    ("playback.time", 1e9, "time", "must be a number in"),
    ("playback.ball_size", "x1000", "ball drawn", "must be one of"),
    ("overlay.view", "under the table", "View", "must be one of 'default', 'receiver'"),
    ("overlay.ab", "Delete A", "A/B", "must be one of 'Pin as A', 'Restore A', 'Clear A'"),
    ("match.match_robot", "won twice", "robot served", "must be one of 'won', 'ace', 'lost'"),
    ("match.match_opponent", "a\x00b", "opponent", "control character"),
]


def _handle(app: StudioApp, path: str) -> Any:
    obj: Any = app
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def test_a_raw_client_cannot_set_any_control_outside_its_rule(app: StudioApp, raw: RawClient, no_traceback: None) -> None:
    """Each value is refused before viser applies it: the message names the control and
    what it accepts, the control keeps its value, nothing is evaluated or started."""
    ticket = app.worker.latest_ticket
    runs_before = set(app.runs_dir.iterdir()) if app.runs_dir.exists() else set()
    for path, value, label, allowed in RAW_CASES:
        handle = _handle(app, path)
        kept = handle.value
        count = len(app.guard.refusals)
        raw.set(handle, value)
        text = _refusal_after(app, count)
        assert text.startswith(f"**Refused:** {label} = ") and allowed in text, (path, value, text)
        assert handle.value == kept, path
        assert app.message_md.content == text  # shown in the studio's message line
    assert app.worker.latest_ticket == ticket  # nothing evaluated
    assert not app.jobs.busy and (set(app.runs_dir.iterdir()) if app.runs_dir.exists() else set()) == runs_before  # nothing started
    # the range of a control cannot be widened by a client either
    count = len(app.guard.refusals)
    raw.send({"type": "GuiUpdateMessage", "uuid": app.form.vx._impl.uuid, "updates": {"max": 1e9, "value": 50.0}})
    assert "only a control's value can be set" in _refusal_after(app, count) and app.form.vx.max == 10.0
    # and the client is still served: a valid value is applied and evaluated
    new_vx = round(app.form.vx.value - 0.4, 2)
    raw.set(app.form.vx, new_vx)
    _wait(lambda: app.worker.latest_ticket > ticket and app.worker.wait_idle(0.1), 120, "the evaluation of a valid value")
    assert app.last is not None and app.last.serve.params.velocity[0] == pytest.approx(new_vx)
    assert raw.closed is None


def test_malformed_and_undecodable_messages_are_dropped_and_reported(studio: tuple[viser.ViserServer, StudioApp], app: StudioApp, raw: RawClient, no_traceback: None) -> None:
    server, _ = studio
    upload_uuid = app.files.upload_button._impl.uuid
    start = {"type": "FileTransferStartUpload", "source_component_uuid": upload_uuid, "transfer_uuid": "t1", "filename": "XYZ.json", "mime_type": "application/json", "part_count": 1, "size_bytes": 5}
    count = len(app.guard.refusals)
    raw.ws.send(msgspec.msgpack.encode(start).replace(b"XYZ", b"\xed\xa0\x80"))  # a lone surrogate, as a browser encodes it
    _wait(lambda: "not valid Unicode" in app.message_md.content, 10, "the refusal of the undecodable message")
    assert "lone surrogate" in app.message_md.content and lone_surrogate(app.message_md.content) is None
    raw.send({"type": "NoSuchMessage"})
    _wait(lambda: "malformed message" in app.message_md.content, 10, "the refusal of an unknown message")
    raw.send({"type": "GuiUpdateMessage", "uuid": [1, 2], "updates": {"value": 1}})
    _wait(lambda: "could not be handled" in app.message_md.content, 10, "the refusal of a malformed update")
    raw.send({**start, "transfer_uuid": "t2", "filename": "big.json", "size_bytes": 10**9})
    _wait(lambda: "Upload refused" in app.message_md.content and "big.json" in app.message_md.content, 10, "the refusal of a huge upload")
    assert "1000000 bytes" in app.message_md.content
    assert len(app.guard.refusals) >= count
    assert raw.closed is None  # the sender stays connected
    other = RawClient(server.get_port())  # and new clients are served
    try:
        _wait(lambda: other.frames > 0, 10, "a new client's first frames")
        assert other.closed is None
    finally:
        other.close()


def test_text_that_cannot_be_encoded_never_reaches_a_browser(studio: tuple[viser.ViserServer, StudioApp], app: StudioApp, no_traceback: None) -> None:
    """A lone surrogate in a GUI element would stop the updates of every browser (the
    messages cannot be encoded); the studio escapes it, and new clients are served."""
    server, _ = studio
    app.message("bad name \ud800")
    assert app.message_md.content == "bad name \\ud800"
    app.checks_md.content = "a status with \udcff inside"  # any element, set by any code: escaped on its way out
    client = RawClient(server.get_port())
    try:
        _wait(lambda: client.frames > 0, 10, "a new client's first frames")
        time.sleep(0.5)
        assert client.closed is None
    finally:
        client.close()
        app.checks_md.content = ""


# -- jobs: nothing is spawned with a refused value --------------------------------------


def test_optimize_and_make_robust_refuse_out_of_range_numbers_and_start_nothing(app: StudioApp, monkeypatch: pytest.MonkeyPatch, no_traceback: None) -> None:
    started: list[tuple[Any, ...]] = []

    def record(*args: Any) -> None:
        started.append(args)
        app.jobs._set_busy(False)

    monkeypatch.setattr(app.jobs, "_run_optimization", record)
    monkeypatch.setattr(app.jobs, "_run_robustify", record)
    jobs = app.jobs
    cases = [
        (jobs.opt_workers, 24, "workers", "[1, 16]"),
        (jobs.opt_tosses, 10**12, "tosses per evaluation", "[1, 20]"),
        (jobs.opt_iterations, math.nan, "iterations", "[1, 100]"),
        (jobs.opt_population, 0, "population", "[2, 50]"),
        (jobs.opt_seed, -1, "seed", "[0, 2147483647]"),
    ]
    for handle, value, label, allowed in cases:
        kept = handle.value
        handle._impl.value = value  # a value that got around every callback
        try:
            jobs.start_optimization()
        finally:
            handle._impl.value = kept
        assert not started, label
        text = jobs.opt_md.content
        assert text.startswith(f"**Cannot start:** {label} = ") and f"must be a whole number in {allowed}" in text, text
        assert app.message_md.content == text
    kept = jobs.rob_evaluations.value
    jobs.rob_evaluations._impl.value = 10**9
    try:
        jobs.start_robustify()
    finally:
        jobs.rob_evaluations._impl.value = kept
    assert not started and "robust candidates" in jobs.opt_md.content and "[12, 10000]" in jobs.opt_md.content
    # the handlers refuse 24 workers too, and a start then runs with the kept value
    kept = jobs.opt_workers.value
    jobs.opt_workers.value = 24
    assert "**Refused:** workers = `24`: must be a whole number in [1, 16]" in app.message_md.content and jobs.opt_workers.value == kept
    jobs.start_optimization()
    _wait(lambda: bool(started), 10, "the recorded start")
    (args,) = started
    assert args[1:6] == (jobs.opt_iterations.value, jobs.opt_population.value, jobs.opt_workers.value, jobs.opt_tosses.value, jobs.opt_seed.value)
    assert args[3] <= 16


# -- uploads --------------------------------------------------------------------------------

GOOD = json.loads((EXAMPLES_DIR / "topspin_left.json").read_text())


def _serve_bytes(**changes: Any) -> bytes:
    return json.dumps({**GOOD, **changes}).encode()


def _deep(depth: int) -> bytes:
    return ("[" * depth + "]" * depth).encode()


UPLOADS = [
    ("nan.json", _serve_bytes().replace(b'"tau": ', b'"tau": NaN, "x_was": '), "must be a finite number"),
    ("infinity.json", _serve_bytes().replace(b'"yaw": ', b'"yaw": Infinity, "x_was": '), "must be a finite number"),
    ("overflow.json", _serve_bytes().replace(b'"roll": ', b'"roll": 1e400, "x_was": '), "must be a finite number"),
    ("huge-int.json", _serve_bytes(x_count=10**30), "integer out of range"),
    ("huge-int-digits.json", b'{"x": ' + b"9" * 5000 + b"}", "digits"),
    ("deep.json", _deep(100_000), "nested 100000 levels deep"),
    ("latin1.json", json.dumps({**GOOD, "notes": "caf\u00e9"}, ensure_ascii=False).encode("latin-1"), "not UTF-8"),
    ("utf16.json", _serve_bytes().decode().encode("utf-16"), "not UTF-8"),
    ("empty.json", b"", "empty (0 bytes)"),
    ("blank.json", b"  \n", "not valid JSON"),
    ("truncated.json", _serve_bytes()[:40], "not valid JSON"),
    ("surrogate.json", _serve_bytes().replace(b'"notes": ', b'"notes": "\\ud800", "x_was": '), "not valid Unicode"),
    ("array.json", b"[1, 2, 3]", "must hold a JSON object"),
    ("side.json", _serve_bytes(side="up"), "field 'side'"),
    ("range.json", json.dumps({**GOOD, "params": {**GOOD["params"], "t_return": 1e6}}).encode(), "t_return"),
    ("big.json", b'{"notes": "' + b"x" * 1_000_001 + b'"}', "more than the 1000000 bytes"),
    ("\ud800.json", _serve_bytes(), "file name is not valid Unicode"),
]


class Uploaded:
    def __init__(self, name: str, content: bytes) -> None:
        self.name, self.content = name, content


@pytest.mark.parametrize(("name", "content", "problem"), UPLOADS, ids=[shown(u[0]) for u in UPLOADS])
def test_a_corrupt_upload_is_refused_naming_the_file_and_the_problem(app: StudioApp, name: str, content: bytes, problem: str, no_traceback: None) -> None:
    ticket = app.worker.latest_ticket
    before = app.controls()
    assert not app.files.upload(Uploaded(name, content))  # what the upload button hands over
    text = app.message_md.content
    assert text.startswith("**Upload rejected:** ") and shown(name) in text and problem in text, text
    assert lone_surrogate(text) is None
    assert app.worker.latest_ticket == ticket and app.controls() == before  # nothing loaded or evaluated


def test_a_valid_upload_still_loads(app: StudioApp) -> None:
    assert app.files.upload(Uploaded("left.json", _serve_bytes(name="uploaded left")))
    assert "Loaded upload `left.json`" in app.message_md.content
    assert app.worker.wait_idle(120) and app.last is not None and app.last.serve.name == "uploaded left"


# -- serve files and open requests ------------------------------------------------------------


def test_a_studio_starts_past_corrupt_seed_files_and_reads_files_only_inside_their_folder(tmp_path: Path, no_traceback: None) -> None:
    serves = tmp_path / "serves"
    serves.mkdir()
    (serves / "a_nan.json").write_bytes(_serve_bytes().replace(b'"tau": ', b'"tau": NaN, "x_was": '))
    (serves / "b_deep.json").write_bytes(_deep(5000))
    (serves / os.fsdecode(b"c_\xff.json")).write_bytes(_serve_bytes())  # a name that is not valid Unicode
    secret = tmp_path / "secret.json"
    secret.write_bytes(_serve_bytes(name="secret serve"))
    (serves / "d_link.json").symlink_to(secret)  # points out of the folder
    (serves / "e_good.json").write_bytes(_serve_bytes(name="good seed"))
    server, app = _start(tmp_path)
    try:
        assert app.last is not None and app.last.serve.name == "good seed"  # the first readable seed
        text = app.message_md.content
        assert "Skipped unreadable serve files" in text and "a_nan.json" in text and "b_deep.json" in text and "d_link.json" in text
        assert "resolves outside the folder" in text and "not valid Unicode" in text and lone_surrogate(text) is None
        options = app.files.serve_file.options
        assert "e_good" in options and not any(lone_surrogate(o) is not None for o in options)
        app.files.serve_file.value = "d_link"
        assert "Cannot load d_link" in app.message_md.content and "resolves outside the folder" in app.message_md.content
        assert app.controls().serve.name == "good seed"
        assert all(s.name != "secret serve" for s in app.jobs.seeds_for("left"))  # seeds are read inside the folder too
        app.files.serve_file.value = "a_nan"
        assert "Cannot load a_nan" in app.message_md.content and "must be a finite number" in app.message_md.content
    finally:
        app.worker.close()
        server.stop()


def test_the_open_request_watcher_survives_any_request_file(app: StudioApp, no_traceback: None) -> None:
    from studio.library.store import OPEN_REQUEST_NAME, ServeLibrary, request_open

    if not (app.library_dir / "index.json").exists() or not ServeLibrary(app.library_dir).entries():
        app.files.export()
    target = ServeLibrary(app.library_dir).entries()[-1]
    request = app.library_dir / OPEN_REQUEST_NAME
    thread = app.files.watch_open_requests(period=0.05)
    try:
        bad = {
            "nested": _deep(100_000),
            "binary": b"\xff\xfe\x00garbage",
            "surrogate": b'{"schema": "serve-studio/open-request@1", "id": "\\ud800", "nonce": "n"}',
            "huge": b"[" + b"1," * 3000 + b"1]",
            "wrong id": json.dumps({"schema": "serve-studio/open-request@1", "id": "../../x", "nonce": "n2"}).encode(),
        }
        for what, content in bad.items():
            request.write_bytes(content)
            _wait(lambda: "Open request ignored" in app.message_md.content and OPEN_REQUEST_NAME in app.message_md.content, 10, f"the {what} request reported")
            assert thread.is_alive(), what
            app.message("")
        request.unlink()
        request.mkdir()  # not even a file
        _wait(lambda: "Open request ignored" in app.message_md.content, 10, "the folder reported")
        request.rmdir()
        if hasattr(os, "mkfifo"):
            os.mkfifo(request)  # a pipe would block a plain read forever
            _wait(lambda: "Open request ignored" in app.message_md.content and "regular file" in app.message_md.content, 10, "the pipe reported")
            request.unlink()
        assert thread.is_alive()
        request_open(app.library_dir, target.id)  # and a good request after all that is acted on
        _wait(lambda: "Opened library serve" in app.message_md.content, 10, "the good request")
    finally:
        app.files.stop_watching()
        thread.join(5)
        assert app.worker.wait_idle(120)


# -- the guard on its own ------------------------------------------------------------------------


def test_the_guard_reports_callback_errors_instead_of_raising() -> None:
    shown_messages: list[str] = []
    guard = InputGuard(shown_messages.append)

    class Handle:
        def __init__(self) -> None:
            self.value = 1.0
            self.callbacks: list[Any] = []
            self._impl = type("Impl", (), {"uuid": "u1", "is_button": False})()

        def on_update(self, cb: Any) -> None:
            self.callbacks.append(cb)

    handle = Handle()
    guard.add(handle, Number("gain", 0.0, 2.0))
    guard.on_update(handle, lambda _event: 1 / 0)
    handle.value = 1.5
    handle.callbacks[0](None)
    assert shown_messages[-1].startswith("**gain failed:** ZeroDivisionError")
    handle.value = 7.0
    handle.callbacks[0](None)
    assert shown_messages[-1] == "**Refused:** gain = `7`: must be a number in [0, 2]; kept `1.5`." and handle.value == 1.5
