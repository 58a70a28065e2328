"""Reward of the paper: spin decomposition on known vectors, terms on known states."""

from __future__ import annotations

import math

import numpy as np
import pytest

from studio.errors import InvalidInputError
from studio.serve.reward import RewardWeights, reward, spin_scalars as spin_components, task_weights, velocity_frame


def test_velocity_frame_is_right_handed_and_horizontal() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        v = rng.normal(size=3)
        f = velocity_frame(v)
        np.testing.assert_allclose(f @ f.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(f) == pytest.approx(1.0)
        assert f[1, 2] == pytest.approx(0.0, abs=1e-12)  # e_y horizontal
        assert f[2, 2] >= 0.0  # e_z points up
        np.testing.assert_allclose(f[0], v / np.linalg.norm(v))


def test_spin_components_known_vectors() -> None:
    v = [5.0, 0.0, 0.0]
    assert spin_components(v, [0, 100, 0]) == pytest.approx((100, 0, 0))  # topspin
    assert spin_components(v, [0, -80, 0]) == pytest.approx((-80, 0, 0))  # backspin
    assert spin_components(v, [0, 0, 50]) == pytest.approx((0, 50, 0))  # sidespin
    assert spin_components(v, [30, 0, 0]) == pytest.approx((0, 0, 30))  # cork
    # travelling -Y: e_x = -Y, e_y = z x (-y) = +X
    assert spin_components([0, -3, 0], [70, 0, 0])[0] == pytest.approx(70)
    # rising ball: e_z tilts back, sidespin mixes with cork
    tb, ss, ck = spin_components([1.0, 0.0, 1.0], [0.0, 0.0, 100.0])
    assert tb == pytest.approx(0) and ss == pytest.approx(100 / math.sqrt(2)) and ck == pytest.approx(100 / math.sqrt(2))


def test_reward_terms() -> None:
    w = RewardWeights(g_top=1.0, g_back=2.0, g_side=1.0, side_direction=-1, spin_max=400)
    top = reward(p2=[1, 0, 0], v2=[4, 0, 1], w2=[0, 200, 0], max_height=0.2, weights=w)
    assert top.r_topback == pytest.approx(0.5) and top.r_side == 0.0
    back = reward(p2=[1, 0, 0], v2=[4, 0, 0], w2=[0, -1000, 0], max_height=0.2, weights=w)
    assert back.r_topback == pytest.approx(2.0)  # clamped at -w_bar, times g_back
    left = reward(p2=[1, 0, 0], v2=[4, 0, 0], w2=[0, 0, -200], max_height=0.2, weights=w)
    right = reward(p2=[1, 0, 0], v2=[4, 0, 0], w2=[0, 0, 200], max_height=0.2, weights=w)
    assert left.r_side == pytest.approx(0.5) and right.r_side == 0.0
    either = RewardWeights(g_side=1.0, spin_max=400)
    assert reward(p2=[1, 0, 0], v2=[4, 0, 0], w2=[0, 0, 200], max_height=0.2, weights=either).r_side == pytest.approx(0.5)


def test_position_velocity_height_terms() -> None:
    w = RewardWeights(g_pos=2.0, target=(1.0, 0.5), pos_sigma=0.1, g_vel_xy=1.0, g_vel_z=-1.0, g_height=1.0, h_ref=0.1)
    on = reward(p2=[1.0, 0.5, 0.02], v2=[3, 4, 2.5], w2=[0, 0, 0], max_height=0.05, weights=w)
    assert on.r_pos == pytest.approx(2.0)
    assert on.r_vel == pytest.approx(5 / 10 - 2.5 / 5)
    assert on.r_height == pytest.approx(1.0)
    off = reward(p2=[1.1, 0.5, 0.02], v2=[3, 4, 2.5], w2=[0, 0, 0], max_height=0.4, weights=w)
    assert off.r_pos == pytest.approx(2.0 * math.exp(-1.0))  # d = 0.1 m = sigma
    assert off.r_height == pytest.approx(0.25)
    assert on.total == pytest.approx(on.r_pos + on.r_vel + on.r_height)


def test_tasks_and_bad_input() -> None:
    assert task_weights("backspin").g_back > 0 and task_weights("backspin", low=False).g_height == 0
    with pytest.raises(InvalidInputError, match="unknown task 'lob'"):
        task_weights("lob")
    with pytest.raises(InvalidInputError, match="g_top"):
        RewardWeights(g_top=-1)
    with pytest.raises(InvalidInputError, match="finite"):
        reward(p2=[np.nan, 0, 0], v2=[1, 0, 0], w2=[0, 0, 0], max_height=0.1, weights=RewardWeights())


def test_spin_at_net_rewards_the_net_crossing_spin() -> None:
    """The backspin a receiver reads at the net, not the rolling spin after the bounce."""
    after = dict(p2=[1.0, 0.0, 0.0], v2=[3.0, 0.0, 2.0], w2=[0.0, 150.0, 0.0], max_height=0.1)  # rolling topspin
    paper = reward(**after, weights=task_weights("backspin"))
    assert paper.r_topback == 0.0  # topspin after the bounce: no backspin reward
    net = reward(**after, weights=task_weights("backspin_net"), v_net=[4.0, 0.0, -1.0], w_net=[0.0, -250.0, 0.0])
    assert net.r_topback == pytest.approx(250.0 / 500.0)  # g_back * |w_tb| / w_bar at the net
    assert net.r_height == paper.r_height and net.r_vel == paper.r_vel == 0.0
    with pytest.raises(InvalidInputError, match="net crossing"):
        reward(**after, weights=task_weights("backspin_net"))
    with pytest.raises(InvalidInputError, match="finite 3-vectors"):
        reward(**after, weights=task_weights("backspin_net"), v_net=[4.0, 0.0, np.nan], w_net=[0.0, -250.0, 0.0])
    spin = reward(**after, weights=task_weights("spin_net"), v_net=[4.0, 0.0, 0.0], w_net=[0.0, -250.0, 400.0])
    assert spin.r_topback + spin.r_side == pytest.approx((250.0 + 400.0) / 1000.0)  # any direction, not clamped at 500
    with pytest.raises(InvalidInputError, match="spin_at"):
        RewardWeights(spin_at="apex")  # type: ignore[arg-type]


def test_signed_spin_form_has_a_slope_through_topspin() -> None:
    """``spin_form="signed"``: r_back rises as topspin falls (the paper's form is flat there),
    stays in [0, g_back] and keeps every legal serve above every illegal one."""
    state = dict(p2=[1.0, 0.0, 0.0], v2=[3.0, 0.0, 1.0], max_height=0.2)
    signed, paper = task_weights("backspin_signed"), task_weights("backspin")
    spins = (600.0, 300.0, 150.0, 0.0, -100.0, -300.0, -800.0)
    r_signed = [reward(**state, w2=[0.0, s, 0.0], weights=signed).r_topback for s in spins]
    r_paper = [reward(**state, w2=[0.0, s, 0.0], weights=paper).r_topback for s in spins]
    assert r_paper[:4] == [0.0] * 4  # the paper's one-sided term: no slope on topspin serves
    assert np.all(np.diff(r_signed) > 0.0)
    assert r_signed[0] == 0.0 and r_signed[-1] == pytest.approx(1.0)  # clamped at +-w_bar = 500 rad/s
    assert r_signed[3] == pytest.approx(0.5) and r_signed[5] == pytest.approx(0.8)  # (1 - w_tb/500) / 2
    top = RewardWeights(g_top=2.0, spin_form="signed")
    assert reward(**state, w2=[0.0, 250.0, 0.0], weights=top).r_topback == pytest.approx(2.0 * 0.75)
    with pytest.raises(InvalidInputError, match="spin_form"):
        RewardWeights(spin_form="linear")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="one direction"):
        RewardWeights(g_top=1.0, g_back=1.0, spin_form="signed")  # a constant: no signal at all
    # every legal serve (r >= 0 here) scores above every illegal one (s_leg <= -0.1, rules.py)
    assert min(r_signed) >= 0.0
