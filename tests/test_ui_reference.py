"""Reference serves for the dashboard (studio.ui.reference) from a small match file made
here in the Ace public format: robot and human serves at the net, beside the library."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from studio.errors import DataFileError
from studio.library.store import ServeLibrary
from studio.paths import example_serves_dir
from studio.physics.ball import DEFAULT_FLIGHT
from studio.physics.flight_calibration import VELOCITY_LAG
from studio.serve.evaluate import EvaluationContext, evaluate_serve
from studio.serve.params import load_serve
from studio.ui.reference import HALF_TURN, HUMAN, ROBOT, reference_serves

HEADER = "player_id,rally_id,type,timestamp,ball_pos,ball_vel_out,ball_spin_out\n"


def _vec(x: np.ndarray) -> str:
    return "[" + " ".join(f"{float(v):.9f}" for v in x) + "]"


def write_match_file(path: Path, serves: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]) -> Path:
    """One rally per serve (who, p, v, w): the serve, then a bounce on the server's half;
    plus a rally that starts with a bounce (no serve: skipped)."""
    lines = [HEADER]
    for k, (who, p, v, w) in enumerate(serves):
        kind = "shot_p1" if who == ROBOT else "shot_p2"
        bounce = "bounce_p1" if who == ROBOT else "bounce_p2"
        lines.append(f"Test Player,/game_0/rally_{k}/event1,{kind},{10.0 * k},{_vec(p)},{_vec(v)},{_vec(w)}\n")
        lines.append(f"Test Player,/game_0/rally_{k}/event2,{bounce},{10.0 * k + 0.2},{_vec(p * [0.5, 0.5, 0])},{_vec(v)},{_vec(w)}\n")
    lines.append(f"Test Player,/game_0/rally_99/event1,bounce_p2,99.0,{_vec(np.array([0.5, 0, 0.02]))},{_vec(np.array([-3.0, 0, 2.0]))},{_vec(np.zeros(3))}\n")
    path.write_text("".join(lines))
    return path


@pytest.fixture(scope="module")
def evaluation():  # type: ignore[no-untyped-def]
    context = EvaluationContext.default()
    return evaluate_serve(load_serve(example_serves_dir() / "topspin_right.json"), context), context


@pytest.fixture(scope="module")
def match_file(evaluation, tmp_path_factory: pytest.TempPathFactory) -> Path:  # type: ignore[no-untyped-def]
    """The example serve's ball just after the racket written as a robot serve (its velocity
    'measured' with the data's lag, as the Ace file has it) and, turned by 180 degrees about
    +Z, as a human serve from the far end."""
    ev, _ = evaluation
    hit = next(e for e in ev.ball.events if e.kind == "racket")
    p, v, w = hit.p, hit.v_after, hit.w_after
    v_measured = v + VELOCITY_LAG * DEFAULT_FLIGHT.acceleration(np.zeros(3), v, w)  # the inverse of the lag correction, to first order
    serves = [(ROBOT, p, v_measured, w), (HUMAN, HALF_TURN @ p, HALF_TURN @ v_measured, HALF_TURN @ w)]
    return write_match_file(tmp_path_factory.mktemp("ref") / "match.csv", serves)


def test_a_library_serve_written_as_a_reference_serve_lands_on_itself(evaluation, match_file: Path) -> None:  # type: ignore[no-untyped-def]
    """Flown from the racket to the net with the project's models, the reference serve has
    the evaluation's own net-crossing state; the human copy (served from the other end)
    the same state; the rally without a serve is skipped."""
    ev, _ = evaluation
    ref = reference_serves(match_file)
    assert ref.serves == {ROBOT: 1, HUMAN: 1} and ref.no_crossing == {ROBOT: 0, HUMAN: 0}
    assert len(ref.table) == 2 and not ref.table["touches_net"].any()
    robot, human = ref.of(ROBOT).iloc[0], ref.of(HUMAN).iloc[0]
    net = ev.metrics.net
    assert robot["speed_h"] == pytest.approx(np.hypot(net["v"][0], net["v"][1]), abs=0.01)
    assert robot["topspin"] == pytest.approx(net["topspin"], abs=1.0) and robot["sidespin"] == pytest.approx(net["sidespin"], abs=1.0)
    assert robot["clearance"] == pytest.approx(net["clearance"], abs=0.002)
    for col in ("speed_h", "spin", "topspin", "sidespin", "cork", "clearance"):
        assert human[col] == pytest.approx(robot[col], abs=1e-6), col
    assert "1 robot serves and 1 human serves" in ref.summary() and "match.csv" in ref.summary()


def test_a_bad_match_file_names_the_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text(HEADER + "P,/g/r/event1,shot_p1,1.0,[1 2],[0 0 0],[0 0 0]\n")
    with pytest.raises(DataFileError, match="line 2"):
        reference_serves(bad)


def test_the_dashboard_draws_the_reference_beside_the_library(evaluation, match_file: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from studio.ui.dashboard import SCATTER_AXES, LibraryDashboard

    ev, _ = evaluation
    ServeLibrary(tmp_path / "lib").add(ev, provenance={"kind": "hand-designed"}, task="topspin_velocity")
    dash = LibraryDashboard(tmp_path / "lib", reference=match_file)
    assert dash.reference is not None and "1 robot serves" in dash.reference_info.object and dash.reference_info.visible

    def legend(fig) -> list[str]:  # type: ignore[no-untyped-def]
        return [item.label["value"] for item in fig.legend[0].items]

    for fig in (dash.scatter.object, dash.polar.object):
        labels = legend(fig)
        assert "Ace robot serves (reference): 1" in labels and "human serves (reference): 1" in labels
        assert "topspin" in labels  # the library's serve, by cluster
    markers = {r.glyph.marker for r in dash.polar.object.renderers if type(r.glyph).__name__ == "Scatter" and isinstance(r.glyph.marker, str)}
    assert {"triangle", "square", "circle"} <= markers  # robot, human, library: marked apart
    dash.axes.value = SCATTER_AXES[1]
    assert "Ace robot serves (reference): 1" in legend(dash.scatter.object)
    # the polar plot puts each serve at (topspin, sidespin): the library's point is its net state
    lib = [r for r in dash.polar.object.renderers if type(r.glyph).__name__ == "Scatter" and r.glyph.marker == "circle" and "x" in r.data_source.data]
    xs = np.concatenate([np.asarray(r.data_source.data["x"]) for r in lib])
    assert ev.metrics.net["topspin"] == pytest.approx(float(xs[0]))
    assert dash.layout.get_root() is not None
    # a bad reference file is reported in the page, the library still shows
    (tmp_path / "bad.csv").write_text(HEADER + "P,/g/r/event1,shot_p1,x,[0 0 0],[0 0 0],[0 0 0]\n")
    dash = LibraryDashboard(tmp_path / "lib", reference=tmp_path / "bad.csv")
    assert dash.reference is None and "Cannot read the reference serves" in dash.reference_info.object and "line 2" in dash.reference_info.object
    assert len(dash.tabulator.value) == 1


def test_dashboard_command_takes_the_library_and_a_reference(tmp_path: Path) -> None:
    from studio.cli import build_parser, main

    parser, _ = build_parser()
    args = parser.parse_args(["dashboard", "LIB", "--reference", "match.csv"])
    assert args.library_dir == "LIB" and args.reference == "match.csv" and args.library is None
    assert parser.parse_args(["dashboard", "--library", "L2"]).library == "L2"
    assert main(["dashboard", "a", "--library", "b"]) == 2  # two different libraries: refused before serving
    assert main(["dashboard", str(tmp_path), "--reference", str(tmp_path / "missing.csv")]) == 2
