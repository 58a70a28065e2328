"""Panel dashboard over a serve library: clustering, layout on real/empty/corrupt libraries,
serve JSON download, and the dashboard in a real browser (Debian chromium, headless)."""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from studio.library.store import INDEX_NAME, ServeLibrary
from studio.serve.params import serve_from_json
from studio.ui.dashboard import (
    SCATTER_AXES,
    LibraryDashboard,
    build_dashboard,
    entry_cluster,
    filter_table,
    spin_cluster,
)

ROOT = Path(__file__).resolve().parent.parent
SERVES = ROOT / "examples" / "serves"
NOTEBOOK = ROOT / "examples" / "inspect_library.ipynb"
ARTIFACTS = ROOT / "test-artifacts"
CHROMIUM = "/usr/bin/chromium"
NAMES = ("backspin_right", "topspin_right", "sidespin_right")


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A library of three evaluated example serves (right toss); the backspin one planned with
    the paper's dynamic limit expansion (x1.5 acceleration and jerk), for the limits column."""
    from dataclasses import replace

    from studio.serve.evaluate import EvaluationContext, evaluate_serve
    from studio.serve.params import LimitScale, load_serve

    folder = tmp_path_factory.mktemp("library")
    context = EvaluationContext.default()
    lib = ServeLibrary(folder)
    for name in NAMES:
        serve = load_serve(SERVES / f"{name}.json")
        if name == "backspin_right":
            serve = replace(serve, limit_scale=LimitScale(acceleration=1.5, jerk=1.5))
        ev = evaluate_serve(serve, context, task=serve.task or "topspin_velocity")
        lib.add(ev, provenance={"kind": "hand-designed", "file": f"{name}.json"}, task=serve.task)
    return folder


def test_limits_text() -> None:
    from studio.serve.params import LimitScale
    from studio.ui.dashboard import limits_text

    assert limits_text(LimitScale()) == "1"
    assert limits_text(LimitScale(velocity=1.1, acceleration=1.5, jerk=1.5)) == "v 1.1, a 1.5, j 1.5"


def test_spin_cluster_by_dominant_component() -> None:
    assert spin_cluster(200.0, 20.0) == "topspin"
    assert spin_cluster(-150.0, 30.0, 10.0) == "backspin"
    assert spin_cluster(10.0, -120.0) == "sidespin"
    assert spin_cluster(60.0, 60.0) == "mixed"  # both at 0.71 |w| < 0.8 |w|
    assert spin_cluster(0.0, 0.0, 100.0) == "mixed"  # pure cork: neither top/back nor side
    assert spin_cluster(5.0, -3.0) == "no spin"  # |w| = 5.8 rad/s < 10 rad/s
    assert spin_cluster(float("nan"), 1.0) == "no net crossing"
    # the threshold: 0.8 |w| exactly is dominant, just below is not
    assert spin_cluster(80.0, 60.0) == "topspin"
    assert spin_cluster(79.0, 61.3) == "mixed"
    assert spin_cluster(80.0, 60.0, dominance=0.9) == "mixed"
    assert entry_cluster({"net": None}) == "no net crossing"
    assert entry_cluster({"net": {"v": [3.0, 0, 0], "w": [0, -90.0, 0], "topspin": -90.0, "sidespin": 0.0, "cork": 0.0}}) == "backspin"
    assert entry_cluster({"net": {"v": "broken"}}) == "no net crossing"  # malformed net state: shown, not raised


