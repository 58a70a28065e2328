"""Tests of studio.toss: release model, toss primitive, synthetic recordings, toss model, CSV."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from studio import constants as C
from studio.errors import DataFileError, InvalidInputError
from studio.physics import ball
from studio.robot.model import Robot, load_robot
from studio.toss.checks import limit_violations
from studio.toss.defaults import (
    DEFAULT_N_TOSSES,
    default_recordings_path,
    generate_default_recordings,
    load_default_toss_model,
)
from studio.toss.design import ClearMove, TossDesign
from studio.toss.flight import free_flights, hermite_interpolate, vertical_rise
from studio.toss.lift_profile import LiftProfile, LiftShape
from studio.toss.local_fit import local_fit_state
from studio.toss.model import TossModel
from studio.toss.noise import TossNoise
from studio.toss.primitive import TOSS_SIDES, TossPrimitive, TossSide
from studio.toss.recordings import (
    TossRecording,
    TossRecordings,
    load_recordings_csv,
    save_recordings_csv,
)
from studio.toss.release import contact_margin, find_release
from studio.toss.report import toss_report
from studio.toss.synthesis import make_toss
from studio.toss.synthetic import nominal_ball_path, simulate_tosses

END_LINE_X = -C.TABLE_LENGTH / 2


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot()


@pytest.fixture(scope="module")
def right(robot: Robot) -> TossPrimitive:
    return make_toss(robot, "right")


@pytest.fixture(scope="module")
def left(robot: Robot) -> TossPrimitive:
    return make_toss(robot, "left")


@pytest.fixture(scope="module")
def nominal(right: TossPrimitive) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return nominal_ball_path(right, end_height=TossNoise().end_height)


# ------------------------------------------------------------------------------------
# Release model
# ------------------------------------------------------------------------------------


def test_find_release_matches_analytic_crossing() -> None:
    # Cup z = -A cos(w t): contact force (a + g) crosses 0 at cos(w t) = -g / (A w^2).
    A, w = 0.1, 20.0
    t = np.arange(0.0, 0.3, 1e-3)
    p = np.stack([np.zeros_like(t), np.zeros_like(t), -A * np.cos(w * t)], axis=1)
    n = np.tile([0.0, 0.0, 1.0], (t.size, 1))
    rel = find_release(t, p, n, drag_k=0.0)
    assert rel is not None
    t_true = math.acos(-C.GRAVITY / (A * w * w)) / w
    assert rel.time == pytest.approx(t_true, abs=2e-6)
    assert rel.index == int(t_true / 1e-3)
    assert rel.velocity[2] == pytest.approx(A * w * math.sin(w * t_true), rel=1e-3)
    assert rel.position[2] == pytest.approx(-A * math.cos(w * t_true), abs=1e-5)
    assert rel.spin == pytest.approx(0.0, abs=1e-12)
    assert rel.sideways_acceleration == pytest.approx(0.0, abs=1e-9)
    # With the exact acceleration given, the crossing is the same.
    a = np.stack([np.zeros_like(t), np.zeros_like(t), A * w * w * np.cos(w * t)], axis=1)
    rel2 = find_release(t, p, n, cup_a=a, drag_k=0.0)
    assert rel2 is not None and rel2.time == pytest.approx(t_true, abs=1e-6)
    # Air drag presses the rising ball into the cup: it leaves when the cup decelerates
    # at g + k v^2 (k v^2 = 0.3 m/s^2 here), a little later.
    k = 0.15
    rel_d = find_release(t, p, n, drag_k=k)
    assert rel_d is not None and rel_d.time > rel.time
    # Exact crossing of (a + g + k v^2) with a = A w^2 cos(w t), v = A w sin(w t).
    lo, hi = t_true, 0.2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        f = A * w * w * math.cos(w * mid) + C.GRAVITY + k * (A * w * math.sin(w * mid)) ** 2
        lo, hi = (mid, hi) if f > 0.0 else (lo, mid)
    assert rel_d.time == pytest.approx(lo, abs=5e-6)
    assert lo - t_true > 5e-4
    assert find_release(t, p, n).time == pytest.approx(  # type: ignore[union-attr]
        find_release(t, p, n, drag_k=ball.DEFAULT_FLIGHT.drag_constant).time, abs=1e-12  # type: ignore[union-attr]
    )
    # A cup that also accelerates sideways (3 m/s^2 along x) releases at the same
    # instant (only the normal force counts) and reports the sideways push the model
    # assumes away.
    p3 = p.copy()
    p3[:, 0] = 1.5 * t**2
    rel3 = find_release(t, p3, n, drag_k=0.0)
    assert rel3 is not None and rel3.time == pytest.approx(t_true, abs=2e-6)
    assert rel3.sideways_acceleration == pytest.approx(3.0, abs=1e-6)
    assert rel3.horizontal_acceleration == pytest.approx(3.0, abs=1e-6)


def test_find_release_tilted_normal_and_no_release() -> None:
    t = np.arange(0.0, 0.5, 1e-3)
    # Cup at rest, normal tilted 30 deg: gravity still pushes the ball into the cup.
    n = np.tile([math.sin(0.5), 0.0, math.cos(0.5)], (t.size, 1))
    assert find_release(t, np.zeros((t.size, 3)), n) is None
    # A sideways acceleration of 20 m/s^2 against a 30 deg tilted normal lifts the ball:
    # (a + g) . n = -20 sin 30 + 9.81 cos 30 = -1.5 < 0 from the start.
    p = np.stack([-10.0 * t**2, np.zeros_like(t), np.zeros_like(t)], axis=1)
    rel = find_release(t, p, n)
    assert rel is not None and rel.index == 0 and rel.time == 0.0
    assert contact_margin(np.array([-20.0, 0.0, 0.0]), n[0]) == pytest.approx(-20 * math.sin(0.5) + 9.81 * math.cos(0.5))
    with pytest.raises(InvalidInputError):
        find_release(t[:2], p[:2], n[:2])
    with pytest.raises(InvalidInputError):
        find_release(t[::-1], p, n)
    with pytest.raises(InvalidInputError):
        find_release(t, p, np.zeros_like(n))


def test_lift_profile_is_smooth_and_stops() -> None:
    prof = LiftProfile.design(2.8, LiftShape(lift_acceleration=18.0, ramp_up=0.2, ramp_release=0.15, ramp_stop=0.22, hold_start=0.05))
    dt = 1e-4
    t = np.arange(0.0, prof.duration + 0.1, dt)
    d = prof.evaluate(t)
    # Derivatives are consistent (finite differences) and continuous up to the 4th.
    for m in range(4):
        fd = np.gradient(d[m], dt)
        assert np.max(np.abs(fd - d[m + 1])[2:-2]) < 2e-3 * max(1.0, np.max(np.abs(d[m + 1])))
        assert np.max(np.abs(np.diff(d[m + 1]))) < np.max(np.abs(d[m + 2])) * dt * 1.01 + 1e-9
    assert d[1][-1] == 0.0 and d[2][-1] == 0.0
    assert d[0][-1] == pytest.approx(prof.travel, abs=1e-9)
    t_rel, v_rel = prof.release_estimate()
    assert v_rel == pytest.approx(2.8, abs=1e-9)
    assert prof.evaluate([t_rel])[2, 0] == pytest.approx(-C.GRAVITY, abs=1e-9)
    assert prof.stop_deceleration > C.GRAVITY


# ------------------------------------------------------------------------------------
# Toss primitive
# ------------------------------------------------------------------------------------


def test_toss_rises_vertically_without_spin(right: TossPrimitive, nominal: tuple[np.ndarray, ...]) -> None:
    rel = right.release
    # Released near vertically (designed: exactly) and without spin (racket does not turn).
    assert rel.horizontal_speed < 0.005
    assert rel.spin < 1e-3
    assert rel.velocity[2] == pytest.approx(2.694, abs=0.005)  # 0.35 m rise against C_D = 0.559 drag
    # Rise above the release point in air: >= 16 cm (ITTF 2.6.2); designed 0.35 m.
    tn, pn, _ = nominal
    rise = float(np.max(pn[:, 2]) - rel.position[2])
    assert rise >= C.TOSS_MIN_RISE
    assert rise == pytest.approx(0.35, abs=2e-3)
    # The analytic drag formula agrees with the integrated flight.
    k = ball.DEFAULT_FLIGHT.drag_constant
    assert vertical_rise(float(rel.velocity[2]), drag_k=k) == pytest.approx(rise, abs=5e-4)
    # Cross-check of the toss flight against studio.physics.ball.simulate (before any contact).
    traj = ball.simulate(ball.BallState(rel.position, rel.velocity, np.zeros(3)), 0.6, t0=rel.time, dt_out=1e-3)
    z_sim = np.interp(tn[tn > rel.time + 0.01], traj.t, traj.p[:, 2], right=np.nan)
    ok = np.isfinite(z_sim)
    assert np.max(np.abs(z_sim[ok] - pn[tn > rel.time + 0.01][ok, 2])) < 1e-4
    # Ball above the playing surface and behind the end line from the start until it
    # comes back to table level, with margin for the toss spread.
    before_table = np.arange(tn.size) < np.argmax((pn[:, 2] < 0.0) & (tn > rel.time))
    assert np.min(pn[before_table, 2]) > 0.0
    assert np.max(pn[:, 0]) < END_LINE_X - C.BALL_RADIUS - 0.1
    # Contact window: the ball stays above the table for 0.6 s after the lift at least.
    assert tn[np.argmax((pn[:, 2] < 0.0) & (tn > rel.time))] - rel.time > 0.6


def test_cup_rises_on_a_vertical_line_without_sideways_push(right: TossPrimitive, left: TossPrimitive) -> None:
    for prim in (right, left):
        rel = prim.release
        # At the release: no horizontal speed (< 2 cm/s) and no horizontal cup
        # acceleration (< 0.5 m/s^2), so the rim does not push the ball (find_release's
        # assumption); the racket is flat, so that is also the sideways push.
        assert rel.horizontal_speed < 0.02
        assert rel.horizontal_acceleration < 0.5
        assert rel.sideways_acceleration < 0.5
        acc = np.gradient(np.gradient(prim.cup_p, prim.dt, axis=0), prim.dt, axis=0)
        assert float(np.hypot(*acc[rel.index, :2])) < 0.5
        # The gantry cancels the arm's horizontal drift: the cup stays on the vertical
        # line through the release point from the start until the racket steps aside.
        until = prim.t <= rel.time + 0.06
        assert np.max(np.abs(prim.cup_p[until, 0] - rel.position[0])) < 1e-4
        assert np.max(np.abs(prim.cup_p[until, 1] - rel.position[1])) < 1e-9
        assert np.max(np.abs(acc[until, :2][5:])) < 0.5
        assert np.ptp(prim.cup_p[until, 2]) > 0.5  # while it rises and stops over ~0.6 m
        # Without that compensation the arm alone moves the cup ~14 cm along x.
        assert np.ptp(prim.q[until, 0]) > 0.1


def test_racket_clears_the_falling_ball(robot: Robot, right: TossPrimitive, left: TossPrimitive) -> None:
    spec = robot.spec.racket
    for prim, sign in ((right, -1.0), (left, 1.0)):
        rel = prim.release
        tn, pn, _ = nominal_ball_path(prim, end_height=0.0)
        cup = prim.cup_p[: tn.size]
        after = tn > rel.time
        # The ball rises out of the cup before the racket moves sideways (gantry Y).
        k_move = int(np.argmax(np.abs(prim.q[:, 1] - prim.q[0, 1]) > 1e-5))
        assert prim.t[k_move] > rel.time + 0.05
        sag = spec.ball_radius - math.sqrt(spec.ball_radius**2 - spec.cup_rim_radius**2)
        assert pn[k_move, 2] - prim.cup_p[k_move, 2] > sag
        # Then it moves 8 cm away from the centre line and lowers the cup by 15 cm.
        assert prim.q[-1, 1] - prim.q[0, 1] == pytest.approx(sign * 0.08, abs=1e-9)
        top = float(np.max(prim.cup_p[:, 2]))
        assert top - prim.cup_p[-1, 2] == pytest.approx(0.15, abs=1e-3)
        # When the falling ball passes the cup's height it is > R + plate radius + 1 cm
        # away from the cup centre.
        falling = after & (np.arange(tn.size) > np.argmax(pn[:, 2]))
        band = falling & (np.abs(pn[:, 2] - cup[:, 2]) < 0.06)
        assert np.any(band)
        gap = np.hypot(pn[band, 0] - cup[band, 0], pn[band, 1] - cup[band, 1])
        assert np.min(gap) > spec.ball_radius + spec.cup_plate_radius + 0.01
    # Too small a side step or too early a start are refused.
    with pytest.raises(InvalidInputError, match=r"ClearMove\.side"):
        make_toss(robot, "right", TossDesign(clear=ClearMove(side=0.03)))
    with pytest.raises(InvalidInputError, match=r"ClearMove\.delay"):
        make_toss(robot, "right", TossDesign(clear=ClearMove(delay=0.0)))


def test_racket_flat_during_lift(right: TossPrimitive) -> None:
    lift = right.t <= right.release.time
    tilt = np.degrees(np.arccos(np.clip(right.cup_normal[lift, 2], -1.0, 1.0)))
    assert np.max(tilt) < 0.01  # the lift keeps the racket exactly flat (< 2 deg required)
    assert right.cup_p[0, 2] > C.BALL_RADIUS  # starts with the ball above the table level
    # The ball rises well above its start: the cup travels about 0.36 m before the release.
    assert 0.25 < right.release.position[2] - right.cup_p[0, 2] < 0.45


def test_primitive_within_joint_limits_and_continuous(robot: Robot, right: TossPrimitive) -> None:
    lim = robot.limits
    u, dt = right.u, right.dt
    assert right.t[-1] >= 1.2 and dt == 1e-3
    assert np.all(u >= lim.lower) and np.all(u <= lim.upper)
    assert np.all(right.q >= lim.lower) and np.all(right.q <= lim.upper)
    # Finite differences of the 1 kHz commands.
    v = np.diff(u, axis=0) / dt
    a = np.diff(u, 2, axis=0) / dt**2
    j = np.diff(u, 3, axis=0) / dt**3
    assert np.all(np.max(np.abs(v), axis=0) <= lim.velocity)
    assert np.all(np.max(np.abs(a), axis=0) <= lim.acceleration)
    assert np.all(np.max(np.abs(j), axis=0) <= lim.jerk * 1.001)
    # The exact derivatives agree with the samples and are within limits with margin.
    assert np.max(np.abs(v - 0.5 * (right.ud[1:] + right.ud[:-1]))) < 1e-4
    assert np.max(np.abs(right.uddd) / lim.jerk) < 0.95
    assert limit_violations(right.u, right.ud, right.udd, right.uddd, lim, q=right.q) == []
    # Continuity up to acceleration: sample-to-sample jumps bounded by the jerk limit.
    assert np.all(np.max(np.abs(np.diff(right.udd, axis=0)), axis=0) <= lim.jerk * dt * 1.001)
    # Starts and ends at rest; the gantry Y axis only moves after the release.
    for arr in (right.ud, right.udd):
        assert np.max(np.abs(arr[0])) < 1e-9 and np.max(np.abs(arr[-1])) < 1e-9
    assert np.ptp(u[right.t <= right.release.time + 0.05, 1]) == 0.0
    # Hand-over state for the strike planner.
    u0, ud0, udd0, X0 = right.command_state(0.5)
    assert np.array_equal(u0, u[500]) and X0.shape == (8, 2) and ud0.shape == udd0.shape == (8,)


def test_too_high_toss_is_rejected(robot: Robot) -> None:
    with pytest.raises(InvalidInputError, match="release height|joint limits"):
        make_toss(robot, "right", TossDesign(rise=0.6))
    with pytest.raises(InvalidInputError, match="side"):
        make_toss(robot, "middle")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="rise"):
        make_toss(robot, "right", TossDesign(rise=0.1))


def test_left_and_right_tosses_mirror(right: TossPrimitive, left: TossPrimitive) -> None:
    r, l = right.release, left.release
    assert r.position[1] == pytest.approx(-0.30, abs=1e-9)
    assert l.position[1] == pytest.approx(0.30, abs=1e-9)
    assert l.position[[0, 2]] == pytest.approx(r.position[[0, 2]], abs=1e-9)
    assert l.velocity == pytest.approx(r.velocity, abs=1e-9)
    assert l.time == pytest.approx(r.time, abs=1e-12)
    assert np.array_equal(left.u[:, [0, *range(2, 8)]], right.u[:, [0, *range(2, 8)]])
    assert np.allclose(left.u[:, 1] - left.u[0, 1], -(right.u[:, 1] - right.u[0, 1]), rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------
# Synthetic recordings and the toss model
# ------------------------------------------------------------------------------------


def test_model_recovers_truth_with_measurement_noise_only(
    robot: Robot, right: TossPrimitive, nominal: tuple[np.ndarray, ...]
) -> None:
    noise = TossNoise(vibration=0.0, release_jitter=0.0, wind=0.0, wind_vertical=0.0)
    recs = simulate_tosses(robot, right, 15, np.random.default_rng(5), noise=noise)
    model = TossModel.from_recordings(right, recs)
    assert model.t_lift == pytest.approx(right.release.time, abs=1e-3)
    tn, pn, _ = nominal
    sel = model.t <= tn[-1]
    err = np.linalg.norm(model.p[sel] - np.stack([np.interp(model.t[sel], tn, pn[:, j]) for j in range(3)], axis=1), axis=1)
    assert np.max(err) < 1.5e-3
    # Clocks recovered; the spread is only the averaged-down tracking noise.
    true_off = np.array([tr.clock_offset for tr in recs.truth or ()])
    assert np.max(np.abs(model.clock_offsets - true_off)) < 1e-3
    assert np.max(model.spread_norm[model.t > model.t_lift]) < 3e-3
    assert model.lift_fit_rms == pytest.approx(noise.measurement, rel=0.15)


def test_model_with_default_noise(robot: Robot, right: TossPrimitive) -> None:
    noise = TossNoise()
    recs = simulate_tosses(robot, right, 15, np.random.default_rng(11), noise=noise)
    assert recs.truth is not None
    # Recordings: camera rate, random phases and clocks, ball seen in the cup first.
    for rec, tr in zip(recs.recordings, recs.truth):
        assert np.allclose(np.diff(rec.t), 1.0 / noise.camera_rate)
        assert rec.t[0] - tr.clock_offset < tr.release_time - 0.2
        assert rec.p[-1, 2] >= noise.end_height - 0.05
    # Every toss leaves near vertically (vibration and jitter included).
    assert max(float(np.hypot(*tr.release_v[:2])) for tr in recs.truth) < 0.05
    model = TossModel.from_recordings(right, recs)
    t_true = float(np.mean([tr.release_time for tr in recs.truth]))
    assert model.t_lift == pytest.approx(t_true, abs=3e-3)
    # Mean path vs the mean of the true (noise-free) paths of the same tosses.
    flight = model.t > max(tr.release_time for tr in recs.truth) + 0.02
    tq = model.t[flight]
    FT, FP, FV = free_flights(
        np.array([tr.release_p for tr in recs.truth]),
        np.array([tr.release_v for tr in recs.truth]),
        np.array([tr.release_time for tr in recs.truth]),
        float(tq[-1]) - min(tr.release_time for tr in recs.truth) + 0.01,
        ball.DEFAULT_FLIGHT,
        wind=np.array([tr.wind for tr in recs.truth]),
        h=1e-3,
    )
    true_paths = [hermite_interpolate(FT[k], FP[k], FV[k], tq) for k in range(len(recs))]
    err = np.linalg.norm(model.p[flight] - np.mean(true_paths, axis=0), axis=1)
    assert np.max(err) < 3e-3
    # Spread 0.7 s after the lift: about +/-1 cm (paper, 15 tosses).
    sp = model.spread_at(model.t_lift + 0.7)
    assert np.all(sp > 2e-3) and np.all(sp < 2e-2)
    assert 0.005 < float(np.linalg.norm(sp)) < 0.025
    # The spread grows with time after the release.
    assert model.spread_norm[-1] > 3 * model.spread_norm[np.searchsorted(model.t, model.t_lift + 0.05)]


def test_model_states_and_sampling(robot: Robot, right: TossPrimitive) -> None:
    recs = simulate_tosses(robot, right, 12, np.random.default_rng(3))
    model = TossModel.from_recordings(right, recs)
    tq = model.t_lift + 0.5
    mean = model.mean_state(tq)
    assert np.array_equal(mean.w, np.zeros(3))
    states = model.ball_states_at(tq)
    assert len(states) == 12 == model.n_tosses
    # per-toss states in flight: local fits of each recording; their mean is the mean path
    # (Savitzky-Golay) up to the two smoothings' difference (< 1 mm)
    assert np.allclose(np.mean([s.p for s in states], axis=0), mean.p, atol=1e-3)
    one = model.recorded_state_at(tq, 7)
    assert np.array_equal(one.p, states[7].p) and np.array_equal(one.v, states[7].v)
    for bad in (-1, 12, 2.5, True, None, "3", float("nan")):
        with pytest.raises(InvalidInputError, match="toss index"):
            model.recorded_state_at(tq, bad)  # type: ignore[arg-type]
    rng = np.random.default_rng(0)
    draws = np.array([model.sample(tq, rng).p for _ in range(400)])
    assert np.allclose(draws.mean(axis=0), mean.p, atol=2e-3)
    assert np.allclose(draws.std(axis=0), model.spread_at(tq), rtol=0.25, atol=5e-4)
    rec = model.sample(tq, rng, method="recorded")
    assert any(np.array_equal(rec.p, s.p) for s in states)
    # Falling after the apex: velocity down, and the mean velocity is the path's derivative.
    assert mean.v[2] < 0.0
    h = 1e-3
    fd = (model.mean_state(tq + h).p - model.mean_state(tq - h).p) / (2 * h)
    assert np.allclose(fd, mean.v, atol=1e-3)
    with pytest.raises(InvalidInputError, match="outside"):
        model.mean_state(5.0)
    with pytest.raises(InvalidInputError, match="method"):
        model.sample(tq, rng, method="other")  # type: ignore[arg-type]


def test_unalignable_recording_is_rejected(robot: Robot, right: TossPrimitive) -> None:
    recs = simulate_tosses(robot, right, 3, np.random.default_rng(1))
    cut = recs.recordings[0]
    late = cut.t > cut.t[0] + 0.4  # drop the in-cup part of the recording
    bad = TossRecordings((TossRecording(cut.toss_id, cut.t[late], cut.p[late]), *recs.recordings[1:]))
    with pytest.raises(InvalidInputError, match="in the cup"):
        TossModel.from_recordings(right, bad)


# ------------------------------------------------------------------------------------
# CSV format
# ------------------------------------------------------------------------------------


def test_csv_round_trip(robot: Robot, right: TossPrimitive, tmp_path: Path) -> None:
    recs = simulate_tosses(robot, right, 3, np.random.default_rng(2))
    path = tmp_path / "tosses.csv"
    save_recordings_csv(path, recs, comment="test data\nsecond line")
    back = load_recordings_csv(path)
    assert [r.toss_id for r in back.recordings] == [r.toss_id for r in recs.recordings]
    for a, b in zip(recs.recordings, back.recordings):
        assert np.allclose(a.t, b.t, atol=5e-7, rtol=0) and np.allclose(a.p, b.p, atol=5e-7, rtol=0)
    assert back.truth is None
    save_recordings_csv(path, recs, decimals=4)
    back4 = load_recordings_csv(path)
    assert np.allclose(back4.recordings[1].p, recs.recordings[1].p, atol=5e-5, rtol=0)


GOOD_HEADER = "toss_id,t,x,y,z"


def _rows(n: int = 25, tid: str = "a", t0: float = 0.0) -> list[str]:
    return [f"{tid},{t0 + 0.005 * k:.4f},-1.6,0.3,{0.1 + 0.01 * k:.4f}" for k in range(n)]


@pytest.mark.parametrize(
    ("lines", "match"),
    [
        ([GOOD_HEADER, *_rows()[:5], "a,0.1000,-1.6,abc,0.2", *_rows(30)[6:]], r"line 7, column y: 'abc' is not a number"),
        ([GOOD_HEADER, *_rows()[:3], "a,0.0150,-1.6,0.3,nan", *_rows()[4:]], r"line 5, column z: 'nan' is not finite"),
        ([GOOD_HEADER, *_rows()[:4], "a,0.0100,-1.6,0.3,0.2", *_rows()[5:]], r"line 6, column t: .*strictly increase"),
        ([GOOD_HEADER, *_rows(10)], r"toss 'a' \(last row line 11\): 10 samples"),
        (["toss_id,t,x,z", "a,0.0,-1.6,0.1"], r"line 1: header .* lacks column\(s\) y"),
        (["# only a comment", GOOD_HEADER + ",t", *_rows()], r"line 2: duplicate column\(s\) t"),
        ([GOOD_HEADER, *_rows()[:2], "a,0.0100,-1.6,0.3", *_rows()[3:]], r"line 4: 4 fields, the header has 5"),
        (["# nothing"], r"no header line"),
        ([GOOD_HEADER], r"no data rows"),
    ],
)
def test_bad_csv_rejected_with_file_and_line(tmp_path: Path, lines: list[str], match: str) -> None:
    path = tmp_path / "bad_tosses.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(DataFileError, match=match) as info:
        load_recordings_csv(path)
    assert "bad_tosses.csv" in str(info.value)


def test_csv_extra_columns_comments_and_interleaved_tosses(tmp_path: Path) -> None:
    a, b = _rows(25, "a"), _rows(25, "b", t0=100.0)
    lines = ["# tracker export", "conf,z,y,x,t,toss_id", ""]
    for ra, rb in zip(a, b):
        for row in (ra, rb):
            tid, t, x, y, z = row.split(",")
            lines.append(",".join(["0.9", z, y, x, t, tid]))
    path = tmp_path / "ok.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    recs = load_recordings_csv(path)
    assert [r.toss_id for r in recs.recordings] == ["a", "b"]
    assert recs.recordings[1].t[0] == pytest.approx(100.0)
    assert recs.recordings[0].p[3] == pytest.approx([-1.6, 0.3, 0.13])


# ------------------------------------------------------------------------------------
# Recorded toss states at the strike (robust evaluation): from the recordings themselves
# ------------------------------------------------------------------------------------

SPREAD_TAUS = (0.6, 0.75, 0.9, 1.05)
"""Strike times [s] (command clock) of the spread test: apex to the end of the recordings."""


def _csv_tosses(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Plain numpy reading of a toss CSV: {toss_id: (t (M,) [s], p (M, 3) [m])}, own clocks."""
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip() and not ln.startswith("#")]
    raw = np.genfromtxt(lines, delimiter=",", names=True, dtype=None, encoding="utf-8")
    out = {}
    for tid in dict.fromkeys(raw["toss_id"]):
        rows = raw[raw["toss_id"] == tid]
        out[str(tid)] = (rows["t"].astype(float), np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(float))
    return out


