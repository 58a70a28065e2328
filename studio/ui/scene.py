"""The studio's 3D scene: a pure description (:class:`SceneFrame`) and a viser adapter.

The description is built from core results by plain functions and can be tested
without a browser; :class:`StudioScene` only maps a frame onto viser scene nodes
(robot from the URDF, ITTF court, ball path, contact markers, racket target). World
frame of ``DESIGN.md``, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.physics.court import DEFAULT_COURT, Court
from studio.paths import robots_dir
from studio.serve.target import RacketTarget

if TYPE_CHECKING:
    import viser

    from studio.serve.evaluate import Evaluation, EvaluationContext

Rgb = tuple[int, int, int]

COLORS: dict[str, Rgb] = {
    "toss": (150, 150, 160),
    "legal": (40, 170, 80),
    "illegal": (220, 50, 40),
    "unknown": (230, 160, 20),
    "rollout": (60, 110, 220),
    "racket": (245, 130, 20),
    "table": (40, 170, 80),
    "net": (220, 50, 40),
    "post": (220, 50, 40),
    "robot": (200, 0, 200),
    "floor": (110, 110, 110),
    "ball": (250, 250, 245),
    "target_normal": (220, 40, 40),
    "target_velocity": (30, 90, 230),
}
"""Scene colours by role (RGB 0-255)."""


@dataclass(frozen=True, slots=True)
class PathSegment:
    """A polyline of the ball path drawn in one colour."""

    name: str
    """Node name suffix (unique within a frame)."""
    points: npt.NDArray[np.float64]
    """Points (N, 3) [m], world frame."""
    color: Rgb
    """RGB colour."""


@dataclass(frozen=True, slots=True)
class Marker:
    """A small sphere marking a contact or a bounce."""

    name: str
    """Node name suffix (unique within a frame)."""
    position: tuple[float, float, float]
    """Centre [m], world frame."""
    color: Rgb
    """RGB colour."""
    label: str = ""
    """Text shown next to the marker (empty: none)."""


@dataclass(frozen=True, slots=True)
class Playback:
    """Time-synchronous samples for animating a serve."""

    t: npt.NDArray[np.float64]
    """Times (M,) [s]."""
    q: npt.NDArray[np.float64] | None
    """Robot joint positions (M, 8), or None to keep the robot still."""
    ball: npt.NDArray[np.float64]
    """Ball centre (M, 3) [m]; NaN rows hide the ball."""

    def index(self, time: float) -> int:
        """Sample index at or just before ``time`` [s] (clamped)."""
        return int(np.clip(np.searchsorted(self.t, time, side="right") - 1, 0, len(self.t) - 1))


@dataclass(frozen=True, slots=True)
class SceneFrame:
    """Everything the scene shows for one state of the studio."""

    segments: tuple[PathSegment, ...] = ()
    """Ball path pieces."""
    markers: tuple[Marker, ...] = ()
    """Contact and bounce markers."""
    target: RacketTarget | None = None
    """Racket target at contact, if any."""
    robot_q: npt.NDArray[np.float64] | None = None
    """Robot configuration (8,) shown when not playing back."""
    playback: Playback | None = None
    """Samples for the play/scrub controls."""
    extra: dict[str, object] = field(default_factory=dict)
    """Free-form values for GUI panels (not drawn)."""


def _segments_array(points: npt.NDArray[np.float64]) -> npt.NDArray[np.float32]:
    """Polyline (N, 3) -> line segment pairs (N-1, 2, 3)."""
    pts = np.asarray(points, dtype=np.float32)
    return np.stack([pts[:-1], pts[1:]], axis=1)


def _wxyz_from_z(z: npt.ArrayLike) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) rotating +Z onto the unit vector z."""
    z = np.asarray(z, dtype=float)
    z = z / np.linalg.norm(z)
    axis = np.cross([0.0, 0.0, 1.0], z)
    s = float(np.linalg.norm(axis))
    c = float(z[2])
    if s < 1e-12:
        return (1.0, 0.0, 0.0, 0.0) if c > 0 else (0.0, 1.0, 0.0, 0.0)
    angle = np.arctan2(s, c)
    axis = axis / s * np.sin(angle / 2)
    return (float(np.cos(angle / 2)), float(axis[0]), float(axis[1]), float(axis[2]))