def test_dashboard_on_a_library_of_three_serves(library: Path) -> None:
    dash = LibraryDashboard(library, studio_url="http://127.0.0.1:8080")
    assert dash.error is None and dash.status.alert_type == "info" and "3 serves" in dash.status.object
    table = dash.table
    assert sorted(table["name"]) == sorted(n.replace("_", " ") for n in NAMES)
    assert list(dash.tabulator.value["id"]) == list(table["id"])
    # backspin serve: negative topspin at the net, clustered as backspin; horizontal speed <= speed
    back = table[table["name"] == "backspin right"].iloc[0]
    assert back["topspin"] < -50 and back["cluster"] == "backspin"
    entry = ServeLibrary(library).get(back["id"])
    v = np.asarray(entry.data["net"]["v"])
    assert back["speed_h"] == pytest.approx(np.hypot(v[0], v[1])) and back["speed_h"] <= entry.data["net"]["speed"]
    assert back["spin"] == pytest.approx(np.linalg.norm(entry.data["net"]["w"]))
    # each serve's limits column says its own limit scale (backspin right plans with x1.5 acceleration and jerk)
    assert set(table["limits"]) == {"1", "v 1, a 1.5, j 1.5"} and back["limits"] == "v 1, a 1.5, j 1.5"
    # the first row is shown: 8 joint command lines, ball path views, studio link, download
    assert dash.selected_id == table["id"].iloc[0]
    lines = [r for r in dash.joints.object.renderers if type(r.glyph).__name__ == "Line"]
    assert len(lines) == 8
    assert dash.top_view.object is not None and dash.side_view.object is not None
    assert "http://127.0.0.1:8080" in dash.studio_link.object
    assert not dash.download.disabled and dash.download.filename == f"{dash.selected_id}.json"
    served = serve_from_json(json.loads(dash._serve_json().getvalue()))
    assert served.params == ServeLibrary(library).get(dash.selected_id).serve.params
    # the scatter: one glyph per cluster present, both axis choices
    assert dash.scatter.object.xaxis[0].axis_label.startswith("horizontal speed")
    dash.axes.value = SCATTER_AXES[1]
    assert dash.scatter.object.xaxis[0].axis_label.startswith("topspin")
    legend = sorted(item.label["value"] for item in dash.scatter.object.legend[0].items)
    assert legend == sorted(set(table["cluster"]))
    # selecting another row switches the detail view
    dash.tabulator.selection = [2]
    assert dash.selected_id == table["id"].iloc[2]
    assert str(table["name"].iloc[2]) in dash.detail_title.object
    # filters
    dash.cluster.value = "backspin"
    assert list(dash.tabulator.value["name"]) == ["backspin right"] and dash.selected_id == back["id"]
    dash.cluster.value = "all"
    dash.legal.value = "illegal"
    assert len(dash.tabulator.value) == 0 and dash.selected_id is None and dash.download.disabled
    dash.legal.value = "legal"
    assert len(dash.tabulator.value) == int(table["legal"].sum())
    assert len(filter_table(table, side="left")) == 0 and len(filter_table(table, side="right")) == 3
    assert len(filter_table(table, task="backspin_net")) == 1  # the backspin example was found on the net-spin task
    # the whole layout turns into Bokeh models (what a browser or a notebook renders)
    layout = build_dashboard(library)
    assert layout.get_root() is not None


def test_missing_and_empty_library_show_a_message(tmp_path: Path) -> None:
    dash = LibraryDashboard(tmp_path / "nowhere")
    assert dash.status.visible and dash.status.alert_type == "warning" and "no index.json" in dash.status.object
    assert len(dash.tabulator.value) == 0 and dash.selected_id is None
    assert dash.layout.get_root() is not None
    (tmp_path / INDEX_NAME).write_text(json.dumps({"schema": "serve-studio/library@1", "serves": []}))
    dash = LibraryDashboard(tmp_path)
    assert "holds no serves" in dash.status.object


def test_corrupt_files_show_an_error_naming_the_file(library: Path, tmp_path: Path) -> None:
    import shutil

    folder = tmp_path / "lib"
    shutil.copytree(library, folder)
    index = folder / INDEX_NAME
    good = index.read_text()
    index.write_text(good[:200])  # truncated JSON
    dash = LibraryDashboard(folder)
    assert dash.error is not None and dash.status.visible and dash.status.alert_type == "danger"
    assert "index.json" in dash.status.object and "not valid JSON" in dash.status.object
    assert len(dash.tabulator.value) == 0
    assert dash.layout.get_root() is not None
    # a wrong field is named too
    doc = json.loads(good)
    doc["serves"][1]["reward"] = "high"
    index.write_text(json.dumps(doc))
    dash.reload_button.clicks += 1  # the reload button re-reads the folder
    assert "serves[1].reward" in dash.status.object
    # repaired: reload recovers
    index.write_text(good)
    dash.reload_button.clicks += 1
    assert dash.error is None and len(dash.tabulator.value) == 3
    # a corrupt arrays file: the serve's view shows the error, the table stays
    first = dash.selected_id
    (folder / f"{first}.npz").write_bytes(b"not a zip")
    dash.reload()
    assert dash.detail_error.visible and f"{first}.npz" in dash.detail_error.object.replace("\\_", "_")
    assert dash.joints.object is None and len(dash.tabulator.value) == 3


