"""The studio's 3D scene: a pure description (:class:`SceneFrame`) and a viser adapter.

The description is built from core results by plain functions and can be tested
without a browser; :class:`StudioScene` only maps a frame onto viser scene nodes
(robot from the URDF, ITTF court, ball path, contact markers, racket target, spin-axis
arrows, the ball with its seam turning at the simulated spin, and the pinned serve's
path as a dashed ghost). World frame of ``docs/frames-and-units.md``: origin at the
centre of the table top, +X towards the receiver, +Z up; metres, seconds, rad/s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.paths import robots_dir
from studio.physics.court import DEFAULT_COURT, Court
from studio.serve.target import RacketTarget
from studio.ui.spin import (
    LOGO_DIRECTION,
    SPIN_ARROW_COLOR,
    SpinArrow,
    integrate_orientation,
    orientation_at,
    seam_points,
    spin_arrows,
)

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
    "seam": (200, 30, 40),
    "logo": (20, 20, 20),
    "ghost": (120, 120, 135),
}
"""Scene colours by role (RGB 0-255)."""

GHOST_DASH = 0.03
"""Length of the dashes (and gaps) of the pinned serve's ghost path [m]."""


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
    radius: float = 0.018
    """Sphere radius [m] (0: the label alone)."""
    opacity: float | None = None
    """Opacity in [0, 1] (None: opaque)."""


@dataclass(frozen=True, slots=True)
class Playback:
    """Time-synchronous samples for animating a serve."""

    t: npt.NDArray[np.float64]
    """Times (M,) [s]."""
    q: npt.NDArray[np.float64] | None
    """Robot joint positions (M, 8), or None to keep the robot still."""
    ball: npt.NDArray[np.float64]
    """Ball centre (M, 3) [m]; NaN rows hide the ball."""
    ball_wxyz: npt.NDArray[np.float64] | None = None
    """Ball orientation (M, 4) (w, x, y, z), integrated from the simulated spin (the seam
    turns with it); None: not turned."""
    contact_t: float | None = None
    """Racket contact time [s] (slow-motion replays start just before it), if struck."""

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
    spin_arrows: tuple[SpinArrow, ...] = ()
    """Spin-axis arrows at the racket contact and after each bounce."""
    extra: dict[str, object] = field(default_factory=dict)
    """Free-form values for GUI panels (not drawn)."""


def _segments_array(points: npt.NDArray[np.float64]) -> npt.NDArray[np.float32]:
    """Polyline (N, 3) -> line segment pairs (N-1, 2, 3)."""
    pts = np.asarray(points, dtype=np.float32)
    return np.stack([pts[:-1], pts[1:]], axis=1)


