"""Scene adapter: pure frame description and the viser mapping, without a browser."""

from __future__ import annotations

import socket

import numpy as np
import pytest
import viser

from studio.robot.model import load_robot
from studio.serve.target import RacketTarget
from studio.ui.scene import (
    Marker,
    PathSegment,
    Playback,
    SceneFrame,
    StudioScene,
    _wxyz_from_z,
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_wxyz_from_z_rotates_z_onto_target() -> None:
    from scipy.spatial.transform import Rotation

    for z in ([1, 0, 0], [0, 0, 1], [0, 0, -1], [0.3, -0.5, 0.8]):
        w, x, y, zq = _wxyz_from_z(z)
        R = Rotation.from_quat([x, y, zq, w]).as_matrix()
        np.testing.assert_allclose(R[:, 2], np.asarray(z) / np.linalg.norm(z), atol=1e-12)


def test_playback_index_clamps() -> None:
    pb = Playback(t=np.array([0.0, 0.1, 0.2]), q=None, ball=np.zeros((3, 3)))
    assert pb.index(-1.0) == 0 and pb.index(0.15) == 1 and pb.index(5.0) == 2


def test_scene_shows_and_replaces_nodes() -> None:
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        scene = StudioScene(server)
        robot = load_robot()
        t = np.linspace(0.0, 1.0, 20)
        path = np.stack([-1.5 + 3 * t, 0 * t, 0.3 - 0.3 * t], axis=1)
        frame = SceneFrame(
            segments=(PathSegment("flight", path, (0, 200, 0)), PathSegment("dot", path[:1], (0, 0, 0))),
            markers=(Marker("b1", (0.0, 0.0, 0.02), (0, 200, 0), "bounce 1"),),
            target=RacketTarget((-1.5, 0.0, 0.3), (1.0, 0.0, 0.0), (4.0, 0.0, 1.0)),
            robot_q=robot.q_flat,
            playback=Playback(t=t, q=np.tile(robot.q_rest, (20, 1)), ball=path),
        )
        scene.show(frame)
        first = len(scene._dynamic)
        # one polyline (the 1-point segment is skipped), marker + label, racket disc + arrows
        assert first == 5
        scene.show(frame)  # replacing must not accumulate nodes
        assert len(scene._dynamic) == first
        scene.show_time(0.5)
        assert scene.ball.visible
        np.testing.assert_allclose(scene.ball.position, path[pb_i := frame.playback.index(0.5)], atol=1e-6)  # type: ignore[union-attr]
        assert pb_i == 9
        scene.set_ball([np.nan, 0.0, 0.0])
        assert not scene.ball.visible
    finally:
        server.stop()


def test_robot_joint_order_matches_urdf() -> None:
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        scene = StudioScene(server)
        names = tuple(scene.urdf._urdf.actuated_joint_names)
        assert names == load_robot().joint_names
    finally:
        server.stop()


@pytest.mark.parametrize("bad", [[np.inf, 0, 0], None])
def test_set_ball_hides_on_bad_position(bad: object) -> None:
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        scene = StudioScene(server)
        scene.set_ball([0.0, 0.0, 0.5])
        scene.set_ball(bad)  # type: ignore[arg-type]
        assert not scene.ball.visible
    finally:
        server.stop()


def test_scene_of_an_evaluation_plays_to_the_second_bounce_with_the_ball_turning() -> None:
    """The playback runs until the ball path ends (the robot held at rest after its
    motion), the ball's orientation follows its spin from the lift, and the spin arrows
    sit at the racket contact and the two bounces."""
    from scipy.spatial.transform import Rotation

    from studio.paths import example_serves_dir
    from studio.serve.evaluate import EvaluationContext, evaluate_serve
    from studio.serve.params import load_serve
    from studio.ui.scene import scene_frame
    from studio.ui.spin import integrate_orientation

    context = EvaluationContext.default()
    ev = evaluate_serve(load_serve(example_serves_dir() / "topspin_right.json"), context)
    frame = scene_frame(ev, context)
    pb = frame.playback
    assert pb is not None and pb.ball_wxyz is not None and pb.q is not None
    assert pb.t[-1] >= ev.ball.t[-1] - 1e-3 and pb.t[-1] >= ev.t[-1]  # the second bounce is in the playback
    assert np.isfinite(pb.ball[pb.index(ev.ball.t[-1] - 0.002)]).all()
    np.testing.assert_allclose(pb.q[-1], ev.q[-1])  # held at rest
    racket = next(e for e in ev.ball.events if e.kind == "racket")
    assert pb.contact_t == racket.t
    # the orientation at a ball sample is the integral of the sampled spin up to it
    k = len(ev.ball.t) // 2
    i = int(np.searchsorted(pb.t, ev.ball.t[k]))
    q_ref = integrate_orientation(ev.ball.t, ev.ball.w)
    from studio.ui.spin import orientation_at

    expected = orientation_at(pb.t[i : i + 1], ev.ball.t, ev.ball.w, q_ref)[0]
    np.testing.assert_allclose(pb.ball_wxyz[i], expected, atol=1e-9)
    before = pb.index(ev.ball.t[0] - 0.01)
    np.testing.assert_allclose(pb.ball_wxyz[before], [1, 0, 0, 0])  # in the cup: not turned
    # over 10 ms after the contact the ball turns by |w| * 10 ms (within the spin's change)
    a, b = pb.index(racket.t + 0.005), pb.index(racket.t + 0.015)
    turned = (Rotation.from_quat(pb.ball_wxyz[b][[1, 2, 3, 0]]) * Rotation.from_quat(pb.ball_wxyz[a][[1, 2, 3, 0]]).inv()).magnitude()
    assert turned == pytest.approx(np.linalg.norm(racket.w_after) * (pb.t[b] - pb.t[a]), rel=0.05)
    assert [a.where for a in frame.spin_arrows] == ["after the racket", "after bounce 1", "after bounce 2"]


def test_ghost_spin_arrows_and_the_turning_ball_in_the_scene() -> None:
    from studio.ui.scene import ghost_frame
    from studio.ui.spin import SpinArrow

    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        scene = StudioScene(server)
        t = np.linspace(0.0, 1.0, 20)
        path = np.stack([-1.5 + 3 * t, 0 * t, 0.3 - 0.3 * t], axis=1)
        wxyz = np.tile([1.0, 0.0, 0.0, 0.0], (20, 1))
        wxyz[10] = [np.cos(0.5), 0.0, np.sin(0.5), 0.0]  # 1 rad about +Y
        arrow = SpinArrow("spin_1", (0.0, 0.0, 0.1), (0.0, 0.1, 0.0), 125.0, 125.0, 0.0, "after bounce 1", "topspin 125, side +0 rad/s")
        frame = SceneFrame(
            segments=(PathSegment("toss", path[:3], (150, 150, 160)), PathSegment("flight", path, (40, 170, 80))),
            markers=(Marker("racket", tuple(path[2]), (245, 130, 20), "racket"), Marker("b1", (0.0, 0.0, 0.02), (40, 170, 80), "bounce 1"), Marker("b2", (1.0, 0.0, 0.02), (40, 170, 80), "bounce 2")),
            playback=Playback(t=t, q=None, ball=path, ball_wxyz=wxyz),
            spin_arrows=(arrow,),
        )
        scene.show(frame)
        assert len(scene._dynamic) == 2 + 6 + 2  # 2 paths, 3 markers + labels, the arrow + its label
        scene.show_time(t[10])
        np.testing.assert_allclose(scene.ball.wxyz, wxyz[10], atol=1e-6)
        np.testing.assert_allclose(scene.ball.position, path[10], atol=1e-6)
        scene.set_ball_scale(3.0)  # bigger ball: same place and turn
        np.testing.assert_allclose(scene.ball.wxyz, wxyz[10], atol=1e-6)
        assert scene.ball.visible and scene.ball_scale == 3.0
        ghost = ghost_frame(frame)
        assert [s.name for s in ghost.segments] == ["flight"]  # not the toss
        assert [m.name for m in ghost.markers] == ["b1", "b2", "label"] and ghost.markers[-1].label == "A (pinned)"
        assert all(m.opacity == 0.45 for m in ghost.markers[:2]) and ghost.markers[-1].radius == 0.0
        assert ghost.segments[0].color != (40, 170, 80)  # faded
        scene.show_ghost(ghost)
        assert scene.ghost_nodes == ("/ghost/flight", "/ghost/markers/b1", "/ghost/markers/b2", "/ghost/labels/label")
        scene.show(frame)  # a new serve keeps the ghost
        assert len(scene.ghost_nodes) == 4
        scene.show_ghost(None)
        assert scene.ghost_nodes == ()
    finally:
        server.stop()


def test_dashed_line_keeps_every_other_piece() -> None:
    from studio.ui.scene import dashed

    pts = np.stack([np.linspace(0.0, 0.3, 31), np.zeros(31), np.zeros(31)], axis=1)  # 1 cm steps
    lines = dashed(pts, dash=0.03)
    assert lines.shape == (15, 2, 3)  # 30 pieces, half of them drawn
    assert dashed(pts[:1]).shape == (0, 2, 3)
