"""The serve reward of the paper: F = r_pos + r_vel + r_top/back + r_side + r_height + s_leg.

All terms except ``s_leg`` come from the ball state just after the second bounce (v_2,
w_2) and from the maximum ball height after the first bounce. The spin is decomposed in
the velocity-aligned frame: e_x parallel to v_2, e_y horizontal and perpendicular to e_x,
e_z completing the right-handed triad and pointing up. With e_y = e_z x e_x a ball
travelling +X has e_y = +Y, so topspin (w_y > 0, ``DESIGN.md``) gives w_tb > 0.

The paper fixes the structure and the spin terms; it leaves the shapes of r_pos, r_vel
and r_height open. The forms chosen here are documented in :class:`RewardWeights`.
Illegal serves get only ``s_leg`` (the legality chain's penalty, :mod:`studio.serve.rules`);
planner failures get the fixed ``P_MPC = -10``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.physics.ball import spin_components
from studio.physics.court import DEFAULT_COURT

PLANNER_FAILURE_PENALTY = -10.0
"""Fixed penalty P_MPC when the motion planner finds no valid plan (paper)."""


def velocity_frame(v: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Rows e_x, e_y, e_z (3, 3) of the paper's velocity-aligned frame for velocity v (3,).

    For a (near) vertical velocity the horizontal direction is undefined; e_x's
    horizontal part then falls back to +X (as :func:`studio.physics.ball.spin_components`).
    """
    # spin_components(v, e_i) = (e_y[i], e_z[i], e_x[i]): project the unit axes.
    ey, ez, ex = (
        np.asarray(c, dtype=float) for c in spin_components(np.broadcast_to(np.asarray(v, float), (3, 3)), np.eye(3))
    )
    return np.stack([ex, ey, ez])


def spin_scalars(v: npt.ArrayLike, w: npt.ArrayLike) -> tuple[float, float, float]:
    """(top/back, side, cork) [rad/s] of one ball state as floats; see :func:`studio.physics.ball.spin_components`."""
    tb, ss, ck = spin_components(v, w)
    return float(tb), float(ss), float(ck)