def _rising_crossing(t: np.ndarray, z: np.ndarray, z_cross: float) -> float:
    """When a recording's height first crosses ``z_cross`` on the way up in the cup [s]:
    quadratic least squares through the samples within 6 cm of it, before the apex."""
    first = t <= t[np.argmax(z)]
    band = first & (np.abs(z - z_cross) < 0.06)
    a, b, c = np.polyfit(t[band] - t[band][0], z[band], 2)
    roots = np.roots([a, b, c - z_cross]).real + t[band][0]
    return float(roots[np.argmin(np.abs(roots - np.mean(t[band])))])


def _recorded_positions_at(side: TossSide, taus: tuple[float, ...]) -> np.ndarray:
    """Independent of studio.toss's estimators: each shipped recording of ``side`` put on
    the command clock by its in-cup crossing of z = 0.21 m (against the primitive's
    predicted cup height), then a quadratic fitted to its samples within +/-30 ms of each
    tau: positions (K, len(taus), 3) [m]."""
    model = load_default_toss_model(side)
    cup_t, cup_z = model.primitive.t, model.primitive.cup_p[:, 2]
    z_cross = 0.21
    i = int(np.argmax(cup_z >= z_cross))
    t_nom = cup_t[i - 1] + (z_cross - cup_z[i - 1]) / (cup_z[i] - cup_z[i - 1]) * (cup_t[i] - cup_t[i - 1])
    out = []
    for t, p in _csv_tosses(default_recordings_path(side)).values():
        tc = t - _rising_crossing(t, p[:, 2], z_cross) + t_nom
        rows = []
        for tau in taus:
            sel = np.abs(tc - tau) <= 0.03
            rows.append([np.polyval(np.polyfit(tc[sel] - tau, p[sel, j], 2), 0.0) for j in range(3)])
        out.append(rows)
    return np.array(out)


