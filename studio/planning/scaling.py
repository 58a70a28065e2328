"""The scales of the strike planner's variables and rows, from the joint limits
(:class:`LimitScaling`): jerks are divided by their limits, every limit row by its limit,
s = (q_tau, qd_tau) by its range. Joint order and units of :mod:`studio.robot.model`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from studio.robot.model import JointLimits

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class LimitScaling:
    """Scaled limit data of one set of joint limits (8 joints; chain components
    c = 0..4 of Z = [u, u', u'', q, q'])."""

    jmax: FloatArray
    """Jerk limits (8,) [m/s^3 | rad/s^3]: the scaled jerks are ``z = j / jmax``."""
    sig: FloatArray
    """Scale (16,) of s = (q_tau, qd_tau) in the reduced problem: min(half range, 1) and
    the velocity limits."""
    row_scale: FloatArray
    """Scale (8, 5) of the limit rows of component c: half range, velocity, acceleration,
    half range, velocity limits."""
    row_lo: FloatArray
    """Lower limits (8, 5) of the chain components."""
    row_hi: FloatArray
    """Upper limits (8, 5) of the chain components."""
    check_lo: FloatArray
    """Lower bounds (8, 5) of the 1 kHz check (``row_lo`` less the check's tolerance)."""
    check_hi: FloatArray
    """Upper bounds (8, 5) of the 1 kHz check."""

    @classmethod
    def of(cls, limits: JointLimits, limit_tolerance: float) -> LimitScaling:
        """The scaling of ``limits``; ``limit_tolerance`` [-]: relative tolerance of the
        1 kHz limit check (fraction of each limit)."""
        L = limits
        half = 0.5 * (L.upper - L.lower)
        row_scale = np.stack([half, L.velocity, L.acceleration, half, L.velocity], axis=1)  # (8, 5)
        row_lo = np.stack([L.lower, -L.velocity, -L.acceleration, L.lower, -L.velocity], axis=1)
        row_hi = np.stack([L.upper, L.velocity, L.acceleration, L.upper, L.velocity], axis=1)
        tol = limit_tolerance * row_scale  # the 1 kHz check's bounds (fast path)
        return cls(
            jmax=np.array(L.jerk, dtype=float),
            sig=np.concatenate([np.minimum(half, 1.0), L.velocity]),
            row_scale=row_scale,
            row_lo=row_lo,
            row_hi=row_hi,
            check_lo=row_lo - tol,
            check_hi=row_hi + tol,
        )
