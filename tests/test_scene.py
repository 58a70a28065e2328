"""Scene adapter: pure frame description and the viser mapping, without a browser."""

from __future__ import annotations

import socket

import numpy as np
import pytest
import viser

from studio.robot.model import load_robot
from studio.serve.target import RacketTarget
from studio.ui.scene import Marker, PathSegment, Playback, SceneFrame, StudioScene, _wxyz_from_z


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