def _evaluation_positions_at(model: TossModel, taus: tuple[float, ...]) -> np.ndarray:
    """Where the robust evaluation's ball is at each tau (K, len(taus), 3) [m]: flown by
    ball.simulate from each toss's recorded_start_state at t_lift + 5 ms (no racket)."""
    t0 = model.t_lift + 0.005
    out = np.empty((model.n_tosses, len(taus), 3))
    for k in range(model.n_tosses):
        for i, tau in enumerate(taus):
            s0 = model.recorded_start_state(k, t0, tau)
            traj = ball.simulate(s0, tau - t0, t0=t0, dt_out=tau - t0)
            assert traj.t[-1] == pytest.approx(tau, abs=1e-9) and not traj.events
            out[k, i] = traj.p[-1]
    return out


@pytest.mark.parametrize("side", TOSS_SIDES)
def test_recorded_toss_spread_at_the_strike_is_the_recordings_spread(side: TossSide) -> None:
    """The balls the robust evaluation flies spread at tau as the recordings do there
    (std per axis and its norm within 20 %), not ~7 times wider as when flown from the
    noisy state just after the lift."""
    model = load_default_toss_model(side)
    recorded = _recorded_positions_at(side, SPREAD_TAUS)
    flown = _evaluation_positions_at(model, SPREAD_TAUS)
    for i, tau in enumerate(SPREAD_TAUS):
        s_rec = recorded[:, i].std(axis=0, ddof=1)
        s_fly = flown[:, i].std(axis=0, ddof=1)
        assert np.allclose(s_fly, s_rec, rtol=0.2, atol=0.0), (tau, s_fly, s_rec)
        assert float(np.linalg.norm(s_fly)) == pytest.approx(float(np.linalg.norm(s_rec)), rel=0.2)
        assert np.allclose(model.recorded_spread_at(tau), s_rec, rtol=0.2)
        # the spread the model reports (Savitzky-Golay paths) agrees too
        assert float(np.linalg.norm(model.spread_at(tau))) == pytest.approx(float(np.linalg.norm(s_rec)), rel=0.2)
    # each toss meets its own recording at tau (the two clock alignments differ by up to
    # ~1 ms, ~3 mm at the ball's 3 m/s; flown from just after the lift: 32-58 mm median)
    miss = np.linalg.norm(flown - recorded, axis=2)
    assert float(np.median(miss)) < 1.5e-3 and float(np.max(miss)) < 5e-3


