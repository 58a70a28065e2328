"""The ITTF court: table top, net, posts, lines and floor, in the world frame.

One geometry description shared by the ball physics (:mod:`studio.physics.ball`), the MuJoCo
scene (:mod:`studio.sim.rollout`), the collision checker and the 3D studio, so they cannot
disagree. World frame (``DESIGN.md``): origin at the centre of the playing surface,
+X towards the receiver, +Z up; all lengths in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from studio import constants as C

Side = Literal["server", "receiver"]


@dataclass(frozen=True, slots=True)
class Box:
    """An axis-aligned box of the court, in the world frame."""

    name: str
    """Unique name (also the MuJoCo geom / collision object name)."""
    center: tuple[float, float, float]
    """Centre of the box [m], world frame."""
    half_size: tuple[float, float, float]
    """Half extents along X, Y, Z [m]."""
    kind: Literal["table", "net", "post", "line", "leg"]
    """What the box is: decides which impact model a ball uses against it."""


@dataclass(frozen=True, slots=True)
class Court:
    """ITTF table, net assembly and floor (Laws 2.1, 2.2). Defaults are the laws' values."""

    length: float = C.TABLE_LENGTH
    """Playing surface length along X [m]."""
    width: float = C.TABLE_WIDTH
    """Playing surface width along Y [m]."""
    height: float = C.TABLE_HEIGHT
    """Playing surface height above the floor [m]."""
    thickness: float = C.TABLE_THICKNESS
    """Table top thickness [m]."""
    net_height: float = C.NET_HEIGHT
    """Height of the net top above the playing surface [m]."""
    net_post_offset: float = C.NET_POST_OFFSET
    """Distance of the outside of the posts from the side lines [m]."""
    net_thickness: float = C.NET_THICKNESS
    """Contact thickness of the net along X [m]."""
    post_size: float = C.NET_POST_SIZE
    """Side of a post's square cross-section [m]."""
    edge_line_width: float = C.EDGE_LINE_WIDTH
    """Width of the white edge lines [m]."""
    centre_line_width: float = C.CENTRE_LINE_WIDTH
    """Width of the centre line [m]."""
    extras: tuple[Box, ...] = field(default=())
    """Additional static boxes (e.g. a ball feeder) that balls and robots may hit."""

    def __post_init__(self) -> None:
        for name in ("length", "width", "height", "thickness", "net_height", "net_thickness", "post_size"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0.0:
                raise ValueError(f"Court.{name} must be a positive finite length in m, got {value!r}")

    # -- derived geometry -----------------------------------------------------------

    @property
    def half_length(self) -> float:
        """Half the table length [m]: the end lines are at x = -/+ half_length."""
        return 0.5 * self.length

    @property
    def half_width(self) -> float:
        """Half the table width [m]: the side lines are at y = -/+ half_width."""
        return 0.5 * self.width

    @property
    def floor_z(self) -> float:
        """World z of the floor [m]."""
        return -self.height

    @property
    def net_half_span(self) -> float:
        """Half the length of the net assembly along Y, posts included [m]."""
        return self.half_width + self.net_post_offset

    @property
    def server_end_line_x(self) -> float:
        """World x of the server's (robot's) end line [m]."""
        return -self.half_length

    # -- queries used by physics and rules ------------------------------------------

    def on_table(self, xy: npt.ArrayLike) -> npt.NDArray[np.bool_] | bool:
        """Whether points (..., 2) [m] lie on the playing surface, edge lines included.

        A ball touching the table at these coordinates is in (ITTF: the lines belong to
        the playing surface).
        """
        xy = np.asarray(xy, dtype=float)
        inside = (np.abs(xy[..., 0]) <= self.half_length) & (np.abs(xy[..., 1]) <= self.half_width)
        return bool(inside) if inside.ndim == 0 else inside

    def side(self, x: float) -> Side:
        """Which half of the table the world x [m] belongs to (x < 0: the server's)."""
        return "server" if x < 0.0 else "receiver"

    def edge_distance(self, xy: npt.ArrayLike) -> npt.NDArray[np.float64] | float:
        """Distance [m] from points (..., 2) to the nearest table edge (end or side line).

        Positive inside the playing surface, negative outside.
        """
        xy = np.asarray(xy, dtype=float)
        d = np.minimum(self.half_length - np.abs(xy[..., 0]), self.half_width - np.abs(xy[..., 1]))
        return float(d) if np.ndim(d) == 0 else d

    def boxes(self) -> tuple[Box, ...]:
        """Static collision boxes: table top, net, the two posts and the extras."""
        hl, hw, t = self.half_length, self.half_width, self.thickness
        top = Box("table_top", (0.0, 0.0, -0.5 * t), (hl, hw, 0.5 * t), "table")
        # The net hangs from the post tops down to the playing surface.
        net = Box(
            "net",
            (0.0, 0.0, 0.5 * self.net_height),
            (0.5 * self.net_thickness, self.net_half_span - self.post_size, 0.5 * self.net_height),
            "net",
        )
        posts = tuple(
            Box(
                f"net_post_{label}",
                (0.0, sign * (self.net_half_span - 0.5 * self.post_size), 0.5 * self.net_height),
                (0.5 * self.post_size, 0.5 * self.post_size, 0.5 * self.net_height),
                "post",
            )
            for label, sign in (("left", 1.0), ("right", -1.0))
        )
        return (top, net, *posts, *self.extras)

    def legs(self) -> tuple[Box, ...]:
        """Four legs under the table top (visual and robot collision only) [m]."""
        leg = 0.04
        z_half = 0.5 * (self.height - self.thickness)
        zc = -self.thickness - z_half
        return tuple(
            Box(
                f"table_leg_{i}",
                (sx * (self.half_length - 0.3), sy * (self.half_width - 0.1), zc),
                (0.5 * leg, 0.5 * leg, z_half),
                "leg",
            )
            for i, (sx, sy) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1)))
        )

    def lines(self) -> tuple[Box, ...]:
        """The white lines painted on the playing surface, as 1 mm thick boxes [m]."""
        hl, hw, e = self.half_length, self.half_width, self.edge_line_width
        z, hz = 0.0005, 0.0005
        return (
            Box("line_end_server", (-hl + 0.5 * e, 0.0, z), (0.5 * e, hw, hz), "line"),
            Box("line_end_receiver", (hl - 0.5 * e, 0.0, z), (0.5 * e, hw, hz), "line"),
            Box("line_side_left", (0.0, hw - 0.5 * e, z), (hl, 0.5 * e, hz), "line"),
            Box("line_side_right", (0.0, -hw + 0.5 * e, z), (hl, 0.5 * e, hz), "line"),
            Box("line_centre", (0.0, 0.0, z), (hl, 0.5 * self.centre_line_width, hz), "line"),
        )


DEFAULT_COURT = Court()
"""The ITTF court with the laws' dimensions."""
