"""The joint-space line the arm lifts the cup along, and the cup height's inverse maps on it.

The arm joints move on a straight line in joint space ``q = q_start + s d``, with ``d``
in the null space of the racket's angular velocity and of the cup's lateral velocity
(:func:`studio.toss.arm.flat_plane_basis`), so the racket stays exactly flat and the cup
moves in a vertical plane on a gentle curve. The direction inside that plane is solved so
the arm alone moves the cup vertically at the release height (:func:`lift_direction`).
Along the line, ``s = S(z)`` and the cup's x ``Xc(z)`` are Chebyshev interpolants of the
cup height (:class:`LiftPath`). Joint order and units of :mod:`studio.robot.model`;
world frame, SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.toss.arm import cup_jacobian, flat_plane_basis

if TYPE_CHECKING:
    from studio.robot.model import Robot

FloatArray = npt.NDArray[np.float64]

CHEBYSHEV_NODES: int = 40
"""Nodes of the Chebyshev interpolants ``S(z)`` and ``Xc(z)``."""

_S_GRID: FloatArray = np.linspace(0.0, 2.0, 201)
"""Line parameters ``s`` at which a candidate line is sampled."""


@dataclass(frozen=True, eq=False)
class _LineSearch:
    """Candidate lift lines ``q_start + s d(psi)``, ``d(psi) = basis [cos psi, sin psi]``,
    sampled at ``s`` in [0, 2]."""

    robot: Robot
    q_start: FloatArray
    """Start configuration (8,)."""
    basis: FloatArray
    """(8, 2) flat, vertical-plane joint directions."""
    z0: float
    """Cup height at the start [m]."""
    travel: float
    """Upward travel of the cup [m]."""

    def line(self, psi: float) -> tuple[FloatArray, FloatArray]:
        """Direction (8,) and cup positions (201, 3) [m] along the line of angle ``psi``."""
        d = self.basis @ np.array([math.cos(psi), math.sin(psi)])
        P = np.array([self.robot.cup_position(self.q_start + s_i * d) for s_i in _S_GRID])
        return d, P

    def vertical_height(self, psi: float) -> tuple[float, float] | None:
        """(height of the first vertical-velocity point above the start, min dz/ds up
        to the top of the lift) along the line, or None (no such point / z not monotonic)."""
        _, P = self.line(psi)
        dP = np.gradient(P, _S_GRID, axis=0)
        if dP[0, 2] < 0.0:
            return None
        flips = np.flatnonzero(np.sign(dP[1:, 0]) != np.sign(dP[:-1, 0]))
        top = np.flatnonzero(P[:, 2] - self.z0 >= self.travel + 0.005)
        if flips.size == 0 or top.size == 0:
            return None
        i_top = int(top[0])
        if float(np.min(dP[: i_top + 1, 2])) <= 0.05:
            return None
        i = int(flips[0])
        # Linear interpolation of the flip of dx/ds.
        w = dP[i, 0] / (dP[i, 0] - dP[i + 1, 0])
        return float((1 - w) * P[i, 2] + w * P[i + 1, 2] - self.z0), float(np.min(dP[: i_top + 1, 2]))

    def bracket(self, h_rel: float) -> tuple[float, float]:
        """Angles (lo, hi) [rad] bracketing the vertical point at ``h_rel`` [m] above the
        start: of the 5-degree grid brackets, the steepest lift (largest min dz/ds)."""
        psis = np.linspace(-math.pi, math.pi, 73)
        heights = [self.vertical_height(float(p_)) for p_ in psis]
        brackets = []
        for k in range(len(psis) - 1):
            h0, h1 = heights[k], heights[k + 1]
            if h0 is not None and h1 is not None and (h0[0] - h_rel) * (h1[0] - h_rel) <= 0.0:
                brackets.append((min(h0[1], h1[1]), float(psis[k]), float(psis[k + 1])))
        if not brackets:
            reach = max((h[0] for h in heights if h is not None), default=0.0)
            raise InvalidInputError(
                f"make_toss: no flat joint-space lift from this start pose moves the cup vertically at the release "
                f"height {h_rel:.3f} m above the start (highest: {reach:.3f} m): raise lift_acceleration, shorten "
                "ramp_release or lower the rise"
            )
        _, lo_psi, hi_psi = max(brackets)  # the steepest lift (largest min dz/ds)
        return lo_psi, hi_psi


def lift_direction(robot: Robot, q_start: FloatArray, z0: float, travel: float, h_rel: float) -> FloatArray:
    """Joint direction ``d`` (8,) of the lift line ``q_start + s d``: flat racket, cup in a
    vertical plane, the cup moving vertically (arm only) at ``h_rel`` [m] above its start
    height ``z0`` [m] (bisection on the line's angle in the flat plane). ``travel`` [m]:
    the lift's upward travel, which the line must reach with z increasing.

    Raises:
        InvalidInputError: no such line (see :meth:`_LineSearch.bracket`).
    """
    basis = flat_plane_basis(robot, q_start)
    search = _LineSearch(robot, q_start, basis, z0, travel)
    lo_psi, hi_psi = search.bracket(h_rel)
    f_lo = search.vertical_height(lo_psi)
    assert f_lo is not None
    for _ in range(40):
        mid = 0.5 * (lo_psi + hi_psi)
        f_mid = search.vertical_height(mid)
        if f_mid is None:
            break
        if (f_mid[0] - h_rel) * (f_lo[0] - h_rel) <= 0.0:
            hi_psi = mid
        else:
            lo_psi, f_lo = mid, f_mid
    psi = 0.5 * (lo_psi + hi_psi)
    return basis @ np.array([math.cos(psi), math.sin(psi)])


@dataclass(frozen=True, eq=False)
class LiftPath:
    """The lift line ``q = q_start + S(z) d`` and the cup's x along it, ``Xc(z)`` (gantry
    fixed), as Chebyshev interpolants of the cup height ``z`` [m] with their derivatives
    up to order 5."""

    q_start: FloatArray
    """Start configuration (8,) [m | rad]."""
    d: FloatArray
    """Joint direction (8,) of the line."""
    S: list[np.polynomial.Chebyshev]
    """Line parameter ``s(z)`` and its derivatives 1-5 in ``z``."""
    Xc: list[np.polynomial.Chebyshev]
    """Cup x ``Xc(z)`` [m] and its derivatives 1-5 in ``z``."""

    @classmethod
    def along(cls, robot: Robot, q_start: FloatArray, d: FloatArray, z0: float, travel: float) -> LiftPath:
        """Interpolants over the lift heights ``[z0 - 1 mm, z0 + travel + 2 mm]``
        (Newton on the cup height at the Chebyshev nodes).

        Raises:
            InvalidInputError: a height not reached along the line, or an interpolant
                off by more than 1e-8 m between the nodes.
        """
        z_lo, z_hi = z0 - 1e-3, z0 + travel + 2e-3
        n_nodes = CHEBYSHEV_NODES
        z_nodes = z_lo + (np.sort(np.polynomial.chebyshev.chebpts1(n_nodes)) + 1.0) * 0.5 * (z_hi - z_lo)
        s_nodes = np.empty(n_nodes)
        x_nodes = np.empty(n_nodes)
        s_prev = 0.0
        for i, zt in enumerate(z_nodes):
            s_i = s_prev
            for _ in range(50):
                qi = q_start + s_i * d
                err = zt - float(robot.cup_position(qi)[2])
                if abs(err) < 1e-13:
                    break
                s_i += err / float(cup_jacobian(robot, qi)[2] @ d)
            else:
                raise InvalidInputError(f"make_toss: cannot reach cup height {zt:.3f} m along the lift")
            s_nodes[i] = s_prev = s_i
            x_nodes[i] = float(robot.cup_position(q_start + s_i * d)[0])
        S = np.polynomial.Chebyshev.fit(z_nodes, s_nodes, n_nodes - 1, domain=[z_lo, z_hi])
        Xc = np.polynomial.Chebyshev.fit(z_nodes, x_nodes, n_nodes - 1, domain=[z_lo, z_hi])
        for zc in 0.5 * (z_nodes[1:] + z_nodes[:-1]):
            cup_c = robot.cup_position(q_start + float(S(zc)) * d)
            e = max(abs(float(cup_c[2]) - zc), abs(float(cup_c[0]) - float(Xc(zc))))
            if e > 1e-8:
                raise InvalidInputError(f"make_toss: path interpolant inaccurate at z = {zc:.3f} m ({e:.1e} m)")
        return cls(
            q_start=q_start,
            d=d,
            S=[S.deriv(m) if m else S for m in range(6)],
            Xc=[Xc.deriv(m) if m else Xc for m in range(6)],
        )