@pytest.mark.parametrize("side", TOSS_SIDES)
def test_recorded_state_reproduces_its_own_recording(side: TossSide) -> None:
    model = load_default_toss_model(side)
    for k in (0, 7, model.n_tosses - 1):
        rec = model.recordings.recordings[k]  # on the command clock
        for tau in (model.free_flight_start + 0.01, 0.8, 0.95, float(model.t[-1])):
            s = model.recorded_state_at(tau, k)
            assert np.array_equal(s.w, np.zeros(3))
            # a 120 ms window of its samples, kept inside [free flight start, last sample]
            w_lo = min(max(tau - 0.06, model.free_flight_start), float(rec.t[-1]) - 0.12)
            near = (rec.t >= w_lo - 1e-9) & (rec.t <= w_lo + 0.12 + 1e-9)
            c = np.polyfit(rec.t[near] - tau, rec.p[near], 2)  # (3, 3)
            assert np.linalg.norm(s.p - c[2]) < 1e-3, (k, tau)
            assert np.linalg.norm(s.v - c[1]) < 0.01, (k, tau)
            # the recorded samples scatter around it by the tracking noise (1.5 mm/axis)
            win = np.abs(rec.t - tau) <= 0.02
            pred = s.p + np.outer(rec.t[win] - tau, s.v)
            pred[:, 2] -= 0.5 * C.GRAVITY * (rec.t[win] - tau) ** 2
            assert float(np.sqrt(np.mean((rec.p[win] - pred) ** 2))) < 3e-3
    # before the free flight (ball in the cup, lift): the smoothed path as before
    tt = model.t_lift
    s = model.recorded_state_at(tt, 3)
    i = int(np.searchsorted(model.t, tt))
    assert np.linalg.norm(s.p - model.tosses_p[3, i]) < 3e-3