def _wxyz_from_z(z: npt.ArrayLike) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) rotating +Z onto the unit vector z."""
    u = np.asarray(z, dtype=float)
    u = u / np.linalg.norm(u)
    axis = np.cross([0.0, 0.0, 1.0], u)
    s = float(np.linalg.norm(axis))
    c = float(u[2])
    if s < 1e-12:
        return (1.0, 0.0, 0.0, 0.0) if c > 0 else (0.0, 1.0, 0.0, 0.0)
    angle = np.arctan2(s, c)
    axis = axis / s * np.sin(angle / 2)
    return (float(np.cos(angle / 2)), float(axis[0]), float(axis[1]), float(axis[2]))


def dashed(points: npt.ArrayLike, dash: float = GHOST_DASH) -> npt.NDArray[np.float32]:
    """Every other piece of length ``dash`` [m] of a polyline (N, 3), as line segment
    pairs (K, 2, 3): a dashed line (the sample spacing sets the resolution)."""
    pts = np.asarray(points, dtype=float)
    if len(pts) < 2:
        return np.zeros((0, 2, 3), dtype=np.float32)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    on = (np.floor(0.5 * (s[:-1] + s[1:]) / dash) % 2) == 0
    return _segments_array(pts)[on]


BALL_MAGNIFICATIONS = {"true size": 1.0, "x2": 2.0, "x3": 3.0, "x5": 5.0}
"""Ball sizes offered for watching the seam turn (the ball is 40 mm across)."""


class StudioScene:
    """Maps :class:`SceneFrame` objects onto a viser server's scene.

    Args:
        server: the viser server (or anything with its ``scene`` API).
        urdf_path: robot URDF to show; defaults to the shipped serve robot.
        court: court geometry to draw.
    """

    def __init__(
        self, server: viser.ViserServer, *, urdf_path: Path | None = None, court: Court = DEFAULT_COURT
    ) -> None:
        from viser.extras import ViserUrdf

        self.server = server
        self.court = court
        self._dynamic: list[object] = []
        self._ghost: list[object] = []
        self._add_court()
        path = urdf_path or robots_dir() / "serve_robot.urdf"
        self.urdf = ViserUrdf(server, path, root_node_name="/robot")
        self.ball_scale = 1.0
        self.ball = self._add_ball(self.ball_scale)
        self.frame: SceneFrame = SceneFrame()

    def _add_court(self) -> None:
        scene = self.server.scene
        scene.set_up_direction("+z")
        c = self.court
        scene.add_grid("/floor", width=8.0, height=6.0, cell_size=0.5, position=(0.0, 0.0, c.floor_z))
        colors = {
            "table": (20, 60, 140),
            "net": (235, 235, 235),
            "post": (40, 40, 40),
            "leg": (50, 50, 50),
            "line": (250, 250, 250),
        }
        for box in (*c.boxes(), *c.legs(), *c.lines()):
            hx, hy, hz = box.half_size
            scene.add_box(
                f"/court/{box.name}",
                color=colors.get(box.kind, (128, 128, 128)),
                dimensions=(2 * hx, 2 * hy, 2 * hz),
                position=box.center,
                opacity=0.75 if box.kind == "net" else None,
                cast_shadow=False,
            )

    def _add_ball(self, scale: float) -> Any:
        """The ball: a frame (placed and turned by :meth:`set_ball`) holding a white sphere,
        a red seam and a black logo dot, drawn ``scale`` times its size."""
        scene = self.server.scene
        r = C.BALL_RADIUS
        ball = scene.add_frame("/ball", show_axes=False, scale=scale, visible=False)
        scene.add_icosphere("/ball/body", radius=r, color=COLORS["ball"], subdivisions=3)
        seam = _segments_array(1.02 * r * seam_points(72))
        scene.add_line_segments(
            "/ball/seam", points=seam, colors=COLORS["seam"], thickness=0.12 * r, thickness_units="world"
        )  # scaled with the frame
        scene.add_icosphere(
            "/ball/logo", radius=0.3 * r, color=COLORS["logo"], position=tuple(0.8 * r * np.asarray(LOGO_DIRECTION))
        )
        return ball

    def set_ball_scale(self, scale: float) -> None:
        """Draw the ball ``scale`` times its true size (its place and turn are kept)."""
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"ball scale must be a positive number, got {scale!r}")
        old = self.ball
        position, wxyz, visible = old.position, old.wxyz, old.visible
        with self.server.atomic():
            old.remove()
            self.ball_scale = float(scale)
            self.ball = self._add_ball(self.ball_scale)
            self.ball.position, self.ball.wxyz, self.ball.visible = position, wxyz, visible

    def set_robot(self, q: npt.ArrayLike) -> None:
        """Show the robot at configuration q (8,) (joint order of the URDF)."""
        self.urdf.update_cfg(np.asarray(q, dtype=float))

    def set_ball(self, p: npt.ArrayLike | None, wxyz: npt.ArrayLike | None = None) -> None:
        """Place the ball at p (3,) [m] turned by ``wxyz`` (w, x, y, z; None: unchanged),
        or hide it (None or NaN)."""
        if p is None or not np.all(np.isfinite(p)):
            self.ball.visible = False
            return
        self.ball.position = tuple(float(x) for x in np.asarray(p))
        if wxyz is not None and np.all(np.isfinite(wxyz)):
            self.ball.wxyz = tuple(float(x) for x in np.asarray(wxyz))
        self.ball.visible = True

    def show(self, frame: SceneFrame) -> None:
        """Replace the dynamic content (paths, markers, target, spin arrows, robot pose) by ``frame``."""
        with self.server.atomic():
            for handle in self._dynamic:
                handle.remove()  # type: ignore[attr-defined]
            self._dynamic = []
            self._dynamic.extend(self._add_paths("/path", frame.segments))
            self._dynamic.extend(self._add_markers("/markers", "/marker_labels", frame.markers))
            if frame.target is not None:
                self._dynamic.extend(self._add_target(frame.target))
            self._dynamic.extend(self._add_spin_arrows(frame.spin_arrows))
            if frame.robot_q is not None:
                self.set_robot(frame.robot_q)
            self.set_ball(None)
        self.frame = frame

    def show_ghost(self, frame: SceneFrame | None) -> None:
        """Draw ``frame`` (a :func:`ghost_frame`) as the pinned serve's ghost; None removes it."""
        with self.server.atomic():
            for handle in self._ghost:
                handle.remove()  # type: ignore[attr-defined]
            self._ghost = []
            if frame is None:
                return
            scene = self.server.scene
            for seg in frame.segments:
                lines = dashed(seg.points)
                if len(lines):
                    self._ghost.append(
                        scene.add_line_segments(f"/ghost/{seg.name}", points=lines, colors=seg.color, thickness=0.005)
                    )
            self._ghost.extend(self._add_markers("/ghost/markers", "/ghost/labels", frame.markers))

    @property
    def ghost_nodes(self) -> tuple[str, ...]:
        """Names of the ghost's scene nodes (empty: no ghost drawn)."""
        return tuple(str(h.name) for h in self._ghost)  # type: ignore[attr-defined]

    def _add_paths(self, root: str, segments: tuple[PathSegment, ...]) -> list[object]:
        scene = self.server.scene
        return [
            scene.add_line_segments(
                f"{root}/{seg.name}", points=_segments_array(seg.points), colors=seg.color, thickness=0.006
            )
            for seg in segments
            if len(seg.points) >= 2
        ]

    def _add_markers(self, root: str, label_root: str, markers: tuple[Marker, ...]) -> list[object]:
        scene = self.server.scene
        out: list[object] = []
        for m in markers:
            if m.radius > 0:
                out.append(
                    scene.add_icosphere(
                        f"{root}/{m.name}", radius=m.radius, color=m.color, position=m.position, opacity=m.opacity
                    )
                )
            if m.label:
                where = (m.position[0], m.position[1], m.position[2] + 0.04)
                out.append(scene.add_label(f"{label_root}/{m.name}", m.label, position=where, font_screen_scale=0.7))
        return out

    def _add_target(self, tgt: RacketTarget) -> list[object]:
        scene = self.server.scene
        pos = np.asarray(tgt.position)
        disc = scene.add_cylinder(
            "/target/racket",
            radius=0.5 * C.RACKET_BLADE_WIDTH,
            height=2 * C.RACKET_HALF_THICKNESS,
            color=COLORS["racket"],
            opacity=0.35,
            position=tuple(pos),
            wxyz=_wxyz_from_z(tgt.normal),
        )
        arrows = np.stack([[pos, pos + 0.15 * np.asarray(tgt.normal)], [pos, pos + 0.05 * np.asarray(tgt.velocity)]])
        arrow_colors = np.array([COLORS["target_normal"], COLORS["target_velocity"]], dtype=np.uint8)
        return [
            disc,
            scene.add_arrows(
                "/target/arrows",
                points=arrows,
                colors=arrow_colors,
                shaft_radius=0.004,
                head_radius=0.01,
                head_length=0.025,
            ),
        ]

    def _add_spin_arrows(self, arrows: tuple[SpinArrow, ...]) -> list[object]:
        scene = self.server.scene
        out: list[object] = []
        for a in arrows:
            start = np.asarray(a.origin)
            tip = start + np.asarray(a.vector)
            out.append(
                scene.add_arrows(
                    f"/spin/{a.name}",
                    points=np.stack([[start, tip]]),
                    colors=SPIN_ARROW_COLOR,
                    shaft_radius=0.003,
                    head_radius=0.009,
                    head_length=0.02,
                )
            )
            out.append(
                scene.add_label(
                    f"/spin_labels/{a.name}",
                    a.label,
                    position=tuple(tip + np.array([0.0, 0.0, 0.02])),
                    font_screen_scale=0.6,
                )
            )
        return out

    def show_time(self, time: float) -> None:
        """Pose robot and ball (place and seam turn) at ``time`` [s] of the current frame's playback."""
        pb = self.frame.playback
        if pb is None or len(pb.t) == 0:
            return
        i = pb.index(time)
        with self.server.atomic():
            if pb.q is not None:
                self.set_robot(pb.q[i])
            self.set_ball(pb.ball[i], None if pb.ball_wxyz is None else pb.ball_wxyz[i])