@dataclass(frozen=True, slots=True)
class RewardWeights:
    """Gains of the reward terms; a zero gain disables a term."""

    g_pos: float = 0.0
    """Gain of r_pos = g_pos * exp(-d / sigma), d the x-y distance of the second bounce
    from ``target`` [m]. A Laplace kernel rather than a Gaussian: with
    exp(-d^2 / (2 * 0.15^2)) the reward had no slope beyond ~0.5 m; 5 aiming runs of 2000
    evaluations (4 legal) ended 0.88 +- 0.45 m from the corner with the Gaussian and
    0.77 +- 0.55 m with this kernel (paper: 0.17 +- 0.29 m) -- better slope, weak evidence."""
    target: tuple[float, float] = (1.2, 0.6)
    """Aim point of the second bounce (x, y) [m], world frame."""
    pos_sigma: float = 0.3
    """Length scale of r_pos [m] (r_pos = g_pos / e at this distance)."""
    g_vel_xy: float = 0.0
    """Gain on |v_xy| / v_xy_ref after the second bounce; negative to penalize speed."""
    g_vel_z: float = 0.0
    """Gain on |v_z| / v_z_ref after the second bounce; negative encourages low serves."""
    v_xy_ref: float = 10.0
    """Normalization of the horizontal speed [m/s]."""
    v_z_ref: float = 5.0
    """Normalization of the vertical speed [m/s]."""
    g_top: float = 0.0
    """Gain of r_top = g_top * max(0, w_tb_hat) (``spin_form="paper"``)."""
    g_back: float = 0.0
    """Gain of r_back = g_back * max(0, -w_tb_hat) (``spin_form="paper"``)."""
    spin_form: Literal["paper", "signed"] = "paper"
    """Shape of r_top and r_back. ``"paper"``: the paper's one-sided max(0, .) terms.
    ``"signed"`` (beyond the paper, which lets the spin terms "reward signed or unsigned
    spin components directly"): r_top = g_top (1 + w_tb_hat) / 2 and
    r_back = g_back (1 - w_tb_hat) / 2, the signed component mapped onto [0, g] so that
    a legal serve still scores >= 0 and above every illegal one. With the paper's form
    a backspin run has no slope on the plateau of topspin serves (every serve flown
    through two table bounces leaves with topspin unless the racket gave it a lot of
    backspin): see ``docs/optimization.md#the-full-experiment-4-tasks-25-serves-each``."""
    g_side: float = 0.0
    """Gain of r_side = g_side * phi(w_ss_hat)."""
    side_direction: Literal[-1, 1] | None = None
    """Preferred sidespin sign d; None rewards either direction (phi = |z|)."""
    spin_max: float = 500.0
    """Clamp w_bar [rad/s] of the normalized spin components (serve spins reach ~550 rad/s)."""
    spin_at: Literal["second_bounce", "net"] = "second_bounce"
    """Ball state whose spin r_top/back and r_side reward: just after the second bounce
    (the paper), or as the ball crosses the net plane (what the receiver reads in
    flight). An option beyond the paper: with this table bounce model the spin after the
    second bounce is close to rolling (top/back ~ |v_xy| / r; median ratio 1.00 in the
    4 x 25 experiment), so there the spin terms mostly reward speed and no serve keeps
    backspin. Velocity, position and height terms are unaffected."""
    g_height: float = 0.0
    """Gain of r_height = g_height * min(1, h_ref / h_max), h_max the highest ball bottom
    above the playing surface after the first bounce: inversely proportional to the
    height, capped at the gain."""
    h_ref: float = 0.10
    """Height [m] at and below which r_height is at its full gain (~ net height)."""

    def __post_init__(self) -> None:
        for name in (
            "g_pos",
            "pos_sigma",
            "g_vel_xy",
            "g_vel_z",
            "v_xy_ref",
            "v_z_ref",
            "g_top",
            "g_back",
            "g_side",
            "spin_max",
            "g_height",
            "h_ref",
        ):
            if not math.isfinite(getattr(self, name)):
                raise InvalidInputError(f"RewardWeights.{name} must be finite")
        for name in ("pos_sigma", "v_xy_ref", "v_z_ref", "spin_max", "h_ref"):
            if getattr(self, name) <= 0:
                raise InvalidInputError(f"RewardWeights.{name} must be positive")
        for name in ("g_top", "g_back", "g_side", "g_pos", "g_height"):
            if getattr(self, name) < 0:
                raise InvalidInputError(f"RewardWeights.{name} must be >= 0 (the paper's gains are non-negative)")
        if self.spin_form not in ("paper", "signed"):
            raise InvalidInputError(f"RewardWeights.spin_form must be 'paper' or 'signed', got {self.spin_form!r}")
        if self.spin_form == "signed" and self.g_top > 0 and self.g_back > 0:
            raise InvalidInputError(
                "RewardWeights: spin_form='signed' rewards one direction; with both g_top and g_back > 0 "
                "r_top + r_back would not depend on the spin (use spin_form='paper' for either direction)"
            )
        if self.spin_at not in ("second_bounce", "net"):
            raise InvalidInputError(f"RewardWeights.spin_at must be 'second_bounce' or 'net', got {self.spin_at!r}")


@dataclass(frozen=True, slots=True)
class RewardTerms:
    """The reward and its terms for one serve."""

    r_pos: float = 0.0
    r_vel: float = 0.0
    r_topback: float = 0.0
    r_side: float = 0.0
    r_height: float = 0.0
    s_leg: float = 0.0
    terms: dict[str, float] = field(default_factory=dict)

    @property
    def total(self) -> float:
        """F, the sum of all terms."""
        return self.r_pos + self.r_vel + self.r_topback + self.r_side + self.r_height + self.s_leg

    def as_dict(self) -> dict[str, float]:
        """Terms by name, plus ``total``."""
        return {
            "r_pos": self.r_pos,
            "r_vel": self.r_vel,
            "r_topback": self.r_topback,
            "r_side": self.r_side,
            "r_height": self.r_height,
            "s_leg": self.s_leg,
            "total": self.total,
        }