def test_recorded_start_state_flies_through_the_recorded_state() -> None:
    model = load_default_toss_model("right")
    t0, tau = model.t_lift + 0.005, 0.91
    for k in (2, 11):
        s0 = model.recorded_start_state(k, t0, tau)
        traj = ball.simulate(s0, tau - t0, t0=t0, dt_out=tau - t0)
        target = model.recorded_state_at(tau, k)
        assert np.linalg.norm(traj.p[-1] - target.p) < 1e-4
        assert np.linalg.norm(traj.v[-1] - target.v) < 1e-3
        assert np.array_equal(s0.w, np.zeros(3))
    # cached per (t_start, tau, flight): a robust evaluation asks for each toss in turn
    assert model._recorded_start_states(t0, tau, None) is model._recorded_start_states(t0, tau, ball.DEFAULT_FLIGHT)
    # nothing to aim at before the free flight: the toss's own state at t_start
    early = model.recorded_start_state(4, t0, model.t_lift + 0.01)
    assert np.array_equal(early.p, model.recorded_state_at(t0, 4).p)
    with pytest.raises(InvalidInputError, match="outside"):
        model.recorded_start_state(0, t0, 5.0)
    with pytest.raises(InvalidInputError, match="toss index"):
        model.recorded_start_state(99, t0, tau)