def _faded(color: Rgb, amount: float = 0.45) -> Rgb:
    """``color`` moved ``amount`` of the way to the ghost grey."""
    g = COLORS["ghost"]
    return tuple(round((1 - amount) * c + amount * k) for c, k in zip(color, g))  # type: ignore[return-value]


def ghost_frame(frame: SceneFrame, label: str = "A (pinned)") -> SceneFrame:
    """The pinned serve's scene drawn as a ghost: its ball path (not the toss) in faded
    colours (drawn dashed by :meth:`StudioScene.show_ghost`), its bounce markers small and
    translucent, ``label`` at its last bounce (or its path's end)."""
    segments = tuple(PathSegment(s.name, s.points, _faded(s.color)) for s in frame.segments if s.name != "toss")
    bounces = [m for m in frame.markers if m.label.startswith("bounce")]
    markers = [Marker(m.name, m.position, _faded(m.color), "", radius=0.012, opacity=0.45) for m in bounces]
    if bounces:
        last = bounces[-1]
        markers.append(Marker("label", last.position, _faded(last.color), label, radius=0.0))
    elif segments and len(segments[0].points):
        end = tuple(float(x) for x in segments[0].points[-1])
        markers.append(Marker("label", end, COLORS["ghost"], label, radius=0.0))  # type: ignore[arg-type]
    return SceneFrame(segments=segments, markers=tuple(markers))