def test_notebook_is_valid_nbformat_without_outputs() -> None:
    nb = json.loads(NOTEBOOK.read_text())
    assert nb["nbformat"] == 4 and isinstance(nb["nbformat_minor"], int) and "metadata" in nb
    assert nb["cells"]
    for cell in nb["cells"]:
        assert cell["cell_type"] in ("markdown", "code") and "metadata" in cell and isinstance(cell["source"], (str, list))
        if cell["cell_type"] == "code":
            assert cell["outputs"] == [] and cell["execution_count"] is None
    code = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    assert "build_dashboard" in code and "ServeLibrary" in code and "evaluate_serve" in code
    compile(code, str(NOTEBOOK), "exec")  # the cells are valid Python


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def served(library: Path) -> Iterator[str]:
    import panel as pn

    port = _free_port()
    server = pn.serve({"/": lambda: build_dashboard(library)}, port=port, address="127.0.0.1", show=False, threaded=True, websocket_origin=[f"127.0.0.1:{port}"])
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.1)
    yield f"http://127.0.0.1:{port}/"
    server.stop()


@pytest.mark.browser
def test_dashboard_in_a_browser(served: str) -> None:
    from playwright.sync_api import sync_playwright

    if not os.path.exists(CHROMIUM):
        pytest.fail(f"{CHROMIUM} is missing: ./dev test installs Debian's chromium (apt-get install chromium)")
    ARTIFACTS.mkdir(exist_ok=True)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=CHROMIUM,
            headless=True,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update", "--disable-sync"],
        )
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1500})
            page.goto(served)
            for name in NAMES:
                page.get_by_text(name.replace("_", " "), exact=True).first.wait_for(timeout=30_000)
            page.get_by_text("3 serves").first.wait_for(timeout=10_000)
            page.get_by_role("button", name="Download serve JSON").wait_for(timeout=10_000)
            # click a table row: the detail heading follows
            page.locator(".tabulator-row").filter(has_text="sidespin right").first.click()
            page.get_by_role("heading", name="sidespin right").wait_for(timeout=20_000)
            page.wait_for_timeout(500)
            page.screenshot(path=str(ARTIFACTS / "dashboard.png"), full_page=True)
        finally:
            browser.close()


def test_match_statistics_from_the_log(library: Path, tmp_path: Path) -> None:
    import shutil

    from studio.library.match import MATCH_LOG

    folder = tmp_path / "lib"
    shutil.copytree(library, folder)
    dash = LibraryDashboard(folder)
    assert "No match log yet" in dash.match.object
    serve_id = ServeLibrary(folder).entries()[0].id
    lines = [
        {"time": "2026-11-23T10:00:00+00:00", "server": "robot", "serve": serve_id, "winner": "robot", "ace": True},
        {"time": "2026-11-23T10:01:00+00:00", "server": "opponent", "serve": None, "winner": "opponent", "ace": False},
    ]
    (folder / MATCH_LOG).write_text("".join(json.dumps(x) + "\n" for x in lines))
    dash.reload()
    assert "win % serving" in dash.match.object and serve_id in dash.match.object
    (folder / MATCH_LOG).write_text('{"time": "x"}\n')
    dash.reload()
    assert "Cannot read the match log" in dash.match.object and "matches.jsonl" in dash.match.object


def test_convergence_of_linked_runs_inside_the_runs_folder_only(library: Path, tmp_path: Path) -> None:
    import shutil

    from studio.optimize.hebo_adapter import HeboConfig
    from studio.optimize.optimizer import OptimizeOptions, Outcome, optimize_serve

    def fake(serve, tosses, rng):  # type: ignore[no-untyped-def]
        r = -float(np.sum((serve.params.to_vector() - 0.5) ** 2)) / 100.0
        return Outcome(r, r > -1.0, "legal" if r > -1.0 else "illegal")

    cheap = HeboConfig(rand_sample=4, es_pop=8, es_iters=2, gp_epochs=5, max_train=12, keep_best=4)
    runs = tmp_path / "runs"
    for name in ("a", "b"):
        optimize_serve(OptimizeOptions(side="right", task="backspin", iterations=3, population=4, workers=1, config=cheap, top_k=1, final_tosses=2), run_dir=runs / name, evaluate=fake)
    outside = tmp_path / "elsewhere"
    shutil.copytree(runs / "a", outside)
    folder = tmp_path / "lib"
    shutil.copytree(library, folder)
    doc = json.loads((folder / INDEX_NAME).read_text())
    ids = [s["id"] for s in doc["serves"]]
    for s, run in zip(doc["serves"], (runs / "a", runs / "b", outside)):
        s["provenance"] = {"kind": "hebo", "run": str(run), "seed": 0}
    (folder / INDEX_NAME).write_text(json.dumps(doc))

    dash = LibraryDashboard(folder, runs_dir=runs)
    assert set(dash.histories) == set(ids[:2])  # the run outside the runs folder is not read
    assert len(dash.histories[ids[0]].reward) == 12
    dash.tabulator.selection = [list(dash.tabulator.value["id"]).index(ids[0])]
    fig = dash.convergence.object
    lines = [r for r in fig.renderers if type(r.glyph).__name__ == "Line"]
    assert len(lines) == 2  # the other run in grey, the selected one highlighted
    assert "2 runs" in dash.convergence_info.object and "12 evaluations" in dash.convergence_info.object
    # a corrupt run log is reported with its file, the rest still shows
    log = runs / "b" / "evaluations.jsonl"
    log.write_text("{broken\n" + log.read_text())
    dash.reload()
    assert set(dash.histories) == {ids[0]} and "evaluations.jsonl" in dash.convergence_info.object.replace("\\_", "_")
    assert dash.layout.get_root() is not None


