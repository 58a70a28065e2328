"""Camera presets of the studio's 3D view.

World frame (``docs/frames-and-units.md``): origin at the centre of the table top, +X
towards the receiver, +Z up, table top at z = 0, the server's end line at
x = -1.37 m and the receiver's at +1.37 m. Positions and look-at points in metres.

- ``receiver``: the receiver's eyes, 0.93 m behind the far end line (x = +2.3 m) and 0.5 m
  above the table (a crouched receiver), looking at the server's racket contact;
- ``side``: from the side of the table (-Y), robot to receiver end in view;
- ``top``: from above, X across the screen;
- ``robot``: over the robot's shoulder, behind the gantry, looking down the table;
- ``default``: the view that shows robot, table and the ball path together
  (:func:`fit_view` of their points, from behind the server's side).

:func:`apply_camera` moves a connected browser's camera (viser ``client.camera``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from studio.physics.court import DEFAULT_COURT

FOV = math.radians(75.0)
"""viser's default vertical field of view [rad]."""

ASPECT = 1.2
"""Width/height of the 3D view assumed for framing (the canvas beside the control panel)."""

DEFAULT_DIRECTION = (-0.50, -0.78, 0.40)
"""Direction from the framed centre to the default camera (behind the server, to its
right, above): the robot in front, the ball flying away from the viewer."""

ROBOT_BOX = ((-2.45, -1.30, DEFAULT_COURT.floor_z), (-1.25, 1.30, 0.95))
"""Box around the robot and its gantry (min corner, max corner) [m] (gantry base at
x = -2 m on the floor, rails at y = +/-1.25 m, the arm up to ~0.9 m above the table)."""


@dataclass(frozen=True, slots=True)
class CameraView:
    """A camera pose: where it is and what it looks at."""

    name: str
    """Preset name shown on its button."""
    position: tuple[float, float, float]
    """Camera position [m], world frame."""
    look_at: tuple[float, float, float]
    """Point at the centre of the view [m], world frame."""
    fov: float = FOV
    """Vertical field of view [rad]."""


def table_points() -> npt.NDArray[np.float64]:
    """The table top's corners and the net posts' tops (6, 3) [m]."""
    c = DEFAULT_COURT
    hx, hy = c.half_length, c.half_width
    corners = [(sx * hx, sy * hy, 0.0) for sx in (-1, 1) for sy in (-1, 1)]
    posts = [(0.0, sy * (hy + c.net_post_offset), c.net_height) for sy in (-1, 1)]
    return np.array(corners + posts, dtype=float)


def robot_points() -> npt.NDArray[np.float64]:
    """Corners of :data:`ROBOT_BOX` (8, 3) [m]."""
    lo, hi = ROBOT_BOX
    return np.array([(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], dtype=float)


def fit_view(
    points: npt.ArrayLike,
    *,
    direction: tuple[float, float, float] = DEFAULT_DIRECTION,
    fov: float = FOV,
    aspect: float = ASPECT,
    margin: float = 1.05,
    name: str = "default",
) -> CameraView:
    """A camera looking along ``-direction`` at the centre of ``points`` (N, 3) [m], far
    enough that all of them are inside the view cone (vertical ``fov`` [rad]; the
    horizontal one from ``aspect``), with ``margin`` (> 1: room around them)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        raise ValueError("fit_view: no finite points to frame")
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    half = min(fov / 2, math.atan(math.tan(fov / 2) * aspect))  # the narrower half-angle
    # each point's distance from the viewing axis and along it: the camera must stand back
    # far enough that the point's angle off the axis stays within the half-angle
    rel = pts - centre
    along = rel @ d
    off = np.linalg.norm(rel - along[:, None] * d, axis=1)
    distance = float(np.max(along + off / math.tan(half))) * margin
    distance = max(distance, 0.5)
    pos = centre + distance * d
    return CameraView(name, tuple(float(x) for x in pos), tuple(float(x) for x in centre), fov)  # type: ignore[arg-type]


def default_view(ball_path: npt.ArrayLike | None = None) -> CameraView:
    """The default framing: robot, table and (if given) the ball path (N, 3) [m] together."""
    pts = [robot_points(), table_points()]
    if ball_path is not None and len(np.asarray(ball_path)):
        path = np.asarray(ball_path, dtype=float).reshape(-1, 3)
        pts.append(path[np.all(np.isfinite(path), axis=1)])
    return fit_view(np.concatenate(pts))


RECEIVER_EYE = (2.3, 0.0, 0.5)
"""The receiver's eyes [m]: 0.93 m behind the far end line, 0.5 m above the table."""

RECEIVER_FOV = math.radians(50.0)
"""The receiver view's vertical field of view [rad]: narrower than the default, the
server's half of the table fills more of the view (as a player's attention does)."""

PRESETS: dict[str, CameraView] = {
    "receiver": CameraView("receiver", RECEIVER_EYE, (-1.3, 0.0, 0.2), RECEIVER_FOV),
    "side": CameraView("side", (-0.45, -4.3, 0.75), (-0.45, 0.0, 0.0)),
    "top": CameraView("top", (-0.45, -0.08, 4.6), (-0.45, 0.0, 0.0)),  # a hair off vertical: the orbit's pole is +Z
    "robot": CameraView("robot", (-3.2, 0.55, 1.6), (0.3, 0.0, 0.0)),
}
"""The fixed presets (``default`` is computed per serve by :func:`default_view`)."""

VIEW_NAMES = ("default", "receiver", "side", "top", "robot")
"""Preset names in button order."""


def view_named(name: str, ball_path: npt.ArrayLike | None = None) -> CameraView:
    """The preset ``name`` (one of :data:`VIEW_NAMES`); ``default`` frames ``ball_path``."""
    if name == "default":
        return default_view(ball_path)
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown view {name!r} (one of {VIEW_NAMES})") from None


def apply_camera(client: Any, view: CameraView) -> None:
    """Move a viser client's camera to ``view`` (position first: viser moves the look-at
    point along with the position, so the look-at point is set after it)."""
    with client.atomic():
        client.camera.up_direction = (0.0, 0.0, 1.0)
        client.camera.fov = view.fov
        client.camera.position = view.position
        client.camera.look_at = view.look_at


def set_initial_camera(server: Any, view: CameraView) -> None:
    """Make ``view`` the pose new browser tabs open with (and "Reset view" returns to)."""
    server.initial_camera.position = view.position
    server.initial_camera.look_at = view.look_at
    server.initial_camera.fov = view.fov