def reward(
    *,
    p2: npt.ArrayLike,
    v2: npt.ArrayLike,
    w2: npt.ArrayLike,
    max_height: float,
    weights: RewardWeights,
    v_net: npt.ArrayLike | None = None,
    w_net: npt.ArrayLike | None = None,
) -> RewardTerms:
    """Reward of a legal serve from the ball state just after the second bounce.

    Args:
        p2: ball position at the second bounce (3,) [m], world frame.
        v2: ball velocity just after the second bounce (3,) [m/s].
        w2: ball spin just after the second bounce (3,) [rad/s].
        max_height: highest ball bottom above the playing surface after the first bounce [m].
        weights: the task's gains.
        v_net, w_net: ball velocity [m/s] and spin [rad/s] (3,) at the net crossing; needed
            when ``weights.spin_at == "net"`` (then the spin terms use them).

    Raises:
        InvalidInputError: non-finite states, or no net state for ``spin_at="net"``.
    """
    p2, v2, w2 = (np.asarray(a, dtype=float) for a in (p2, v2, w2))
    if not (
        np.all(np.isfinite(p2)) and np.all(np.isfinite(v2)) and np.all(np.isfinite(w2)) and math.isfinite(max_height)
    ):
        raise InvalidInputError("reward: ball state at the second bounce must be finite")
    v_spin, w_spin = v2, w2
    if weights.spin_at == "net":
        if v_net is None or w_net is None:
            raise InvalidInputError("reward: spin_at='net' needs the ball state at the net crossing (v_net, w_net)")
        v_spin, w_spin = np.asarray(v_net, dtype=float), np.asarray(w_net, dtype=float)
        if (
            v_spin.shape != (3,)
            or w_spin.shape != (3,)
            or not (np.all(np.isfinite(v_spin)) and np.all(np.isfinite(w_spin)))
        ):
            raise InvalidInputError("reward: ball state at the net crossing must be two finite 3-vectors")
    wt = weights
    d = float(np.hypot(p2[0] - wt.target[0], p2[1] - wt.target[1]))
    r_pos = wt.g_pos * math.exp(-d / wt.pos_sigma)
    r_vel = wt.g_vel_xy * float(np.hypot(v2[0], v2[1])) / wt.v_xy_ref + wt.g_vel_z * abs(float(v2[2])) / wt.v_z_ref
    tb, ss, _ = spin_scalars(v_spin, w_spin)
    tb_hat = float(np.clip(tb, -wt.spin_max, wt.spin_max)) / wt.spin_max
    ss_hat = float(np.clip(ss, -wt.spin_max, wt.spin_max)) / wt.spin_max
    r_topback = _topback(wt, tb_hat)
    phi = abs(ss_hat) if wt.side_direction is None else max(0.0, wt.side_direction * ss_hat)
    r_side = wt.g_side * phi
    r_height = wt.g_height * min(1.0, wt.h_ref / max(max_height, 1e-6))
    return RewardTerms(r_pos=r_pos, r_vel=r_vel, r_topback=r_topback, r_side=r_side, r_height=r_height)


def _topback(wt: RewardWeights, tb_hat: float) -> float:
    """r_top + r_back for the normalized top/back spin ``tb_hat`` in [-1, 1]."""
    if wt.spin_form == "signed":
        return wt.g_top * (1.0 + tb_hat) / 2.0 + wt.g_back * (1.0 - tb_hat) / 2.0
    return wt.g_top * max(0.0, tb_hat) + wt.g_back * max(0.0, -tb_hat)


_LOW = 0.5
"""Weight of the "low" height term the paper adds to every training run."""

TASKS: dict[str, RewardWeights] = {
    "aiming": RewardWeights(
        g_pos=2.0, target=(DEFAULT_COURT.half_length - 0.15, DEFAULT_COURT.half_width - 0.15), g_height=_LOW
    ),
    "topspin_velocity": RewardWeights(g_top=1.0, g_vel_xy=1.0, g_height=_LOW),
    "backspin": RewardWeights(g_back=1.0, g_height=_LOW),
    "sidespin": RewardWeights(g_side=1.0, g_height=_LOW),
    "backspin_signed": RewardWeights(g_back=1.0, g_height=_LOW, spin_form="signed"),
    "backspin_net": RewardWeights(g_back=1.0, g_height=_LOW, spin_at="net"),
    "spin_net": RewardWeights(g_top=1.0, g_back=1.0, g_side=1.0, spin_max=1000.0, g_height=_LOW, spin_at="net"),
}
"""Task presets of the paper's experiment (Table II): aiming at a table corner (15 cm
inside the receiver's left corner), topspin & horizontal velocity, backspin, sidespin in
either direction; each with the "low" height weighting the paper adds to all runs. Beyond
the paper: ``backspin_signed`` rewards the signed top/back spin at the second bounce
(:attr:`RewardWeights.spin_form`: a slope from topspin towards backspin); ``backspin_net`` rewards backspin as the ball crosses the net
(:attr:`RewardWeights.spin_at`); ``spin_net`` rewards the spin a receiver reads at the
net in any direction, |w_tb| + |w_ss| up to 1000 rad/s each (the serve capability
envelope, the paper's Fig. 3b: how much spin the robot can put on a legal serve)."""


def task_weights(name: str, *, low: bool = True) -> RewardWeights:
    """The preset ``name`` (see :data:`TASKS`); ``low=False`` drops the height term."""
    if name not in TASKS:
        raise InvalidInputError(f"unknown task {name!r}; known tasks: {', '.join(TASKS)}")
    weights = TASKS[name]
    return weights if low else replace(weights, g_height=0.0)
