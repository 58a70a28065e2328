"""The serve capability envelope's claims (experiments/envelope/README.md): a legal serve with
more than the paper's 550 rad/s at the net, faster than its 6.7 m/s, and one with more than
300 rad/s of backspin at the net, each within every joint's effort limit. The ball state comes from the evaluation; the efforts are recomputed with
pinocchio (RNEA on the URDF) straight on the exported arrays, not with the project's
effort code."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pinocchio as pin
import pytest

from studio.library.store import ServeLibrary
from studio.paths import robots_dir
from studio.serve.evaluate import Evaluation, EvaluationContext, evaluate_serve
from studio.serve.params import load_serve

ENVELOPE = Path(__file__).resolve().parent.parent / "experiments" / "envelope"
NAMES = ("gantry_x", "gantry_y", "a1", "a2", "a3", "a4", "a5", "a6")


def _pinocchio_peak_usage(tmp_path: Path, ev: Evaluation) -> npt.NDArray[np.float64]:
    """Export ``ev`` (refused beyond an effort limit), then each joint's peak effort over its
    limit, recomputed with pinocchio's RNEA on the exported arrays and the TOML's joint model."""
    entry = ServeLibrary(tmp_path / "lib").add(ev)
    with np.load(tmp_path / "lib" / entry.data["arrays"], allow_pickle=False) as npz:
        t, u, q = npz["t"], npz["u"], npz["q"]
    doc = tomllib.loads((robots_dir() / "serve_robot.toml").read_text(encoding="utf-8"))
    joints = {j["name"]: j for j in doc["joints"] if j["type"] != "fixed"}
    wn, zeta, limit = (np.array([joints[n][k] for n in NAMES]) for k in ("wn", "zeta", "effort"))
    qd = np.gradient(q, t, axis=0)
    qdd = wn**2 * (u - q) - 2 * zeta * wn * qd
    model = pin.buildModelFromUrdf(str(robots_dir() / "serve_robot.urdf"))
    data = model.createData()
    peak = np.max([np.abs(pin.rnea(model, data, q[k], qd[k], qdd[k])) for k in range(0, len(t), 2)], axis=0)
    assert peak == pytest.approx(entry.data["robot"]["efforts"]["peak"], rel=0.03, abs=1.0)
    return np.asarray(peak / limit, dtype=float)


def test_the_spinniest_serve_within_the_effort_limits_beats_the_papers_550_rad_s(tmp_path: Path) -> None:
    serve = load_serve(ENVELOPE / "spinniest_within_efforts.json")
    ev = evaluate_serve(serve, EvaluationContext.default(), task="spin_net")
    assert ev.legal and ev.metrics is not None and ev.metrics.net is not None
    assert np.linalg.norm(ev.metrics.net["w"]) > 550.0 and ev.metrics.net["speed"] > 6.7
    usage = _pinocchio_peak_usage(tmp_path, ev)
    assert np.all(usage <= 1.0), dict(zip(NAMES, np.round(usage, 3)))


def test_a_serve_within_the_effort_limits_has_300_rad_s_of_backspin_at_the_net(tmp_path: Path) -> None:
    serve = load_serve(ENVELOPE / "largest_backspin_within_efforts.json")
    ev = evaluate_serve(serve, EvaluationContext.default(), task="backspin_net")
    assert ev.legal and ev.metrics is not None and ev.metrics.net is not None
    assert ev.metrics.net["topspin"] < -300.0
    usage = _pinocchio_peak_usage(tmp_path, ev)
    assert np.all(usage <= 1.0), dict(zip(NAMES, np.round(usage, 3)))