def test_local_fit_state_windows_and_refusals() -> None:
    t = np.arange(0.0, 1.0, 0.005)
    p = np.stack([0.1 + 0.2 * t, -0.3 * t, 1.0 + 2.0 * t - 4.9 * t**2], axis=1)
    kw = {"half_window": 0.06, "order": 2}
    for time in (0.0, 0.03, 0.5, 0.99):  # one-sided windows at both ends of the span
        pos, vel = local_fit_state(t, p, time, (0.0, float(t[-1])), **kw)
        assert np.allclose(pos, [0.1 + 0.2 * time, -0.3 * time, 1.0 + 2.0 * time - 4.9 * time**2], atol=1e-12)
        assert np.allclose(vel, [0.2, -0.3, 2.0 - 9.8 * time], atol=1e-9)
    with pytest.raises(InvalidInputError, match="not covered"):
        local_fit_state(t, p, 1.2, (0.0, float(t[-1])), **kw)
    with pytest.raises(InvalidInputError, match="shorter"):
        local_fit_state(t, p, 0.5, (0.45, 0.55), **kw)
    gap = (t < 0.4) | (t > 0.6)
    with pytest.raises(InvalidInputError, match="does not cover"):
        local_fit_state(t[gap], p[gap], 0.5, (0.0, float(t[-1])), **kw)


