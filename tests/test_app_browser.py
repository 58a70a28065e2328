"""The studio in a real browser (Debian chromium via playwright, headless).

Screenshots of the states are saved to ``test-artifacts/`` (git-ignored; each test prints
the paths it wrote).
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytestmark = pytest.mark.browser

ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts"
CHROMIUM = "/usr/bin/chromium"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(predicate, timeout: float = 60.0, what: str = "condition") -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[object, str, Path]]:
    import viser

    from studio.serve.evaluate import EvaluationContext
    from studio.ui.app import StudioApp

    port = _free_port()
    serves = tmp_path_factory.mktemp("serves")
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = StudioApp(server, context=EvaluationContext.default(), serves_dir=serves, library_dir=serves / "library")
    _wait(lambda: app.last is not None, 120, "first evaluation")
    yield app, f"http://127.0.0.1:{port}", serves
    app.worker.close()
    server.stop()


@pytest.fixture(scope="module")
def page(studio: tuple[object, str, Path]) -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    if not os.path.exists(CHROMIUM):
        pytest.fail(f"{CHROMIUM} is missing: ./dev test installs Debian's chromium (apt-get install chromium)")
    ARTIFACTS.mkdir(exist_ok=True)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update", "--disable-sync", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"],
        )
        pg = browser.new_page(viewport={"width": 1400, "height": 900})
        pg.goto(studio[1])
        pg.get_by_text("Racket velocity [m/s]").wait_for(timeout=60_000)
        yield pg
        browser.close()


def _shot(page, name: str, **kw) -> Path:  # type: ignore[no-untyped-def]
    """Save a screenshot as a test artifact and print where."""
    path = ARTIFACTS / name
    page.screenshot(path=str(path), **kw)
    print(f"screenshot: {path}")
    return path


def _close_toasts(page) -> None:  # type: ignore[no-untyped-def]
    """Close notifications (headless chromium gets "Software WebGL rendering detected"),
    which would cover the overlay's top left corner."""
    buttons = page.locator(".mantine-Notification-closeButton")
    for i in range(buttons.count()):
        if buttons.nth(i).is_visible():
            buttons.nth(i).click()


OVERLAY_LABELS = ("", "verdict", "first failing check", "reward F", "net: speed", "net: top/back", "net: side", "2nd bounce: top/back", "2nd bounce: side", "net clearance", "joint efforts")


def _overlay(page) -> dict[str, list[str]]:  # type: ignore[no-untyped-def]
    """The overlay table as the page shows it: {row label: [now, pinned A?]}."""
    rows = page.eval_on_selector_all("tr", "rows => rows.map(r => Array.from(r.cells).map(c => c.innerText.trim()))")
    return {r[0]: r[1:] for r in rows if r and r[0] in OVERLAY_LABELS}


def _number(text: str) -> float:
    """The first number in ``text``; negative for "backspin N"."""
    import re

    value = float(re.search(r"[-+]?\d+(?:\.\d+)?", text).group())  # type: ignore[union-attr]
    return -value if text.startswith("backspin") else value


def _example(app, name: str = "topspin_right") -> object:  # type: ignore[no-untyped-def]
    """Load a shipped example (paused), wait for its evaluation, return it."""
    from studio.serve.params import load_serve

    if app.playback.playing:
        app.playback.toggle()
    app.load(load_serve(Path(__file__).resolve().parent.parent / "examples" / "serves" / f"{name}.json"))
    _wait(lambda: app.worker.wait_idle(0.1) and app.last is not None and app.last.serve.name == name.replace("_", " "), 60, f"the example {name}")
    return app.last


def _set_number(page, label: str, value: float) -> None:  # type: ignore[no-untyped-def]
    """Type into the number field of the slider labelled ``label``."""
    row = page.get_by_text(label, exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]")
    box = row.locator("input").last
    box.fill(str(value))
    box.press("Enter")


