"""Ball physics: flight, impacts, event-driven simulation, racket calibration."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from studio.physics import ball as B
from studio.physics import ball_calibration as BC
from studio import constants as C
from studio.errors import DataFileError, InvalidInputError

R_BALL = C.BALL_RADIUS


def _first_table_bounce(state: B.BallState, **kw: object) -> B.Event:
    traj = B.simulate(state, 2.0, max_table_bounces=1, **kw)  # type: ignore[arg-type]
    assert traj.events and traj.events[0].kind == "table", f"events: {[e.kind for e in traj.events]}"
    return traj.events[0]


# --- flight ------------------------------------------------------------------------


def test_scalar_derivative_matches_vectorized_acceleration() -> None:
    fm = B.FlightModel()
    rng = np.random.default_rng(1)
    v = rng.normal(0, 5, (20, 3))
    w = rng.normal(0, 300, (20, 3))
    a = fm.acceleration(np.zeros((20, 3)), v, w)
    wd = fm.spin_derivative(v, w)
    deriv = fm.scalar_derivative()
    for i in range(20):
        d = deriv([0.0, 0.0, 0.0, *v[i], *w[i]])
        np.testing.assert_allclose(d[3:6], a[i], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(d[6:9], wd[i], rtol=1e-12, atol=1e-12)


def test_magnus_direction_and_saturation() -> None:
    fm = B.FlightModel()
    v = np.array([8.0, 0.0, 0.0])
    a_top = fm.acceleration(np.zeros(3), v, [0.0, 300.0, 0.0])
    a_none = fm.acceleration(np.zeros(3), v, [0.0, 0.0, 0.0])
    a_side = fm.acceleration(np.zeros(3), v, [0.0, 0.0, 300.0])
    assert a_top[2] < a_none[2] - 1.0  # topspin pushes down
    assert a_side[1] > 1.0  # w_z > 0 pushes to +Y (left of the flight direction)
    # the saturating law C_L = S / (lift_a + lift_b S), checked on round parameters:
    # S = 0.25 -> 1/6, S = 4 -> 4/9, far below the linear law's 4
    assert B.FlightModel(lift_a=1.0, lift_b=2.0).lift_coefficient(0.25) == pytest.approx(1 / 6)
    assert B.FlightModel(lift_a=1.0, lift_b=2.0).lift_coefficient(4.0) == pytest.approx(4 / 9)
    # the default (fitted on match flights) saturates at 1 / lift_b ~ 0.30
    assert fm.lift_coefficient(4.0) == pytest.approx(4.0 / (fm.lift_a + 4.0 * fm.lift_b))
    assert 0.2 < fm.lift_coefficient(0.25) < fm.lift_coefficient(4.0) < 1.0 / fm.lift_b <= 0.31
    # cork spin (along v) makes no lift
    a_cork = fm.acceleration(np.zeros(3), v, [300.0, 0.0, 0.0])
    np.testing.assert_allclose(a_cork, a_none, atol=1e-12)


def test_rk4_matches_tight_dop853_reference() -> None:
    fm = B.FlightModel()
    s = B.BallState([-1.3, 0.1, 0.5], [6.0, -0.5, 1.0], [20.0, 250.0, -150.0])
    traj = B.simulate(s, 0.25, stop_on_floor=False)
    assert not traj.events
    deriv = fm.scalar_derivative()
    ref = solve_ivp(lambda t, y: deriv(y), (0.0, 0.25), s.as_vector(), method="DOP853", rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(traj.p[-1], ref.y[:3, -1], atol=1e-7)
    np.testing.assert_allclose(traj.v[-1], ref.y[3:6, -1], atol=1e-6)
    np.testing.assert_allclose(traj.w[-1], ref.y[6:9, -1], atol=1e-5)


def test_topspin_shorter_backspin_longer() -> None:
    p, v = [-1.3, 0.0, 0.30], [3.5, 0.0, 0.8]
    x_none = _first_table_bounce(B.BallState(p, v, [0, 0, 0])).p[0]
    x_top = _first_table_bounce(B.BallState(p, v, [0, 200, 0])).p[0]
    x_back = _first_table_bounce(B.BallState(p, v, [0, -200, 0])).p[0]
    assert x_top < x_none - 0.05
    assert x_back > x_none + 0.05


def test_sidespin_curves_left_for_positive_wz() -> None:
    # travelling +X: w_z > 0 (counter-clockwise seen from above) curves to +Y (left)
    p, v = [-1.3, 0.0, 0.30], [3.5, 0.0, 0.8]
    y_left = _first_table_bounce(B.BallState(p, v, [0, 0, 250])).p[1]
    y_right = _first_table_bounce(B.BallState(p, v, [0, 0, -250])).p[1]
    assert y_left > 0.03
    assert y_right < -0.03
    assert y_left == pytest.approx(-y_right, abs=1e-9)


def test_mirror_symmetry_in_y() -> None:
    s = B.BallState([-1.3, 0.2, 0.3], [4.5, -0.6, 0.9], [40.0, 180.0, -220.0])
    # reflection y -> -y: positions/velocities flip y, the spin (a pseudovector) flips x and z
    m = B.BallState(s.p * [1, -1, 1], s.v * [1, -1, 1], s.w * [-1, 1, -1])
    a = B.simulate(s, 1.2, max_table_bounces=3)
    b = B.simulate(m, 1.2, max_table_bounces=3)
    assert [e.kind for e in a.events] == [e.kind for e in b.events]
    assert len(a.table_bounces) >= 2
    np.testing.assert_allclose(a.t, b.t, atol=1e-12)
    np.testing.assert_allclose(b.p, a.p * [1, -1, 1], atol=1e-9)
    np.testing.assert_allclose(b.v, a.v * [1, -1, 1], atol=1e-9)
    np.testing.assert_allclose(b.w, a.w * [-1, 1, -1], atol=1e-7)


def test_no_energy_gain_along_a_bouncing_serve() -> None:
    fm = B.FlightModel()
    s = B.BallState([-1.3, 0.1, 0.3], [4.0, 0.4, 0.5], [0.0, -300.0, 200.0])
    traj = B.simulate(s, 1.5, max_table_bounces=4)
    assert len(traj.table_bounces) >= 2
    e = fm.energy(traj.p, traj.v, traj.w)
    assert np.all(np.diff(e) <= 1e-9)
    assert e[-1] < e[0]


def test_spin_components_sign_convention() -> None:
    tb, ss, ck = B.spin_components([5.0, 0.0, 0.0], [10.0, 200.0, -30.0])
    assert (float(tb), float(ss), float(ck)) == pytest.approx((200.0, -30.0, 10.0))
    # travelling -X the same w_y is backspin
    tb, _, _ = B.spin_components([-5.0, 0.0, 0.0], [0.0, 200.0, 0.0])
    assert float(tb) == pytest.approx(-200.0)
    tb, ss, ck = B.spin_components(np.array([[0.0, 3.0, 0.0]]), np.array([[-50.0, 0.0, 7.0]]))
    # travelling +Y: e_y = Z x Y = -X, so w_x < 0 (top of the ball moving +Y) is topspin
    assert tb.shape == (1,) and float(tb[0]) == pytest.approx(50.0)
    assert float(ss[0]) == pytest.approx(7.0)


# --- impacts -----------------------------------------------------------------------


def test_drop_test_itt_f_2_1_3() -> None:
    assert BC.drop_test_rebound() == pytest.approx(C.DROP_TEST_REBOUND, abs=0.015)


def _kinetic(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    return 0.5 * C.BALL_MASS * np.sum(v * v, axis=-1) + 0.5 * C.BALL_INERTIA * np.sum(w * w, axis=-1)


def test_table_bounce_regimes_and_energy() -> None:
    table = B.TableBounceModel()
    rng = np.random.default_rng(2)
    v = rng.normal(0, 4, (2000, 3))
    v[:, 2] = -np.abs(v[:, 2]) - 0.1
    w = rng.normal(0, 300, (2000, 3))
    v2, w2 = table.bounce(v, w)
    assert np.all(_kinetic(v2, w2) <= _kinetic(v, w) + 1e-15)
    np.testing.assert_allclose(v2[:, 2], -table.restitution * v[:, 2])
    # rolling regime: no spin, slow tangential speed -> contact point ends at rest
    v2, w2 = table.bounce([0.5, 0.0, -3.0], [0.0, 0.0, 0.0])
    assert v2[0] - R_BALL * w2[1] == pytest.approx(0.0, abs=1e-12)
    assert v2[0] == pytest.approx(0.5 * 0.6)  # v_t' = v_t (1 - 1/(1 + 3/2))
    # sliding regime: fast slip, Coulomb impulse mu (1 + e) |v_z|
    v2, _ = table.bounce([6.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    assert v2[0] == pytest.approx(6.0 - table.friction * (1 + table.restitution) * 2.0)
    # topspin speeds the ball up, backspin slows it
    assert table.bounce([3.0, 0, -2.0], [0, 300.0, 0])[0][0] > table.bounce([3.0, 0, -2.0], [0, -300.0, 0])[0][0]


def test_racket_bounce_energy_never_increases() -> None:
    rng = np.random.default_rng(3)
    v = rng.normal(0, 6, (4000, 3))
    v[:, 2] = -np.abs(v[:, 2]) - 0.05
    w = rng.normal(0, 400, (4000, 3))
    for model in (B.RacketModel.default(), B.RacketModel.for_racket("racket_03"), B.RacketModel(compliance_0=1.0)):
        v2, w2 = model.bounce(v, w)
        assert np.all(_kinetic(v2, w2) <= _kinetic(v, w) * (1 + 1e-12))
        assert np.all(v2[:, 2] > 0.0)


def test_racket_model_held_out_rms() -> None:
    rows = BC.load_bounce_csv(BC.dataset_path("racket_01"))
    idx = np.random.default_rng(7).permutation(len(rows))
    test, train = idx[:160], idx[160:]
    model = BC.fit_racket_model(rows.subset(train))
    ev, ew = BC.prediction_errors(model, rows.subset(test))
    rms_v, rms_w = float(np.sqrt(np.mean(ev**2))), float(np.sqrt(np.mean(ew**2)))
    assert rms_v < 0.5
    assert rms_w < 45.0
    # and it beats the reference elastic-rubber model on the spin by a wide margin
    ref = BC.fit_reference_model(rows.subset(train))
    _, ew_ref = BC.prediction_errors(ref, rows.subset(test))
    assert rms_w < 0.8 * float(np.sqrt(np.mean(ew_ref**2)))


def test_default_racket_model_matches_shipped_fit_figures() -> None:
    model = B.RacketModel.default()
    assert model.name == "racket_01"
    rows = BC.load_bounce_csv(BC.dataset_path("racket_01"))
    ev, ew = BC.prediction_errors(model, rows)
    assert float(np.sqrt(np.mean(ev**2))) < 0.45
    assert float(np.sqrt(np.mean(ew**2))) < 25.0
    assert model.cv_rms_velocity is not None and model.cv_rms_velocity < 0.5
    assert model.cv_rms_spin is not None and model.cv_rms_spin < 45.0


def test_bounce_moving_at_rest_equals_racket_frame_bounce() -> None:
    model = B.RacketModel.default()
    R = Rotation.from_euler("xyz", [0.3, -0.5, 1.1]).as_matrix()
    v_loc, w_loc = np.array([1.5, -0.4, -6.0]), np.array([30.0, 200.0, -40.0])
    v_out, w_out = model.bounce_moving(R @ v_loc, R @ w_loc, R, np.zeros(3), 1.0)
    v_ref, w_ref = model.bounce(v_loc, w_loc)
    np.testing.assert_allclose(R.T @ v_out, v_ref, atol=1e-12)
    np.testing.assert_allclose(R.T @ w_out, w_ref, atol=1e-12)
    # face B: the same impact seen through the racket turned by pi about x
    F = R @ np.diag([1.0, -1.0, -1.0])
    v_out, w_out = model.bounce_moving(F @ v_loc, F @ w_loc, R, np.zeros(3), -1.0)
    np.testing.assert_allclose(F.T @ v_out, v_ref, atol=1e-12)
    np.testing.assert_allclose(F.T @ w_out, w_ref, atol=1e-12)


# --- events --------------------------------------------------------------------------


def test_table_event_exact_and_matches_vacuum_parabola() -> None:
    vac = B.FlightModel().without_air()
    z0, vz, g = 0.4, 1.2, vac.gravity
    s = B.BallState([-1.2, 0.1, z0], [1.0, 0.0, vz], [0.0, 0.0, 0.0])
    ev = _first_table_bounce(s, flight=vac)
    t_exact = (vz + math.sqrt(vz * vz + 2 * g * (z0 - R_BALL))) / g
    assert ev.t == pytest.approx(t_exact, abs=1e-9)
    assert ev.p[2] == pytest.approx(R_BALL, abs=1e-9)
    assert ev.part == "top" and ev.side == "server"
    # with air: still exactly at contact, and independent of the integration step
    s2 = B.BallState([-1.3, 0.0, 0.3], [5.0, 0.2, 0.5], [0.0, 150.0, 60.0])
    e1 = _first_table_bounce(s2)
    e2 = _first_table_bounce(s2, max_step=0.0025)
    assert e1.p[2] == pytest.approx(R_BALL, abs=1e-9)
    assert e1.t == pytest.approx(e2.t, abs=1e-8)


def test_net_and_post_hits_are_detected() -> None:
    low = B.BallState([-0.3, 0.0, 0.10], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    traj = B.simulate(low, 1.0)
    first = traj.events[0]
    assert first.kind == "net" and first.part == "net"
    assert first.p[0] == pytest.approx(-C.NET_THICKNESS / 2 - R_BALL, abs=1e-6)
    assert abs(first.v_after[0]) < 0.2 * abs(first.v_before[0])
    y_post = C.TABLE_WIDTH / 2 + C.NET_POST_OFFSET - C.NET_POST_SIZE / 2
    post = B.BallState([-0.3, y_post, 0.10], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    first = B.simulate(post, 1.0).events[0]
    assert first.kind == "net" and first.part == "post"
    # a ball whose bottom passes ~1 cm over the net top does not touch it
    over = B.BallState([-0.3, 0.0, C.NET_HEIGHT + R_BALL + 0.025], [6.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    traj = B.simulate(over, 0.3)
    assert [e.kind for e in traj.events] == ["table"]
    i = int(np.argmin(np.abs(traj.p[:, 0])))
    assert 0.005 < traj.p[i, 2] - R_BALL - C.NET_HEIGHT < 0.02


def test_table_edge_and_side_hits() -> None:
    hl = C.TABLE_LENGTH / 2
    vac = B.FlightModel(gravity=0.0, air_density=0.0)
    # falling onto the receiver's end-line rim, centre 1 cm beyond the end line: "edge"
    s = B.BallState([hl + 0.01, 0.0, 0.1], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    ev = B.simulate(s, 0.2, flight=vac).events[0]
    assert (ev.kind, ev.part, ev.side) == ("table", "edge", "receiver")
    assert np.hypot(ev.p[0] - hl, ev.p[2]) == pytest.approx(R_BALL, abs=1e-9)
    assert ev.v_after[0] > 0.5  # kicked outwards by the rim
    # flying horizontally into the side of the top, 1 cm below the surface: "side"
    s = B.BallState([0.5, -1.0, -0.01], [0.0, 3.0, 0.0], [0.0, 0.0, 0.0])
    ev = B.simulate(s, 0.2, flight=vac).events[0]
    assert (ev.kind, ev.part) == ("table", "side")
    np.testing.assert_allclose(ev.normal, [0.0, -1.0, 0.0], atol=1e-12)
    assert ev.v_after[1] < 0.0


def test_grazing_net_top_is_found_between_samples() -> None:
    # the ball's bottom dips 1 mm into the net top in the middle of one integration step
    z = C.NET_HEIGHT + R_BALL - 0.001
    s = B.BallState([-0.05, 0.0, z], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    vac = B.FlightModel(gravity=0.0, air_density=0.0)
    traj = B.simulate(s, 0.02, flight=vac, max_step=0.01)
    assert [e.part for e in traj.events][:1] == ["net"]


def _racket_motion(face_dir: float, x0: float, speed: float) -> B.SampledRacketMotion:
    """Racket with its face-A normal along face_dir * X, moving +X at `speed`."""
    t = np.linspace(0.0, 0.2, 21)
    p = np.stack([x0 + speed * t, np.zeros_like(t), np.full_like(t, 0.5)], axis=1)
    z = np.array([face_dir, 0.0, 0.0])
    y = np.array([0.0, 0.0, 1.0])
    R = np.repeat(np.stack([np.cross(y, z), y, z], axis=1)[None], len(t), axis=0)
    return B.SampledRacketMotion(t, p, R)


@pytest.mark.parametrize(("face_dir", "part"), [(1.0, "face_a"), (-1.0, "face_b")])
def test_moving_racket_hits_falling_ball(face_dir: float, part: str) -> None:
    motion = _racket_motion(face_dir, x0=-1.7, speed=5.0)
    # ball falling in front of the racket (no table underneath: x < -1.37)
    ball = B.BallState([-1.55, 0.0, 0.52], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0])
    traj = B.simulate(ball, 0.2, racket=motion)
    rk = traj.events_of("racket")
    assert len(rk) == 1
    ev = rk[0]
    assert ev.part == part
    # contact when the ball centre is r + half thickness ahead of the moving blade
    rs = motion.state(ev.t)
    assert ev.p[0] - rs.p[0] == pytest.approx(R_BALL + C.RACKET_HALF_THICKNESS, abs=1e-9)
    # pushed forward faster than the racket (restitution ~0.75 at 5 m/s)
    assert 5.0 + 0.6 * 5.0 < ev.v_after[0] < 5.0 + 0.95 * 5.0
    assert abs(ev.v_after[1]) < 1e-9
    # a ball at rest hit by a flat racket gets no spin about y beyond what the fall gives
    assert abs(ev.w_after[1]) < 60.0


def test_sampled_racket_motion_recovers_velocity_and_spin() -> None:
    omega = np.array([0.0, 2.0, 8.0])
    t = np.linspace(0.0, 0.5, 26)
    R = Rotation.from_rotvec(t[:, None] * omega[None]).as_matrix()
    p = np.stack([1.0 + 3.0 * t, -2.0 * t, 0.5 + t * t], axis=1)
    motion = B.SampledRacketMotion(t, p, R)
    st = motion.state(0.237)
    np.testing.assert_allclose(st.omega, omega, atol=1e-9)
    np.testing.assert_allclose(st.R, Rotation.from_rotvec(0.237 * omega).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(st.v, [3.0, -2.0, 2 * 0.237], atol=1e-6)
    np.testing.assert_allclose(st.p, [1.0 + 3 * 0.237, -2 * 0.237, 0.5 + 0.237**2], atol=1e-6)
    with pytest.raises(InvalidInputError):
        motion.state(0.6)


# --- validation --------------------------------------------------------------------


def test_bad_inputs_rejected(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match=r"BallState\.v"):
        B.BallState([0, 0, 0], [0, float("nan"), 0], [0, 0, 0])
    with pytest.raises(InvalidInputError, match="BallState.p"):
        B.BallState([0, 0], [0, 0, 0], [0, 0, 0])
    s = B.BallState([0, 0, 0.3], [0, 0, 0], [0, 0, 0])
    with pytest.raises(InvalidInputError, match="t_max"):
        B.simulate(s, -1.0)
    with pytest.raises(InvalidInputError, match="FlightModel.drag_coefficient"):
        B.FlightModel(drag_coefficient=float("inf"))
    with pytest.raises(InvalidInputError, match="SampledRacketMotion"):
        B.SampledRacketMotion([0.0, 1.0], np.zeros((2, 3)), np.stack([np.eye(3), 2 * np.eye(3)]))

    header = ",".join(BC.REQUIRED_COLUMNS)
    good = "0,001," + ",".join(["1.0"] * 6) + ",0.5,0.0,-5.0,1.0,0.0,4.0"
    ok = tmp_path / "ok.csv"
    ok.write_text(f"{header}\n{good}\n")
    assert len(BC.load_bounce_csv(ok)) == 1
    missing = tmp_path / "missing.csv"
    missing.write_text(header.replace(",v_out_z", "") + "\n")
    with pytest.raises(DataFileError, match=r"missing\.csv.*v_out_z"):
        BC.load_bounce_csv(missing)
    bad = tmp_path / "bad.csv"
    bad.write_text(f"{header}\n{good}\n{good.replace('-5.0', 'abc')}\n")
    with pytest.raises(DataFileError, match=r"bad\.csv: line 3, column 'v_in_z'"):
        BC.load_bounce_csv(bad)
    nan = tmp_path / "nan.csv"
    nan.write_text(f"{header}\n{good.replace('0.5', 'nan', 1)}\n")
    with pytest.raises(DataFileError, match="line 2, column 'v_in_x': not finite"):
        BC.load_bounce_csv(nan)


def test_relative_rotation_vectors_match_scipy_including_half_turns() -> None:
    from scipy.spatial.transform import Rotation

    from studio.physics.ball import _relative_rotvecs

    rng = np.random.default_rng(3)
    big = Rotation.random(300, random_state=1).as_matrix()  # arbitrary increments, some near pi
    small = Rotation.from_rotvec(np.cumsum(0.02 * rng.normal(size=(300, 3)), axis=0)).as_matrix()  # 1 kHz-like
    for R in (big, small):
        rot = Rotation.from_matrix(R)
        expected = (rot[:-1].inv() * rot[1:]).as_rotvec()
        np.testing.assert_allclose(_relative_rotvecs(R), expected, atol=1e-9)
    half = np.stack([np.eye(3), Rotation.from_rotvec([0.0, np.pi, 0.0]).as_matrix()])
    assert np.isclose(np.linalg.norm(_relative_rotvecs(half)[0]), np.pi)


def test_racket_models_file_that_is_not_utf8_names_the_file(tmp_path: Path) -> None:
    """A racket-model JSON saved in Latin-1: DataFileError naming the file, not a raw
    UnicodeDecodeError (the reader caught only OSError)."""
    bad = tmp_path / "racket_models.json"
    bad.write_bytes(B.RACKET_MODELS_JSON.read_bytes().replace(b'"', b'"\xe9', 1))
    with pytest.raises(DataFileError, match=r"racket_models\.json: not UTF-8 text \(byte 0xe9") as info:
        B._load_racket_models(bad)
    assert info.value.path == str(bad)