def _reference_file(path: Path, n: int = 10) -> Path:
    """A small match file in the Ace public format made up here: n rallies, each starting
    with a serve, robot (shot_p1, from x < 0) and human (shot_p2, from x > 0) in turn."""
    rng = np.random.default_rng(0)
    vec = lambda x: "[" + " ".join(f"{v:.4f}" for v in x) + "]"
    lines = ["player_id,rally_id,type,timestamp,ball_pos,ball_vel_out,ball_spin_out\n"]
    for k in range(n):
        if k % 2:  # human, towards -X
            p, v, w = [1.80, -0.45, 0.22], [-5.5, 1.0, -0.5], [-40.0, 20.0, 180.0]
        else:
            p, v, w = [-1.62, 0.15, 0.24], [4.2, -0.5, -0.5], [20.0, 150.0, -60.0]
        p, v, w = np.add(p, rng.normal(0, 0.03, 3)), np.add(v, rng.normal(0, 0.3, 3)), np.add(w, rng.normal(0, 60.0, 3))
        lines.append(f"Test Player,/game_0/rally_{k}/event1,{'shot_p2' if k % 2 else 'shot_p1'},{10.0 * k},{vec(p)},{vec(v)},{vec(w)}\n")
    path.write_text("".join(lines))
    return path


@pytest.mark.browser
def test_dashboard_with_reference_serves_in_a_browser(library: Path, tmp_path: Path) -> None:
    """The library's serves among reference serves (robot and human, marked apart) in the
    net-crossing scatter and the spin-direction polar plot, in a real browser."""
    import panel as pn
    from playwright.sync_api import sync_playwright

    from studio.ui.dashboard import LibraryDashboard

    reference = _reference_file(tmp_path / "match.csv")
    dash = LibraryDashboard(library, reference=reference)
    assert dash.reference is not None and dash.reference.serves == {"robot": 5, "human": 5}
    labels = [item.label["value"] for item in dash.polar.object.legend[0].items]
    assert "Ace robot serves (reference): 5" in labels and "human serves (reference): 5" in labels
    port = _free_port()
    server = pn.serve({"/": lambda: build_dashboard(library, reference=reference)}, port=port, address="127.0.0.1", show=False, threaded=True, websocket_origin=[f"127.0.0.1:{port}"])
    if not os.path.exists(CHROMIUM):
        pytest.fail(f"{CHROMIUM} is missing: ./dev test installs Debian's chromium (apt-get install chromium)")
    ARTIFACTS.mkdir(exist_ok=True)
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update", "--disable-sync"])
            try:
                page = browser.new_page(viewport={"width": 1400, "height": 1700})
                page.goto(f"http://127.0.0.1:{port}/")
                page.get_by_text("Reference: 5 robot serves").first.wait_for(timeout=30_000)
                page.get_by_text("match.csv").first.wait_for(timeout=10_000)
                page.get_by_text("3 serves").first.wait_for(timeout=10_000)
                page.wait_for_timeout(1500)  # the Bokeh canvases draw
                assert page.locator(".bk-Canvas, canvas").count() >= 2
                path = ARTIFACTS / "dashboard_reference_serves.png"
                page.screenshot(path=str(path), full_page=True)
                print(f"screenshot: {path}")
            finally:
                browser.close()
    finally:
        server.stop()
