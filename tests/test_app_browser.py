"""The studio in a real browser (Debian chromium via playwright, headless).

Screenshots of the states are saved to ``test-artifacts/``.
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

    from studio.ui.app import StudioApp
    from studio.serve.evaluate import EvaluationContext

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


def _set_number(page, label: str, value: float) -> None:  # type: ignore[no-untyped-def]
    """Type into the number field of the slider labelled ``label``."""
    row = page.get_by_text(label, exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]")
    box = row.locator("input").last
    box.fill(str(value))
    box.press("Enter")


def test_slider_change_replans_and_updates_checklist(studio, page) -> None:  # type: ignore[no-untyped-def]
    app, _, _ = studio
    page.screenshot(path=str(ARTIFACTS / "studio_initial.png"))
    before = app.last
    assert before.legal, before.reason  # the studio opens on a legal example serve
    page.get_by_role("tab", name="Checks").click()
    page.get_by_text("LEGAL").first.wait_for(timeout=30_000)
    page.get_by_role("tab", name="Serve").click()
    _set_number(page, "v_x", round(before.serve.params.velocity[0] - 0.6, 2))
    _wait(lambda: app.last is not before and app.last.serve.params != before.serve.params, 60, "re-plan after slider change")
    after = app.last
    assert after.serve.params.velocity[0] == pytest.approx(before.serve.params.velocity[0] - 0.6, abs=0.051)
    assert after.ball is not None and before.ball is not None
    assert not (len(after.ball.p) == len(before.ball.p) and (after.ball.p == before.ball.p).all())  # the path moved
    page.screenshot(path=str(ARTIFACTS / "studio_after_slider.png"))


def test_illegal_serve_is_flagged(studio, page) -> None:  # type: ignore[no-untyped-def]
    app, _, _ = studio
    page.get_by_role("tab", name="Serve").click()
    _set_number(page, "v_z", 4.5)  # racket flying upwards: the ball never bounces on the server's court
    _set_number(page, "roll", 60.0)
    _wait(lambda: app.last is not None and app.last.serve.params.velocity[2] == pytest.approx(4.5), 60, "evaluation of the illegal serve")
    assert not app.last.legal
    page.get_by_role("tab", name="Checks").click()
    page.get_by_text("ILLEGAL").or_(page.get_by_text("NO PLAN")).or_(page.get_by_text("COLLISION")).first.wait_for(timeout=30_000)
    page.get_by_text("FAIL").first.wait_for(timeout=30_000)
    page.screenshot(path=str(ARTIFACTS / "studio_illegal.png"))


def test_save_seed_writes_a_valid_serve_file(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.serve.params import load_serve

    app, _, serves = studio
    page.get_by_role("tab", name="Serve").click()
    page.get_by_role("button", name="Save as seed").click()
    _wait(lambda: any(serves.glob("*.json")), 30, "seed file")
    saved = load_serve(next(serves.glob("*.json")))
    assert saved.params == app.controls().serve.params


def test_export_puts_the_serve_in_the_library(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.library.store import ServeLibrary

    app, _, serves = studio
    page.get_by_role("tab", name="Serve").click()
    page.get_by_role("button", name="Export to library").click()
    library = ServeLibrary(serves / "library")
    _wait(lambda: (serves / "library" / "index.json").exists() and len(library.entries()) == 1, 30, "library export")
    entry = library.entries()[0]
    assert entry.serve.params == app.last.serve.params
    assert entry.arrays()["u"].shape[1] == 8
    page.get_by_text("Exported").first.wait_for(timeout=10_000)
    page.screenshot(path=str(ARTIFACTS / "studio_exported.png"))


def test_dashboard_open_in_studio_loads_the_serve_in_the_page(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.ui.dashboard import LibraryDashboard

    app, url, serves = studio
    page.get_by_role("tab", name="Serve").click()
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
    page.screenshot(path=str(ARTIFACTS / "studio_opened_from_dashboard.png"))


def test_match_tab_serves_and_records_a_point(studio, page) -> None:  # type: ignore[no-untyped-def]
    from studio.library.match import MATCH_LOG, load_points

    from studio.serve.evaluate import evaluate_serve
    from studio.library.store import ServeLibrary
    from studio.serve.params import load_serve

    app, _, serves = studio
    example = Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json"
    ServeLibrary(serves / "library").add(evaluate_serve(load_serve(example), app.context))  # a legal serve to select
    page.get_by_role("tab", name="Match").click()
    page.get_by_role("button", name="Next serve").click()
    _wait(lambda: app._match_serve is not None, 30, "selected serve")
    page.get_by_role("button", name="ace").click()
    log = serves / "library" / MATCH_LOG
    _wait(lambda: log.exists() and len(load_points(log)) == 1, 30, "recorded point")
    (point,) = load_points(log)
    assert point.server == "robot" and point.serve == app._match_serve and point.ace and point.winner == "robot"
    page.get_by_text("serving: robot won 100.0 % of 1").first.wait_for(timeout=10_000)
    page.screenshot(path=str(ARTIFACTS / "studio_match.png"))


def test_mujoco_rollout_checkbox_evaluates_with_the_rollout(studio, page) -> None:  # type: ignore[no-untyped-def]
    """Ticking "MuJoCo rollout" re-evaluates the serve with the MuJoCo rollout and shows its
    verdict (it used to fail with "rollout: X covers ... samples, t_end = ... needs ...")."""
    from studio.serve.params import load_serve

    app, _, _ = studio
    example = Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json"
    if app._playing:  # a match serve left playing: the software-rendered page would crawl
        app._toggle_play()
    app.load(load_serve(example))
    _wait(lambda: app.worker.wait_idle(0.1) and app.last is not None and app.last.serve.name == "topspin right", 60, "the example serve")
    page.get_by_role("tab", name="Serve").click()
    box = page.get_by_text("MuJoCo rollout", exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]").locator("input[type=checkbox]")
    box.check(force=True)  # Mantine's input sits under its styled box
    try:
        _wait(lambda: app.mujoco.value is True, 30, "the checkbox to reach the studio")
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
        page.screenshot(path=str(ARTIFACTS / "studio_mujoco_rollout.png"))
    finally:
        page.get_by_role("tab", name="Serve").click()
        box.uncheck(force=True)
        _wait(lambda: app.mujoco.value is False and app.worker.wait_idle(0.1) and app.last is not None and app.last.rollout is None, 120, "back to the analytic evaluation")