def test_slider_change_replans_and_updates_checklist(studio, page) -> None:  # type: ignore[no-untyped-def]
    app, _, _ = studio
    _close_toasts(page)
    _shot(page, "studio_initial.png")
    before = app.last
    assert before.legal, before.reason  # the studio opens on a legal example serve
    page.get_by_role("tab", name="Checks").click()
    page.get_by_text("LEGAL").first.wait_for(timeout=30_000)
    page.get_by_role("tab", name="Serve", exact=True).click()
    _set_number(page, "v_x", round(before.serve.params.velocity[0] - 0.6, 2))
    _wait(lambda: app.last is not before and app.last.serve.params != before.serve.params, 60, "re-plan after slider change")
    after = app.last
    assert after.serve.params.velocity[0] == pytest.approx(before.serve.params.velocity[0] - 0.6, abs=0.051)
    assert after.ball is not None and before.ball is not None
    assert not (len(after.ball.p) == len(before.ball.p) and (after.ball.p == before.ball.p).all())  # the path moved
    _shot(page, "studio_after_slider.png")


def test_illegal_serve_is_flagged(studio, page) -> None:  # type: ignore[no-untyped-def]
    app, _, _ = studio
    page.get_by_role("tab", name="Serve", exact=True).click()
    _set_number(page, "v_z", 4.5)  # racket flying upwards: the ball never bounces on the server's court
    _set_number(page, "roll", 60.0)
    _wait(lambda: app.last is not None and app.last.serve.params.velocity[2] == pytest.approx(4.5), 60, "evaluation of the illegal serve")
    assert not app.last.legal
    page.get_by_role("tab", name="Checks").click()
    page.get_by_text("ILLEGAL").or_(page.get_by_text("NO PLAN")).or_(page.get_by_text("COLLISION")).first.wait_for(timeout=30_000)
    page.get_by_text("FAIL").first.wait_for(timeout=30_000)
    _shot(page, "studio_illegal.png")


