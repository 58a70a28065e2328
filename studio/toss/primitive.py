"""The toss motion primitive ``u_t(t)``: joint commands at 1 kHz and their predicted
execution (paper, "Ball toss using motion primitives"). :func:`studio.toss.design.make_toss`
builds one.

Times are on the *command clock* of the primitive: ``t = 0`` is the first sample of
``u_t``. Joint order and units of :mod:`studio.robot.model`; world frame, SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.toss.lift_profile import LiftProfile
from studio.toss.release import Release

FloatArray = npt.NDArray[np.float64]

TossSide = Literal["right", "left"]
TOSS_SIDES: Final[tuple[TossSide, ...]] = ("right", "left")
"""The two toss sides. Facing the receiver (+X), the robot's right is world -Y."""

DEFAULT_DT: Final[float] = 1e-3
"""Command period of the toss primitive [s] (the robot's 1 kHz command rate, paper)."""


@dataclass(frozen=True, eq=False)
class TossPrimitive:
    """A toss motion primitive ``u_t(t)`` and its predicted execution (paper: "the
    resulting motion is a trajectory of joint commands that produces a ball toss").

    Commands are sampled at ``dt`` on the toss's command clock (``t[0] = 0``); command
    ``u[k]`` is held over ``[t[k], t[k] + dt)``. ``u`` is continuous up to acceleration:
    ``ud`` and ``udd`` are its exact derivatives, so a strike plan can take over from
    any sample ``k`` with the initial command state ``(u[k], ud[k], udd[k])`` and the
    predicted joint state ``X[k]``. Arrays are read-only.
    """

    name: str
    """Identifier, e.g. ``"toss_right"``."""
    side: TossSide
    """Toss side: ``"right"`` (world -Y of the robot's centre line) or ``"left"`` (+Y)."""
    t: FloatArray
    """Command times (N,) [s], ``t[k] = k dt``."""
    u: FloatArray
    """Joint position commands (N, 8) [m, m, rad x 6], robot joint order."""
    ud: FloatArray
    """Command velocities (N, 8) [m/s | rad/s]."""
    udd: FloatArray
    """Command accelerations (N, 8) [m/s^2 | rad/s^2]."""
    uddd: FloatArray
    """Command jerks (N, 8) [m/s^3 | rad/s^3] (piecewise continuous)."""
    X: FloatArray
    """Predicted joint state (N, 8, 2) = [q, q'] from the robot's joint dynamics
    (``robot.dynamics.simulate(u, dt, X0)``, starting at rest at ``u[0]``)."""
    cup_p: FloatArray
    """Predicted centre of the ball in the cup (N, 3) [m], world frame."""
    cup_normal: FloatArray
    """Predicted racket (face A) normal (N, 3), world frame."""
    release: Release
    """Predicted release of the ball (:func:`studio.toss.release.find_release` on the predicted motion)."""
    profile: LiftProfile
    """Vertical cup motion the commands realise."""
    dt: float = DEFAULT_DT
    """Command period [s]."""

    def __post_init__(self) -> None:
        if self.side not in TOSS_SIDES:
            raise InvalidInputError(f"TossPrimitive.side must be one of {TOSS_SIDES}, got {self.side!r}")
        n = self.t.shape[0]
        for fname, shape in (
            ("t", (n,)),
            ("u", (n, 8)),
            ("ud", (n, 8)),
            ("udd", (n, 8)),
            ("uddd", (n, 8)),
            ("X", (n, 8, 2)),
            ("cup_p", (n, 3)),
            ("cup_normal", (n, 3)),
        ):
            arr = np.array(getattr(self, fname), dtype=float)
            if arr.shape != shape:
                raise InvalidInputError(f"TossPrimitive.{fname}: expected shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise InvalidInputError(f"TossPrimitive.{fname}: values must be finite")
            arr.setflags(write=False)
            object.__setattr__(self, fname, arr)

    @property
    def q(self) -> FloatArray:
        """Predicted joint positions (N, 8)."""
        return self.X[:, :, 0]

    @property
    def duration(self) -> float:
        """Time of the last command [s]."""
        return float(self.t[-1])

    def index_at(self, time: float) -> int:
        """Index of the command sample at or just before ``time`` [s] (clipped to the
        primitive)."""
        k = int(math.floor(float(time) / self.dt + 1e-9))
        return min(max(k, 0), self.t.size - 1)

    def command_state(self, time: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Hand-over state at the sample at or before ``time``: ``(u, ud, udd, X)`` with
        shapes (8,), (8,), (8,), (8, 2)."""
        k = self.index_at(time)
        return self.u[k].copy(), self.ud[k].copy(), self.udd[k].copy(), self.X[k].copy()