def test_recording_with_a_gap_at_the_strike_is_refused(robot: Robot, right: TossPrimitive) -> None:
    recs = simulate_tosses(robot, right, 4, np.random.default_rng(8))
    first = recs.recordings[0]
    off = recs.truth[0].clock_offset  # type: ignore[index]
    keep = np.abs(first.t - off - 0.9) > 0.07  # 140 ms without the ball seen around 0.9 s
    holed = TossRecording(toss_id=first.toss_id, t=first.t[keep], p=first.p[keep])
    model = TossModel.from_recordings(right, TossRecordings(recordings=(holed, *recs.recordings[1:]), truth=recs.truth))
    with pytest.raises(InvalidInputError, match=f"{first.toss_id}.*does not cover"):
        model.recorded_state_at(0.9, 0)
    assert np.isfinite(model.recorded_state_at(0.9, 1).p).all()


# ------------------------------------------------------------------------------------
# Shipped defaults
# ------------------------------------------------------------------------------------


@pytest.mark.parametrize("side", TOSS_SIDES)
def test_default_models_load(side: TossSide) -> None:
    path = default_recordings_path(side)
    assert path.is_file() and path.stat().st_size < 300_000
    model = load_default_toss_model(side)
    assert model is load_default_toss_model(side)  # cached
    assert model.side == side and model.n_tosses == DEFAULT_N_TOSSES
    # t_lift of a vertical release scatters by ~2.5 ms (std) over 20 noisy tosses
    assert model.t_lift == pytest.approx(model.primitive.release.time, abs=6e-3)
    y_sign = -1.0 if side == "right" else 1.0
    assert model.mean_state(model.t_lift + 0.3).p[1] == pytest.approx(0.30 * y_sign, abs=0.02)
    apex = float(np.max(model.p[:, 2]))
    assert apex - model.primitive.release.position[2] == pytest.approx(0.35, abs=0.01)
    assert model.t[-1] >= model.t_lift + 0.7
    assert 0.005 < float(np.linalg.norm(model.spread_at(model.t_lift + 0.7))) < 0.025
    report = toss_report(side)
    assert f"toss_{side}: 20 tosses" in report and f"t_lift {model.t_lift:.4f} s" in report and "0.7 s after the lift" in report


def test_generator_is_deterministic(tmp_path: Path) -> None:
    paths = generate_default_recordings(tmp_path, n=2, seed=7)
    first = [p.read_bytes() for p in paths]
    paths = generate_default_recordings(tmp_path, n=2, seed=7)
    assert [p.read_bytes() for p in paths] == first
    assert [p.name for p in paths] == ["right.csv", "left.csv"]


def test_noise_validation() -> None:
    with pytest.raises(InvalidInputError, match="vibration"):
        TossNoise(vibration=-1.0)
    with pytest.raises(InvalidInputError, match="camera_rate"):
        TossNoise(camera_rate=0.0)
    with pytest.raises(InvalidInputError, match="clock_offset"):
        TossNoise(clock_offset=(5.0, 1.0))


def test_t_lift_of_the_shipped_recordings_is_unchanged() -> None:
    """The release-time fit's residuals come from per-recording sums (normal equations);
    the dense least-squares version gave these values (to the last digits)."""
    from studio.toss.defaults import load_default_toss_model

    assert load_default_toss_model("right").t_lift == pytest.approx(0.36278579354291823, abs=1e-9)
    assert load_default_toss_model("left").t_lift == pytest.approx(0.3613239543407857, abs=1e-9)
