"""The serve capability envelope's claim (experiments/envelope/README.md): a legal serve with
more than the paper's 550 rad/s at the net, faster than its 6.7 m/s, within every joint's
effort limit. The ball state comes from the evaluation; the efforts are recomputed with
pinocchio (RNEA on the URDF) straight on the exported arrays, not with the project's
effort code."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from studio.library.store import ServeLibrary
from studio.paths import robots_dir
from studio.serve.evaluate import EvaluationContext, evaluate_serve
from studio.serve.params import load_serve

ENVELOPE = Path(__file__).resolve().parent.parent / "experiments" / "envelope"
NAMES = ("gantry_x", "gantry_y", "a1", "a2", "a3", "a4", "a5", "a6")


def test_the_spinniest_serve_within_the_effort_limits_beats_the_papers_550_rad_s(tmp_path: Path) -> None:
    serve = load_serve(ENVELOPE / "spinniest_within_efforts.json")
    ev = evaluate_serve(serve, EvaluationContext.default(), task="spin_net")
    assert ev.legal and ev.metrics is not None and ev.metrics.net is not None
    w_net = np.asarray(ev.metrics.net["w"], dtype=float)
    assert np.linalg.norm(w_net) > 550.0 and ev.metrics.net["speed"] > 6.7
    entry = ServeLibrary(tmp_path / "lib").add(ev)  # refused (EffortLimitError) beyond a limit
    with np.load(tmp_path / "lib" / entry.data["arrays"], allow_pickle=False) as npz:
        t, u, q = npz["t"], npz["u"], npz["q"]
    doc = tomllib.loads((robots_dir() / "serve_robot.toml").read_text(encoding="utf-8"))
    joints = {j["name"]: j for j in doc["joints"] if j["type"] != "fixed"}
    wn, zeta, limit = (np.array([joints[n][k] for n in NAMES]) for k in ("wn", "zeta", "effort"))
    qd = np.gradient(q, t, axis=0)
    qdd = wn**2 * (u - q) - 2 * zeta * wn * qd  # the TOML's joint model drives the joints
    model = pin.buildModelFromUrdf(str(robots_dir() / "serve_robot.urdf"))
    data = model.createData()
    peak = np.max([np.abs(pin.rnea(model, data, q[k], qd[k], qdd[k])) for k in range(0, len(t), 2)], axis=0)
    assert np.all(peak <= limit), dict(zip(NAMES, np.round(peak / limit, 3)))
    assert peak[1] == pytest.approx(entry.data["robot"]["efforts"]["peak"][1], rel=0.03)  # gantry_y, the busiest