class StudioScene:
    """Maps :class:`SceneFrame` objects onto a viser server's scene.

    Args:
        server: the viser server (or anything with its ``scene`` API).
        urdf_path: robot URDF to show; defaults to the shipped serve robot.
        court: court geometry to draw.
    """

    def __init__(self, server: viser.ViserServer, *, urdf_path: Path | None = None, court: Court = DEFAULT_COURT) -> None:
        from viser.extras import ViserUrdf

        self.server = server
        self.court = court
        self._dynamic: list[object] = []
        self._add_court()
        path = urdf_path or robots_dir() / "serve_robot.urdf"
        self.urdf = ViserUrdf(server, path, root_node_name="/robot")
        self.ball = server.scene.add_icosphere("/ball", radius=C.BALL_RADIUS, color=COLORS["ball"], visible=False)
        self.frame: SceneFrame = SceneFrame()

    def _add_court(self) -> None:
        scene = self.server.scene
        scene.set_up_direction("+z")
        c = self.court
        scene.add_grid("/floor", width=8.0, height=6.0, cell_size=0.5, position=(0.0, 0.0, c.floor_z))
        colors = {"table": (20, 60, 140), "net": (235, 235, 235), "post": (40, 40, 40), "leg": (50, 50, 50), "line": (250, 250, 250)}
        for box in (*c.boxes(), *c.legs(), *c.lines()):
            scene.add_box(
                f"/court/{box.name}",
                color=colors.get(box.kind, (128, 128, 128)),
                dimensions=tuple(2 * h for h in box.half_size),
                position=box.center,
                opacity=0.75 if box.kind == "net" else None,
                cast_shadow=False,
            )

    def set_robot(self, q: npt.ArrayLike) -> None:
        """Show the robot at configuration q (8,) (joint order of the URDF)."""
        self.urdf.update_cfg(np.asarray(q, dtype=float))

    def set_ball(self, p: npt.ArrayLike | None) -> None:
        """Place the ball at p (3,) [m], or hide it (None or NaN)."""
        if p is None or not np.all(np.isfinite(p)):
            self.ball.visible = False
            return
        self.ball.position = tuple(float(x) for x in np.asarray(p))
        self.ball.visible = True

    def show(self, frame: SceneFrame) -> None:
        """Replace the dynamic content (paths, markers, target, robot pose) by ``frame``."""
        scene = self.server.scene
        with self.server.atomic():
            for handle in self._dynamic:
                handle.remove()  # type: ignore[attr-defined]
            self._dynamic = []
            for seg in frame.segments:
                if len(seg.points) < 2:
                    continue
                lines = _segments_array(seg.points)
                self._dynamic.append(
                    scene.add_line_segments(f"/path/{seg.name}", points=lines, colors=seg.color, thickness=0.006)
                )
            for m in frame.markers:
                self._dynamic.append(scene.add_icosphere(f"/markers/{m.name}", radius=0.018, color=m.color, position=m.position))
                if m.label:
                    self._dynamic.append(
                        scene.add_label(
                            f"/marker_labels/{m.name}",
                            m.label,
                            position=(m.position[0], m.position[1], m.position[2] + 0.04),
                            font_screen_scale=0.7,
                        )
                    )
            if frame.target is not None:
                tgt = frame.target
                pos = np.asarray(tgt.position)
                self._dynamic.append(
                    scene.add_cylinder(
                        "/target/racket",
                        radius=0.5 * C.RACKET_BLADE_WIDTH,
                        height=2 * C.RACKET_HALF_THICKNESS,
                        color=COLORS["racket"],
                        opacity=0.35,
                        position=tuple(pos),
                        wxyz=_wxyz_from_z(tgt.normal),
                    )
                )
                arrows = np.stack([
                    [pos, pos + 0.15 * np.asarray(tgt.normal)],
                    [pos, pos + 0.05 * np.asarray(tgt.velocity)],
                ])
                arrow_colors = np.array([COLORS["target_normal"], COLORS["target_velocity"]], dtype=np.uint8)
                self._dynamic.append(
                    scene.add_arrows("/target/arrows", points=arrows, colors=arrow_colors, shaft_radius=0.004, head_radius=0.01, head_length=0.025)
                )
            if frame.robot_q is not None:
                self.set_robot(frame.robot_q)
            self.set_ball(None)
        self.frame = frame

    def show_time(self, time: float) -> None:
        """Pose robot and ball at ``time`` [s] of the current frame's playback."""
        pb = self.frame.playback
        if pb is None or len(pb.t) == 0:
            return
        i = pb.index(time)
        with self.server.atomic():
            if pb.q is not None:
                self.set_robot(pb.q[i])
            self.set_ball(pb.ball[i])


def scene_frame(ev: Evaluation, context: EvaluationContext) -> SceneFrame:
    """The 3D scene description of an evaluation (pure; no viser needed)."""
    color = COLORS["legal"] if ev.status == "legal" else COLORS["illegal"]
    segments = [PathSegment("toss", ev.toss_p, COLORS["toss"])]
    markers: list[Marker] = []
    if ev.ball is not None:
        segments.append(PathSegment("flight", ev.ball.p, color))
        bounce = 0
        for k, e in enumerate(ev.ball.events):
            label = e.kind
            if e.kind == "table":
                bounce += 1
                label = f"bounce {bounce}"
            markers.append(Marker(f"event_{k}", tuple(float(x) for x in e.p), COLORS.get(e.kind, COLORS["unknown"]) if e.kind != "table" else color, label))  # type: ignore[arg-type]
    if ev.rollout is not None:
        segments.append(PathSegment("mujoco", np.asarray(ev.rollout.p), COLORS["rollout"]))
    playback = None
    q0 = context.robot.q_flat
    if ev.t is not None and ev.q is not None:
        ball_p = np.full((len(ev.t), 3), np.nan)
        if ev.ball is not None:
            bt = ev.ball.t
            inside = (ev.t >= bt[0]) & (ev.t <= bt[-1])
            for i in range(3):
                ball_p[inside, i] = np.interp(ev.t[inside], bt, ev.ball.p[:, i])
        cup = ev.t < ev.toss_t[-1] if len(ev.toss_t) else np.zeros(len(ev.t), bool)
        for i in range(3):
            ball_p[cup, i] = np.interp(ev.t[cup], ev.toss_t, ev.toss_p[:, i])
        playback = Playback(t=ev.t, q=ev.q, ball=ball_p)
        q0 = ev.q[np.searchsorted(ev.t, ev.serve.params.tau).clip(0, len(ev.t) - 1)]
    return SceneFrame(segments=tuple(segments), markers=tuple(markers), target=ev.target, robot_q=q0, playback=playback)