def _playback(ev: Evaluation) -> Playback | None:
    """Robot and ball samples on the motion's time grid, continued (robot at rest) until
    the ball path ends, with the ball's orientation integrated from its spin."""
    if ev.t is None or ev.q is None or len(ev.t) == 0:
        return None
    t, q = np.asarray(ev.t, dtype=float), np.asarray(ev.q, dtype=float)
    if ev.ball is not None and len(t) > 1 and ev.ball.t[-1] > t[-1]:
        dt = float(t[1] - t[0])
        extra = t[-1] + dt * np.arange(1, int(np.ceil((ev.ball.t[-1] - t[-1]) / dt)) + 1)
        t = np.concatenate([t, extra])
        q = np.concatenate([q, np.repeat(q[-1:], len(extra), axis=0)])
    ball_p = np.full((len(t), 3), np.nan)
    wxyz = np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))
    contact = None
    if ev.ball is not None:
        bt = ev.ball.t
        inside = (t >= bt[0]) & (t <= bt[-1])
        for i in range(3):
            ball_p[inside, i] = np.interp(t[inside], bt, ev.ball.p[:, i])
        turns = integrate_orientation(bt, ev.ball.w)
        wxyz[inside] = orientation_at(t[inside], bt, ev.ball.w, turns)
        contact = next((float(e.t) for e in ev.ball.events if e.kind == "racket"), None)
    cup = t < ev.toss_t[-1] if len(ev.toss_t) else np.zeros(len(t), bool)
    for i in range(3):
        ball_p[cup, i] = np.interp(t[cup], ev.toss_t, ev.toss_p[:, i])
    return Playback(t=t, q=q, ball=ball_p, ball_wxyz=wxyz, contact_t=contact)


def scene_frame(ev: Evaluation, context: EvaluationContext) -> SceneFrame:
    """The 3D scene description of an evaluation (pure; no viser needed)."""
    color = COLORS["legal"] if ev.status == "legal" else COLORS["illegal"]
    segments = [PathSegment("toss", ev.toss_p, COLORS["toss"])]
    markers: list[Marker] = []
    arrows: tuple[SpinArrow, ...] = ()
    if ev.ball is not None:
        segments.append(PathSegment("flight", ev.ball.p, color))
        bounce = 0
        for k, e in enumerate(ev.ball.events):
            label: str = e.kind
            if e.kind == "table":
                bounce += 1
                label = f"bounce {bounce}"
            markers.append(
                Marker(
                    f"event_{k}",
                    (float(e.p[0]), float(e.p[1]), float(e.p[2])),
                    COLORS.get(e.kind, COLORS["unknown"]) if e.kind != "table" else color,
                    label,
                )
            )
        arrows = spin_arrows(ev.ball)
    if ev.rollout is not None:
        segments.append(PathSegment("mujoco", np.asarray(ev.rollout.p), COLORS["rollout"]))
    playback = _playback(ev)
    q0 = context.robot.q_flat
    if ev.t is not None and ev.q is not None:
        q0 = ev.q[np.searchsorted(ev.t, ev.serve.params.tau).clip(0, len(ev.t) - 1)]
    return SceneFrame(
        segments=tuple(segments),
        markers=tuple(markers),
        target=ev.target,
        robot_q=q0,
        playback=playback,
        spin_arrows=arrows,
    )
