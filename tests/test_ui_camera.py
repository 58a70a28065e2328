"""Camera presets (studio.ui.camera): the receiver's eyes, framing robot, table and ball."""

from __future__ import annotations

import math

import numpy as np
import pytest

from studio.physics.court import DEFAULT_COURT
from studio.ui.camera import (
    FOV,
    PRESETS,
    RECEIVER_EYE,
    VIEW_NAMES,
    apply_camera,
    default_view,
    fit_view,
    robot_points,
    table_points,
    view_named,
)


def _inside_cone(view, points: np.ndarray, half_angle: float) -> bool:  # type: ignore[no-untyped-def]
    axis = np.subtract(view.look_at, view.position)
    axis = axis / np.linalg.norm(axis)
    rel = points - np.asarray(view.position)
    cos = rel @ axis / np.linalg.norm(rel, axis=1)
    return bool(np.all(cos >= math.cos(half_angle) - 1e-9))


def test_receiver_view_is_behind_the_far_end_line_at_eye_height() -> None:
    v = view_named("receiver")
    x, y, z = v.position
    assert x == pytest.approx(2.3) and x > DEFAULT_COURT.half_length + 0.5 and y == 0.0 and 0.4 <= z <= 0.6
    assert v.position == RECEIVER_EYE
    assert v.look_at[0] < -DEFAULT_COURT.half_length + 0.2  # looks at the server's end, where the racket meets the ball
    assert _inside_cone(v, table_points()[:4], math.radians(89))  # the table is in front


def test_side_top_and_robot_views_see_the_table() -> None:
    for name in ("side", "top", "robot"):
        v = view_named(name)
        assert _inside_cone(v, table_points(), FOV / 2), name
    assert view_named("top").position[2] > 4.0 and view_named("side").position[1] < -3.0
    assert view_named("robot").position[0] < -2.5  # behind the gantry (x = -2 m)
    with pytest.raises(ValueError):
        view_named("ceiling")
    assert set(VIEW_NAMES) == {"default", *PRESETS}


def test_fit_view_keeps_every_point_in_the_view_cone() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(-2, 2, size=(50, 3))
    v = fit_view(pts, aspect=1.0)
    assert _inside_cone(v, pts, FOV / 2)
    np.testing.assert_allclose(v.look_at, 0.5 * (pts.min(0) + pts.max(0)))
    closer = fit_view(pts, aspect=1.0, margin=0.7)  # too close: some point leaves the cone
    assert not _inside_cone(closer, pts, FOV / 2)


def test_default_view_frames_robot_table_and_ball_path() -> None:
    path = np.stack([np.linspace(-1.6, 1.9, 30), np.linspace(0.0, 0.5, 30), 0.3 * np.ones(30)], axis=1)
    v = default_view(path)
    everything = np.concatenate([robot_points(), table_points(), path])
    assert _inside_cone(v, everything, FOV / 2 * 0.999)
    assert v.position[0] < v.look_at[0]  # from behind the server
    assert default_view(None).position != v.position  # the path widens the framing


def test_apply_camera_sets_position_then_look_at() -> None:
    calls: list[tuple[str, object]] = []

    class Camera:
        def __setattr__(self, name: str, value: object) -> None:
            calls.append((name, value))

    class Client:
        camera = Camera()

        def atomic(self):  # type: ignore[no-untyped-def]
            from contextlib import nullcontext

            return nullcontext()

    v = view_named("receiver")
    apply_camera(Client(), v)
    names = [n for n, _ in calls]
    assert names.index("position") < names.index("look_at")  # viser moves look_at with the position
    assert dict(calls)["position"] == v.position and dict(calls)["look_at"] == v.look_at and dict(calls)["fov"] == v.fov
