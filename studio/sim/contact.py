"""One ball contact of a rollout (:class:`Contact`): what the ball touched, where, and
its velocity and spin before and after. World frame, SI units."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

ContactKind = Literal["racket", "robot", "table", "net", "post", "floor"]
"""What the ball touched (the legality chain's categories, :mod:`studio.serve.rules`)."""


@dataclass(frozen=True, slots=True)
class Contact:
    """One ball contact of a rollout (world frame, SI units)."""

    t: float
    """Contact instant [s] (clock of the rollout's ``t``)."""
    kind: ContactKind
    """``"racket"`` (blade), ``"robot"`` (any other robot geom), ``"table"``, ``"net"``,
    ``"post"`` or ``"floor"``."""
    geom: str
    """Name of the MuJoCo geom the ball touched."""
    body: str
    """Name of the body of that geom (``"world"`` for the court)."""
    part: str
    """Racket: ``"face_a"``, ``"face_b"`` or ``"rim"``; table: ``"top"`` or ``"edge"``;
    otherwise the geom name."""
    p: FloatArray
    """Ball centre at contact [m], (3,)."""
    point: FloatArray
    """Contact point on the geom's surface [m], (3,)."""
    normal: FloatArray
    """Unit contact normal (3,), from the geom towards the ball centre."""
    v_before: FloatArray
    """Ball velocity just before [m/s], (3,)."""
    v_after: FloatArray
    """Ball velocity just after [m/s], (3,)."""
    w_before: FloatArray
    """Ball spin just before [rad/s], (3,)."""
    w_after: FloatArray
    """Ball spin just after [rad/s], (3,)."""
    surface_velocity: FloatArray
    """Velocity of the touched surface at the contact point [m/s], (3,) (0 for the court)."""
    side: Literal["server", "receiver"] | None = None
    """Table half for table and floor contacts (x < 0: server), else None."""

    @property
    def position(self) -> FloatArray:
        """Alias of :attr:`p`: ball centre at contact [m]."""
        return self.p
