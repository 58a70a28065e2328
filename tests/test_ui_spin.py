"""Spin made visible (studio.ui.spin): orientation integrated from w(t), seam, spin arrows."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from studio.physics.ball import Event, Trajectory, spin_components
from studio.ui.spin import (
    ARROW_LENGTH_PER_SPIN,
    ARROW_LENGTH_RANGE,
    LOGO_DIRECTION,
    integrate_orientation,
    orientation_at,
    quat_from_rotvec,
    quat_multiply,
    rotate,
    seam_points,
    spin_arrows,
)


def _as_rotation(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])  # scipy is scalar-last


def test_constant_spin_turns_the_ball_by_w_times_t() -> None:
    """100 rad/s of topspin about +Y for 0.1 s: 10 rad about +Y (the seam is carried along)."""
    t = np.linspace(0.0, 0.1, 101)
    w = np.tile([0.0, 100.0, 0.0], (len(t), 1))
    q = integrate_orientation(t, w)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    expected = Rotation.from_rotvec([0.0, 10.0, 0.0])
    assert (_as_rotation(q[-1]) * expected.inv()).magnitude() < 1e-9
    # a seam point on +X after a quarter turn about +Y (t = pi/200 s) points along -Z
    k = int(np.argmin(np.abs(t - np.pi / 200)))
    np.testing.assert_allclose(rotate(q[k], [1.0, 0.0, 0.0]), _as_rotation(q[k]).apply([1.0, 0.0, 0.0]), atol=1e-12)


def test_a_changing_axis_composes_in_the_world_frame() -> None:
    """Spin about +Z, then about +X: the world-frame composition R_x(1) R_z(2), not the reverse."""
    t = np.array([0.0, 0.01, 0.01, 0.02])  # a repeated time (a bounce) adds no turn
    w = np.array([[0.0, 0.0, 200.0], [0.0, 0.0, 200.0], [100.0, 0.0, 0.0], [100.0, 0.0, 0.0]])
    q = integrate_orientation(t, w)
    expected = Rotation.from_rotvec([1.0, 0.0, 0.0]) * Rotation.from_rotvec([0.0, 0.0, 2.0])
    assert (_as_rotation(q[-1]) * expected.inv()).magnitude() < 1e-9
    wrong = Rotation.from_rotvec([0.0, 0.0, 2.0]) * Rotation.from_rotvec([1.0, 0.0, 0.0])
    assert (_as_rotation(q[-1]) * wrong.inv()).magnitude() > 0.5


def test_orientation_between_samples_turns_on_at_the_sample_spin() -> None:
    t = np.array([0.0, 0.1])
    w = np.array([[0.0, 0.0, 50.0], [0.0, 0.0, 50.0]])
    q = integrate_orientation(t, w)
    out = orientation_at(np.array([-1.0, 0.05, 0.1, 5.0]), t, w, q)
    for got, angle in zip(out, (0.0, 2.5, 5.0, 5.0)):  # before: the first; after: held at the last
        assert (_as_rotation(got) * Rotation.from_rotvec([0.0, 0.0, angle]).inv()).magnitude() < 1e-9


def test_quaternion_helpers_agree_with_scipy() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 3))
    qa, qb = quat_from_rotvec(a), quat_from_rotvec(b)
    ra, rb = Rotation.from_rotvec(a), Rotation.from_rotvec(b)
    assert (_as_rotation(quat_multiply(qa, qb)) * (ra * rb).inv()).magnitude() < 1e-12
    assert (_as_rotation(quat_from_rotvec([1e-14, 0, 0])).magnitude()) < 1e-12


def test_seam_lies_on_the_ball_and_the_logo_sits_in_a_lobe() -> None:
    seam = seam_points(200)
    np.testing.assert_allclose(np.linalg.norm(seam, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(seam[0], seam[-1], atol=1e-12)  # closed
    assert np.ptp(seam[:, 2]) > 1.5  # not planar: a turn about any axis moves it
    logo = np.asarray(LOGO_DIRECTION)
    assert np.linalg.norm(logo) == pytest.approx(1.0)
    assert np.degrees(np.arccos(np.clip(seam @ logo, -1, 1))).min() > 40.0


def _event(kind: str, t: float, p: list[float], v: list[float], w: list[float]) -> Event:
    a = np.asarray
    return Event(kind, t, a(p, float), a(v, float), a(v, float), a(w, float), a(w, float), "top", a([0, 0, 1.0]))  # type: ignore[arg-type]


def test_spin_arrows_at_the_racket_and_after_each_bounce() -> None:
    """Arrow along w (right-hand rule), 12 cm per 150 rad/s, labelled with the components."""
    events = (
        _event("table", 0.1, [-1.0, 0, 0.02], [0, 0, 1.0], [0, 0, 0]),  # before the strike: no arrow
        _event("racket", 0.2, [-1.5, 0, 0.25], [4.0, 0, 0], [0, 150.0, 0]),
        _event("table", 0.4, [-0.5, 0, 0.02], [4.0, 0, 1.0], [0, -300.0, 30.0]),
        _event("table", 0.7, [0.8, 0, 0.02], [3.0, 0, 1.0], [0, 1.0, 0.0]),
    )
    traj = Trajectory(np.zeros(2), np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), events, "max_table_bounces")
    arrows = spin_arrows(traj)
    assert [a.where for a in arrows] == ["after the racket", "after bounce 1", "after bounce 2"]
    racket, b1, b2 = arrows
    np.testing.assert_allclose(racket.vector, [0.0, 150.0 * ARROW_LENGTH_PER_SPIN, 0.0])
    assert racket.topspin == pytest.approx(150.0) and racket.label == "topspin 150, side +0 rad/s"
    tb, ss, _ = spin_components([4.0, 0, 1.0], [0, -300.0, 30.0])
    assert b1.topspin == pytest.approx(float(tb)) and b1.sidespin == pytest.approx(float(ss)) and b1.label.startswith("backspin ")
    assert np.linalg.norm(b1.vector) == pytest.approx(np.hypot(300.0, 30.0) * ARROW_LENGTH_PER_SPIN)
    assert np.linalg.norm(b2.vector) == pytest.approx(ARROW_LENGTH_RANGE[0])  # a weak spin keeps a visible arrow
    assert b2.origin == (0.8, 0.0, 0.02)