def test_save_seed_writes_a_valid_serve_file(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.serve.params import load_serve

    app, _, serves = studio
    page.get_by_role("tab", name="Serve", exact=True).click()
    page.get_by_role("button", name="Save as seed").click()
    _wait(lambda: any(serves.glob("*.json")), 30, "seed file")
    saved = load_serve(next(serves.glob("*.json")))
    assert saved.params == app.controls().serve.params


def test_export_puts_the_serve_in_the_library(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.library.store import ServeLibrary

    app, _, serves = studio
    _example(app)  # within the effort limits (the studio's first serve, backspin heavy right, is refused)
    page.get_by_role("tab", name="Serve", exact=True).click()
    page.get_by_role("button", name="Export to library").click()
    library = ServeLibrary(serves / "library")
    _wait(lambda: (serves / "library" / "index.json").exists() and len(library.entries()) == 1, 30, "library export")
    entry = library.entries()[0]
    assert entry.serve.params == app.last.serve.params
    assert entry.arrays()["u"].shape[1] == 8
    page.get_by_text("Exported").first.wait_for(timeout=10_000)
    _shot(page, "studio_exported.png")


def test_dashboard_open_in_studio_loads_the_serve_in_the_page(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.ui.dashboard import LibraryDashboard

    app, url, serves = studio
    page.get_by_role("tab", name="Serve", exact=True).click()
    if not (serves / "library" / "index.json").exists():
        page.get_by_role("button", name="Export to library").click()
        _wait(lambda: (serves / "library" / "index.json").exists(), 30, "library export")
    dash = LibraryDashboard(serves / "library", studio_url=url)
    entry = dash.entry(dash.selected_id)
    assert entry is not None
    _set_number(page, "v_y", round(entry.serve.params.velocity[1] + 0.8, 2))  # move away from the library serve
    _wait(lambda: app.last is not None and app.last.serve.params.velocity[1] == pytest.approx(entry.serve.params.velocity[1] + 0.8, abs=0.051), 60, "slider change")
    assert dash.open_in_studio()  # what the dashboard's "Open in studio" button does on the server side
    page.get_by_text("Opened library serve").first.wait_for(timeout=30_000)  # the studio's watcher loaded it
    _wait(lambda: app.last is not None and app.last.serve.params.velocity[1] == pytest.approx(entry.serve.params.velocity[1], abs=0.051), 60, "re-plan of the opened serve")
    _shot(page, "studio_opened_from_dashboard.png")


def test_match_tab_serves_and_records_a_point(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.library.match import MATCH_LOG, load_points
    from studio.library.store import ServeLibrary
    from studio.serve.evaluate import evaluate_serve
    from studio.serve.params import load_serve

    app, _, serves = studio
    example = Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json"
    ServeLibrary(serves / "library").add(evaluate_serve(load_serve(example), app.context))  # a legal serve to select
    page.get_by_role("tab", name="Match").click()
    page.get_by_role("button", name="Next serve").click()
    _wait(lambda: app.match.current is not None, 30, "selected serve")
    page.get_by_role("button", name="ace").click()
    log = serves / "library" / MATCH_LOG
    _wait(lambda: log.exists() and len(load_points(log)) == 1, 30, "recorded point")
    (point,) = load_points(log)
    assert point.server == "robot" and point.serve == app.match.current and point.ace and point.winner == "robot"
    page.get_by_text("serving: robot won 100.0 % of 1").first.wait_for(timeout=10_000)
    _shot(page, "studio_match.png")


def test_mujoco_rollout_checkbox_evaluates_with_the_rollout(studio, page) -> None:  # type: ignore[no-untyped-def]
    """Ticking "MuJoCo rollout" re-evaluates the serve with the MuJoCo rollout and shows its
    verdict (it used to fail with "rollout: X covers ... samples, t_end = ... needs ...")."""
    from studio.serve.params import load_serve

    app, _, _ = studio
    example = Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json"
    if app.playback.playing:  # a match serve left playing: the software-rendered page would crawl
        app.playback.toggle()
    app.load(load_serve(example))
    _wait(lambda: app.worker.wait_idle(0.1) and app.last is not None and app.last.serve.name == "topspin right", 60, "the example serve")
    page.get_by_role("tab", name="Serve", exact=True).click()
    box = page.get_by_text("MuJoCo rollout", exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]").locator("input[type=checkbox]")
    box.check(force=True)  # Mantine's input sits under its styled box
    try:
        _wait(lambda: app.form.mujoco.value is True, 30, "the checkbox to reach the studio")
        _wait(lambda: app.worker.wait_idle(0.1) and app.last is not None and app.last.rollout is not None or "Evaluation failed" in app.status_md.content, 120, "MuJoCo evaluation")
        assert "Evaluation failed" not in app.status_md.content, app.status_md.content
        ev = app.last
        assert ev.legal, ev.reason
        assert ev.rollout.end_reason == "floor" and ev.rollout.t[-1] > ev.t[-1]  # the ball followed past the motion's end
        page.get_by_role("tab", name="Checks").click()
        page.get_by_text("LEGAL").first.wait_for(timeout=30_000)
        assert page.get_by_text("Evaluation failed").count() == 0
        page.get_by_role("tab", name="Metrics").click()
        page.get_by_text("time: mujoco").first.wait_for(timeout=30_000)
        _shot(page, "studio_mujoco_rollout.png")
    finally:
        page.get_by_role("tab", name="Serve", exact=True).click()
        box.uncheck(force=True)
        _wait(lambda: app.form.mujoco.value is False and app.worker.wait_idle(0.1) and app.last is not None and app.last.rollout is None, 120, "back to the analytic evaluation")


def test_a_slider_change_shows_the_new_verdict_and_net_spin_in_the_overlay(studio, page) -> None:  # type: ignore[no-untyped-def]
    """Move v_x on the Serve tab: the overlay over the 3D view shows the re-planned serve's
    verdict, reward, net speed and spins, second-bounce spins and clearance, equal to the
    evaluation's (to the digits shown), without leaving the Serve tab."""
    app, _, _ = studio
    before = _example(app)
    page.get_by_role("tab", name="Serve", exact=True).click()
    _close_toasts(page)
    new_vx = round(before.serve.params.velocity[0] - 0.3, 2)
    _set_number(page, "v_x", new_vx)
    _wait(lambda: app.worker.wait_idle(0.1) and app.last is not before and app.last.serve.params.velocity[0] == pytest.approx(new_vx, abs=0.026), 60, "re-plan")
    ev = app.last
    m = ev.metrics
    _wait(lambda: _overlay(page).get("net: speed") == [f"{m.net['speed']:.2f} m/s"], 30, "the overlay to show the new evaluation")
    shown = _overlay(page)
    assert shown[""] == ["now"]
    assert shown["verdict"] == [{"legal": "LEGAL", "illegal": "ILLEGAL"}.get(ev.status, shown["verdict"][0])]
    assert _number(shown["reward F"][0]) == pytest.approx(ev.reward.total, abs=0.0005)
    assert _number(shown["net: speed"][0]) == pytest.approx(m.net["speed"], abs=0.005)
    assert _number(shown["net: top/back"][0]) == pytest.approx(m.net["topspin"], abs=0.5)
    assert _number(shown["net: side"][0]) == pytest.approx(m.net["sidespin"], abs=0.5)
    assert _number(shown["2nd bounce: top/back"][0]) == pytest.approx(m.second_bounce["topspin"], abs=0.5)
    assert _number(shown["2nd bounce: side"][0]) == pytest.approx(m.second_bounce["sidespin"], abs=0.5)
    assert _number(shown["net clearance"][0]) == pytest.approx(100 * m.net_clearance, abs=0.05)
    assert shown["joint efforts"][0].startswith("within" if app.last_efforts.within else "EXCEED")
    verdict_line = page.get_by_text(app.last_efforts.headline().split("**")[1])  # the joint-effort verdict line
    assert any(verdict_line.nth(i).is_visible() for i in range(verdict_line.count()))  # in the overlay (the Checks tab's is hidden)
    assert page.get_by_role("tab", name="Serve", exact=True).get_attribute("aria-selected") == "true"  # no tab change needed
    assert page.get_by_role("tab", name="At a glance").is_visible()
    _shot(page, "studio_overlay_after_slider.png")


def test_receiver_view_and_the_ball_turning_in_slow_motion(studio, page) -> None:  # type: ignore[no-untyped-def]
    """"receiver" puts the browser's camera at the receiver's eyes (reported back by the
    page); "Slow motion from contact" plays at 0.02x and the ball (with its seam) turns at
    the simulated spin."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from studio.ui.camera import RECEIVER_EYE

    app, _, _ = studio
    _example(app)
    _close_toasts(page)
    (client,) = app.server.get_clients().values()
    seen: list[tuple[float, ...]] = []
    client.camera.on_update(lambda cam: seen.append(tuple(float(x) for x in cam.position)))
    page.get_by_role("button", name="receiver", exact=True).click()
    _wait(lambda: any(np.allclose(p, RECEIVER_EYE, atol=0.01) for p in seen), 30, "the page's camera at the receiver's eyes")
    assert app.view == "receiver"
    _shot(page, "studio_receiver_view.png")
    page.get_by_role("button", name="Slow motion from contact").click()
    _wait(lambda: app.playback.playing, 10, "slow motion to start")
    assert app.playback.speed.value == "0.02x"
    pb = app.scene.frame.playback
    samples = []
    for _ in range(6):
        time.sleep(0.3)
        with app._lock:
            samples.append((app.playback.clock, np.array(app.scene.ball.wxyz)))
    page.wait_for_timeout(300)
    _shot(page, "studio_receiver_slow_motion.png")
    page.get_by_role("button", name="Pause").click()
    _wait(lambda: not app.playback.playing, 10, "pause")
    clocks = [c for c, _ in samples]
    assert clocks[0] >= pb.contact_t - 0.031 and 0.0 < clocks[-1] - clocks[0] < 0.1  # 1.5 s of wall time at 0.02x: ~30 ms
    for clock, wxyz in samples:  # the drawn ball turns as the serve's integrated spin says
        np.testing.assert_allclose(wxyz, pb.ball_wxyz[pb.index(clock)], atol=1e-6)
    rot = lambda q: Rotation.from_quat(np.asarray(q)[[1, 2, 3, 0]])
    turned = (rot(samples[-1][1]) * rot(samples[0][1]).inv()).magnitude()
    assert turned > 0.5, turned  # > 30 degrees in 1.5 s of slow motion: visible
    # artifacts to look at: the ball in flight from the receiver's eyes, and a close-up of its seam
    from studio.ui.camera import CameraView, apply_camera

    t_flight = pb.contact_t + 0.2
    app.playback.seek(t_flight)
    page.wait_for_timeout(1000)
    _shot(page, "studio_receiver_ball_in_flight.png")
    p = pb.ball[pb.index(t_flight)]
    apply_camera(client, CameraView("close-up", tuple(p + np.array([0.25, -0.2, 0.08])), tuple(p)))
    page.wait_for_timeout(1500)
    _shot(page, "studio_ball_seam_closeup.png", clip={"x": 450, "y": 200, "width": 500, "height": 450})
    page.get_by_role("button", name="default", exact=True).click()


def test_break_a_serve_see_the_pinned_one_beside_it_and_undo(studio, page) -> None:  # type: ignore[no-untyped-def]
    """Pin the legal serve, break it with v_z: the overlay shows the broken serve's verdict
    and first failing check beside the pinned serve's numbers, the pinned path is drawn as
    a dashed ghost; Undo puts the previous v_z back (in the page too) and the serve is legal again."""
    app, _, _ = studio
    good_ev = _example(app)
    good = app.controls()
    page.get_by_role("tab", name="Serve", exact=True).click()
    _close_toasts(page)
    page.get_by_role("button", name="Pin as A").click()
    _wait(lambda: app.pin is not None and "/ghost/flight" in app.scene.ghost_nodes, 20, "the pin and its ghost")  # drawn after the pin
    assert app.pin.controls.serve == good.serve
    _set_number(page, "v_z", 4.5)
    _wait(lambda: app.worker.wait_idle(0.1) and app.last is not None and app.last.serve.params.velocity[2] == pytest.approx(4.5), 60, "the broken serve")
    broken = app.last
    assert not broken.legal
    _wait(lambda: _overlay(page).get("") == ["now", "pinned A"] and _overlay(page)["verdict"][0] != "LEGAL", 30, "the overlay with the pinned column")
    shown = _overlay(page)
    assert shown["verdict"] == [{"illegal": "ILLEGAL", "planner_failed": "NO PLAN", "collision": "COLLISION"}[broken.status], "LEGAL"]
    failure = broken.legality.first_failure if broken.legality is not None else None
    assert shown["first failing check"][1] == "none" and shown["first failing check"][0].startswith(failure.label if failure is not None else "")
    assert shown["net: speed"][1] == f"{good_ev.metrics.net['speed']:.2f} m/s"  # the pinned serve's numbers beside
    assert _number(shown["reward F"][1]) == pytest.approx(good_ev.reward.total, abs=0.0005)
    _shot(page, "studio_ab_broken_beside_pinned.png")
    page.get_by_role("button", name="Undo", exact=True).click()
    _wait(lambda: app.worker.wait_idle(0.1) and app.controls() == good and app.last is not None and app.last.serve.params == good.serve.params, 60, "undo")
    assert app.last.legal
    vz_box = page.get_by_text("v_z", exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]").locator("input").last
    _wait(lambda: float(vz_box.input_value()) == pytest.approx(good.serve.params.velocity[2], abs=0.026), 10, "the page's v_z back")
    _wait(lambda: _overlay(page).get("verdict") == ["LEGAL", "LEGAL"], 30, "the overlay to show the legal serve again")
    _shot(page, "studio_after_undo.png")
    page.get_by_role("button", name="Clear A").click()
    _wait(lambda: app.pin is None and app.scene.ghost_nodes == (), 10, "the pin cleared")


STORM_SLIDERS = {"v_x": (-10.0, 10.0), "v_y": (-5.0, 5.0), "v_z": (-5.0, 5.0), "roll": (-180.0, 180.0), "yaw": (-90.0, 270.0), "tau [s]": (0.55, 1.05), "return [s]": (0.4, 1.2)}
"""The sliders the five pages move (label -> range); the contact offset and joint-limit folders start closed."""

CORRUPT_UPLOAD_JS = """() => {
  const input = document.querySelector('input[type=file]');
  const file = new File([new TextEncoder().encode('{"name": "x", "params": {"tau": NaN}}')], "\\ud800 serve.json", {type: "application/json"});
  const dt = new DataTransfer();
  dt.items.add(file);
  input.files = dt.files;
  input.dispatchEvent(new Event("change", {bubbles: true}));
  return file.name;
}"""
"""Uploads, from the page, a corrupt serve file (NaN) named with a lone surrogate; a
browser's File turns the surrogate into U+FFFD, so the name arrives as valid text."""

TYPE_JS = """(box, value) => {
  const setter = Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, "value").set;
  setter.call(box, String(value));
  box.dispatchEvent(new Event("input", {bubbles: true}));
}"""
"""Types ``value`` into an input as a user does (React sees an input event)."""

STORM_JS = """([boxes, ranges, seconds, pastEnd]) => {
  const setter = Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, "value").set;
  window.__storm = new Promise(resolve => {
    let moves = 0, past = 0;
    const t0 = performance.now();
    const timer = setInterval(() => {
      if (performance.now() - t0 > 1000 * seconds) { clearInterval(timer); resolve([moves, past]); return; }
      const i = Math.floor(Math.random() * boxes.length);
      const [lo, hi] = ranges[i];
      let value = (lo + Math.random() * (hi - lo)).toFixed(2);
      if (Math.random() < pastEnd) { value = String(hi + 50); past++; }
      setter.call(boxes[i], value);
      boxes[i].dispatchEvent(new Event("input", {bubbles: true}));
      moves++;
    }, 60);
  });
  return true;
}"""
"""Starts, in a page, ``seconds`` of slider changes every 60 ms (a random slider of
``boxes``, a random value in its range, a share ``pastEnd`` of them 50 past its end), as a
user typing into the number boxes; ``window.__storm`` resolves to [changes, past the end].
Each page runs its own, so the five pages change sliders at the same time."""


class _RawUploader:
    """A WebSocket client speaking viser's protocol (as any script on the machine can),
    which uploads a file whose name holds a lone surrogate: a browser's JavaScript sends
    such text as bytes that are not UTF-8 (the issue's upload)."""

    def __init__(self, port: int, upload_uuid: str) -> None:
        import threading

        import viser
        from websockets.sync.client import connect

        self.uuid = upload_uuid
        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        self.closed: BaseException | None = None
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self) -> None:
        try:
            while True:
                self.ws.recv()
        except Exception as err:  # noqa: BLE001 - recorded: the connection ended
            self.closed = err

    def upload(self, name: str, content: bytes) -> None:
        import msgspec

        mark = "@" * len(name.encode("utf-8", "surrogatepass"))
        start = {"type": "FileTransferStartUpload", "source_component_uuid": self.uuid, "transfer_uuid": "raw-1", "filename": mark,
                 "mime_type": "application/json", "part_count": 1, "size_bytes": len(content)}  # fmt: skip
        self.ws.send(msgspec.msgpack.encode(start).replace(mark.encode(), name.encode("utf-8", "surrogatepass")))
        self.ws.send(msgspec.msgpack.encode({"type": "FileTransferPart", "source_component_uuid": self.uuid, "transfer_uuid": "raw-1", "part_index": 0, "content": content}))

    def close(self) -> None:
        self.ws.close()


def _number_box(page, label: str):  # type: ignore[no-untyped-def]
    """The number box beside the slider labelled ``label`` (an element handle)."""
    row = page.get_by_text(label, exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]")
    return row.locator("input").last.element_handle()


def test_five_browsers_moving_sliders_and_a_surrogate_named_upload_leave_every_client_answered(studio, page, caplog, capfd) -> None:  # type: ignore[no-untyped-def]
    """Five pages move sliders at once for ~25 s (a few values past a slider's end among
    them) while one uploads a corrupt file named with a lone surrogate: the studio keeps
    answering every page (each shows the verdict of a last change made from each page in
    turn), refuses the upload visibly, and logs no traceback."""
    import logging

    from studio.storage.jsonfile import lone_surrogate

    app, url, _ = studio
    caplog.set_level(logging.WARNING)
    capfd.readouterr()  # earlier output is not this test's
    _example(app)
    browser = page.context.browser
    contexts = [browser.new_context(viewport={"width": 1100, "height": 760}) for _ in range(4)]
    try:
        pages = [page] + [c.new_page() for c in contexts]
        for pg in pages[1:]:
            pg.goto(url)
        for pg in pages[1:]:  # software WebGL on a loaded machine: a page may take a while
            pg.get_by_text("Racket velocity [m/s]").wait_for(timeout=240_000)
        for pg in pages:
            _close_toasts(pg)
            pg.get_by_role("tab", name="Serve", exact=True).click()
        _wait(lambda: len(app.server.get_clients()) >= 5, 60, "five connected pages")
        name_box = pages[3].get_by_text("Name", exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]").locator("input").last.element_handle()
        raw = _RawUploader(app.server.get_port(), app.files.upload_button._impl.uuid)
        seen = len(app.messages)
        ranges = [list(r) for r in STORM_SLIDERS.values()]
        start = time.monotonic()
        for pg in pages:
            assert pg.evaluate(STORM_JS, [[_number_box(pg, label) for label in STORM_SLIDERS], ranges, 25.0, 0.02])
        time.sleep(8.0)
        assert pages[2].evaluate(CORRUPT_UPLOAD_JS) == "\ufffd serve.json"  # corrupt, from a browser
        name_box.evaluate(TYPE_JS, "evil \ud800")  # a lone surrogate typed into a text field
        raw.upload("\ud800 serve.json", b'{"tau": NaN}')  # the upload: the name's surrogate on the wire
        counts = [pg.evaluate("() => window.__storm") for pg in pages]  # each page's changes, once its storm is over
        moves, past_end = sum(c[0] for c in counts), sum(c[1] for c in counts)
        notes = [f"{moves} slider changes ({past_end} past a slider's end) from 5 pages at once in {time.monotonic() - start:.0f} s: {counts}"]
        assert all(c[0] > 0 for c in counts)
        refused = lambda what: [m for m in app.messages[seen:] if what in m]  # noqa: E731
        _wait(lambda: bool(refused("Upload rejected")), 60, "the refusal of the browser's corrupt upload")
        _wait(lambda: bool(refused("not valid Unicode")), 60, "the refusal of the surrogate-named upload")
        notes += [f"browser upload: {refused('Upload rejected')[0]}", f"raw upload: {refused('not valid Unicode')[0]}", f"name field: {app.form.name.value!r}"]
        assert "\ufffd serve.json" in refused("Upload rejected")[0] and "must be a finite number" in refused("Upload rejected")[0]
        assert lone_surrogate(app.form.name.value) is None  # the surrogate typed in the page never became the serve's name
        assert raw.closed is None  # the sender of the undecodable upload is still connected
        raw.close()
        if past_end:
            assert any(m.startswith("**Refused:** ") and "must be a number in [" in m for m in app.messages[seen:])
        assert app.last is not None
        # every page is still answered: a change from each in turn, its verdict on all five
        base = round(app.form.vx.value, 1)
        for i, pg in enumerate(pages):
            vx = round(base + (0.3 if base < 0 else -0.3) * (i + 1), 2)
            _set_number(pg, "v_x", vx)
            _wait(lambda vx=vx: app.worker.wait_idle(0.1) and app.last is not None and app.last.serve.params.velocity[0] == pytest.approx(vx, abs=0.026), 120, f"page {i}'s change evaluated")
            ev = app.last
            badge = {"legal": "LEGAL", "illegal": "ILLEGAL", "planner_failed": "NO PLAN", "collision": "COLLISION"}[ev.status]
            for j, other in enumerate(pages):
                _wait(lambda other=other, ev=ev, badge=badge: _overlay(other).get("reward F", [""])[0] == f"{ev.reward.total:+.3f}" and _overlay(other).get("verdict", [""])[0] == badge, 60, f"page {j} to show page {i}'s verdict")
        for i, pg in enumerate(pages):
            _shot(pg, f"studio_five_clients_{i}.png")
        assert all(rule.refusal(handle.value) is None for handle, rule in app.form.rules.values())  # every control within its rule
        assert app.controls().serve.params == app.last.serve.params  # what is shown is what was evaluated
    finally:
        for c in contexts:
            c.close()
    err = capfd.readouterr().err
    assert "Traceback" not in err, err
    tracebacks = [f"{r.name}: {r.getMessage()}" for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]
    assert not tracebacks, tracebacks
    with capfd.disabled():
        print("\n".join(notes + [f"log: {r.name}: {r.getMessage()}" for r in caplog.records]))
