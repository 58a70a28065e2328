"""Effort limits (robots/serve_robot.toml), the effort report and the export's refusal.

The limits are checked with MuJoCo's own rigid-body code on the MJCF (not pinocchio, which
derives them in experiments/effort_limits.py), and an export's efforts are recomputed with
pinocchio straight on the NPZ arrays."""

from __future__ import annotations

import tomllib
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from studio.errors import InvalidInputError
from studio.library.store import INDEX_NAME, ServeLibrary
from studio.paths import robots_dir
from studio.serve.efforts import EffortLimitError, EffortReport, effort_report, parse_limits
from studio.serve.evaluate import EvaluationContext, evaluate_serve
from studio.serve.params import load_serve

SERVES = Path(__file__).resolve().parent.parent / "examples" / "serves"
NAMES = ("gantry_x", "gantry_y", "a1", "a2", "a3", "a4", "a5", "a6")


def _toml_joints() -> dict[str, dict]:  # type: ignore[type-arg]
    doc = tomllib.loads((robots_dir() / "serve_robot.toml").read_text(encoding="utf-8"))
    return {j["name"]: j for j in doc["joints"] if j["type"] != "fixed"}


def _mujoco_single_axis_need(samples: int = 3000) -> np.ndarray:
    """max over random poses of |gravity_j| + M_jj a_j with 6 kg at 100 mm out from the
    flange and 60 mm off its axis: MuJoCo on the MJCF, drive inertia (armature) removed."""
    spec = mujoco.MjSpec.from_file(str(robots_dir() / "serve_robot.xml"))
    flange = spec.body("flange")
    payload = flange.add_body(name="payload", pos=[0.06, 0.0, 0.10])
    payload.mass, payload.ipos, payload.inertia, payload.explicitinertial = 6.0, [0.0, 0.0, 0.0], [1e-9, 1e-9, 1e-9], True
    for joint in spec.joints:
        joint.armature = 0.0
    model = spec.compile()
    data = mujoco.MjData(model)
    joints = _toml_joints()
    accel = np.array([joints[n]["acceleration"] for n in NAMES])
    lo, hi = model.jnt_range[:, 0], model.jnt_range[:, 1]
    rng = np.random.default_rng(7)
    full = np.zeros((model.nv, model.nv))
    worst = np.zeros(model.nv)
    for _ in range(samples):
        data.qpos[:] = rng.uniform(lo, hi)
        data.qvel[:] = 0.0
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, full)
        worst = np.maximum(worst, np.abs(data.qfrc_bias) + np.diag(full) * accel)
    return worst


def test_toml_limits_follow_the_stated_rule_on_mujoco() -> None:
    """effort = 1.25 x (hold the 6 kg payload anywhere and accelerate it at the joint's own
    limit), rounded up to 2 digits: at least the rule, at most rounding and sampling above."""
    need = 1.25 * _mujoco_single_axis_need()
    limits = np.array([_toml_joints()[n]["effort"] for n in NAMES])
    assert np.all(limits >= need * 0.98), dict(zip(NAMES, need))  # 3000 poses find ~the 20,000 poses' maximum
    assert np.all(limits <= need * 1.12), dict(zip(NAMES, need))
    assert limits[3] > 600.0  # a2: the payload at full reach alone needs 6 kg g 1 m ~ 60 N m, the arm's own weight much more


def test_report_flags_refuses_and_raises() -> None:
    rep = EffortReport(NAMES, np.array([4600.0, 1000, 300, 300, 80, 5, 5, 0.1]), np.zeros(8), np.array([4000.0, 2600, 680, 850, 260, 35, 35, 7]))
    assert not rep.within and rep.exceeded == ("gantry_x",) and rep.worst[0] == "gantry_x"
    assert rep.usage[0] == pytest.approx(1.15) and "EXCEED" in rep.headline() and "gantry_x 115 %" in rep.headline()
    with pytest.raises(EffortLimitError, match=r"gantry_x 4600 > 4000 \(115 %\).*--effort-limit gantry_x=4600"):
        rep.require_within()
    raised = rep.with_limits({"gantry_x": 5000})
    assert raised.within and raised.raised == ("gantry_x",) and raised.limit[0] == 5000 and "(raised)" in raised.markdown()
    raised.require_within()
    to_peak = rep.raised_to_peaks()
    assert to_peak.within and to_peak.limit[0] == pytest.approx(4600) and to_peak.raised == ("gantry_x",)
    assert rep.to_json()["exceeded"] == ["gantry_x"] and raised.to_json()["raised"] == ["gantry_x"]


