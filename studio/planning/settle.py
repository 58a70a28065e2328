"""The final hold of a serve's last command until the predicted joints are at rest
(:func:`settle_hold`, tolerances :class:`SettleTolerance`). Joint order and units of
:mod:`studio.robot.model`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.planning.chain import free_response
from studio.planning.options import COMMAND_DT
from studio.planning.strike import checked_vector
from studio.robot.model import JointDynamics

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SettleTolerance:
    """When the predicted joints count as at rest on the last command (per joint, in the
    joint's unit: gantry [m, m/s], arm [rad, rad/s])."""

    position: float = 1e-4
    """Largest |q - u_end| [m | rad] (0.1 mm, 0.1 mrad)."""
    velocity: float = 1e-3
    """Largest |q'| [m/s | rad/s] (1 mm/s, 1 mrad/s)."""
    horizon: float = 0.2
    """The state must stay within the tolerances this long after the end [s] (the joint
    model is under-damped: zeta 0.85-0.9)."""
    max_hold: float = 3.0
    """Longest hold tried [s]."""

    def __post_init__(self) -> None:
        for name in ("position", "velocity", "horizon", "max_hold"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInputError(f"SettleTolerance.{name} must be finite and > 0, got {v!r}")


SETTLE: Final[SettleTolerance] = SettleTolerance()
"""Default rest tolerances of exported serves."""


def settle_hold(
    u_end: npt.ArrayLike,
    X_end: npt.ArrayLike,
    dynamics: JointDynamics,
    *,
    dt: float = COMMAND_DT,
    tol: SettleTolerance = SETTLE,
) -> FloatArray:
    """Predicted states (n, 8, 2) at t_end + dt, ..., t_end + n dt of the joints holding the
    command ``u_end`` (8,) that is sent at t_end, from their state ``X_end`` (8, 2) at t_end.

    n is the smallest count such that the last two samples (their velocities, exact and as
    finite differences from the sample before) and every sample over ``tol.horizon`` after
    them are within ``tol``
    (0 if the motion already ends that way).

    Raises:
        InvalidInputError: not settled within ``tol.max_hold``.
    """
    u1 = checked_vector(u_end, (8,), "settle_hold u_end")
    X0 = checked_vector(X_end, (8, 2), "settle_hold X_end")
    n_max, n_look = int(math.ceil(tol.max_hold / dt)), int(math.ceil(tol.horizon / dt))
    # exact free response of e = q - u1 under the held command, all samples at once
    times: FloatArray = np.arange(n_max + n_look + 1, dtype=np.float64)[:, None] * dt
    phi = free_response(dynamics.wn, dynamics.zeta, times)
    S = np.einsum("jnab,nb->jna", phi, np.stack([X0[:, 0] - u1, X0[:, 1]], axis=1))
    S[:, :, 0] += u1
    ok = np.all((np.abs(S[:, :, 0] - u1) <= tol.position) & (np.abs(S[:, :, 1]) <= tol.velocity), axis=1)
    ok[1:] &= np.all(np.abs(np.diff(S[:, :, 0], axis=0)) <= tol.velocity * dt, axis=1)  # as a controller sees it
    bad = np.flatnonzero(~ok[: n_max + n_look])
    if bad.size == 0:
        return S[1:1]
    n = int(bad[-1]) + 2  # after the last bad sample: one good sample, then the end sample
    if n > n_max:
        raise InvalidInputError(f"settle_hold: the joints are not within {tol} after {tol.max_hold} s of hold")
    return S[1 : n + 1]