@pytest.mark.parametrize(
    ("given", "match"),
    [
        (["gantry_x"], "expected JOINT=VALUE"),
        (["elbow=3"], "unknown joint 'elbow'"),
        (["a2=nan"], "a2: must be a finite number > 0"),
        (["a2=-5"], "a2: must be a finite number > 0"),
        (["a2=1e400"], "a2: must be a finite number > 0"),
        ({"a2": True}, "a2: must be a finite number > 0"),
    ],
)
def test_bad_user_limits_are_refused_naming_the_joint(given: object, match: str) -> None:
    with pytest.raises(InvalidInputError, match=match):
        parse_limits(given, NAMES)  # type: ignore[arg-type]


def test_parse_limits_reads_joint_value_pairs() -> None:
    assert parse_limits(["gantry_x=4700", " a2 = 900.5 "], NAMES) == {"gantry_x": 4700.0, "a2": 900.5}


@pytest.fixture(scope="module")
def beyond():  # type: ignore[no-untyped-def]
    """backspin_heavy_right (acceleration and jerk limits x2): its gantry_x force beyond the limit."""
    serve = load_serve(SERVES / "backspin_heavy_right.json")
    return evaluate_serve(serve, EvaluationContext.default(), task=serve.task)


def test_export_beyond_the_limits_is_refused_and_writes_nothing(tmp_path: Path, beyond) -> None:  # type: ignore[no-untyped-def]
    lib = ServeLibrary(tmp_path / "lib")
    with pytest.raises(EffortLimitError, match=r"gantry_x \d+ > 4000"):
        lib.add(beyond)
    assert not (tmp_path / "lib").exists() or not any((tmp_path / "lib").iterdir())


def test_export_with_a_raised_limit_records_it_and_pinocchio_agrees(tmp_path: Path, beyond) -> None:  # type: ignore[no-untyped-def]
    """Raised on purpose: exported, the entry says so, and RNEA recomputed on the NPZ
    (pinocchio on the URDF, speeds and accelerations from the arrays and the TOML's joint
    model) exceeds the robot's gantry_x limit but not the raised one."""
    entry = ServeLibrary(tmp_path / "lib").add(beyond, effort_limits={"gantry_x": 5200.0})
    eff = entry.data["robot"]["efforts"]
    assert eff["raised"] == ["gantry_x"] and eff["limit"][0] == 5200.0 and eff["within"] is True
    with np.load(tmp_path / "lib" / entry.data["arrays"], allow_pickle=False) as npz:
        t, u, q = npz["t"], npz["u"], npz["q"]
    joints = _toml_joints()
    wn, zeta = (np.array([joints[n][k] for n in NAMES]) for k in ("wn", "zeta"))
    qd = np.gradient(q, t, axis=0)
    qdd = wn**2 * (u - q) - 2 * zeta * wn * qd
    model = pin.buildModelFromUrdf(str(robots_dir() / "serve_robot.urdf"))
    data = model.createData()
    peak = np.max([np.abs(pin.rnea(model, data, q[k], qd[k], qdd[k])) for k in range(0, len(t), 2)], axis=0)
    assert 4000.0 < peak[0] < 5200.0
    assert peak[0] == pytest.approx(eff["peak"][0], rel=0.03)


def test_every_example_exports_within_the_limits_or_is_refused(tmp_path: Path) -> None:
    """The done-when of the hardware issue: each example's export either has every peak
    within the TOML's limits or is refused; the refused one is the x2 expansion."""
    context = EvaluationContext.default()
    limits = np.array([_toml_joints()[n]["effort"] for n in NAMES])
    refused = []
    for path in sorted(SERVES.glob("*.json")):
        serve = load_serve(path)
        ev = evaluate_serve(serve, context, task=serve.task or "topspin_velocity")
        rep = effort_report(ev.motion, context.robot)
        assert rep is not None
        try:
            entry = ServeLibrary(tmp_path / path.stem).add(ev)
        except EffortLimitError:
            refused.append(path.stem)
            assert not rep.within and not (tmp_path / path.stem / INDEX_NAME).exists()
        else:
            assert rep.within and np.all(np.array(entry.data["robot"]["efforts"]["peak"]) <= limits)
    assert refused == ["backspin_heavy_right"]
    assert all(not load_serve(SERVES / f"{n}.json").limit_scale.is_identity for n in refused)
