"""Savitzky-Golay smoothing of a toss recording: position, velocity and acceleration
estimates on a uniform resampling (SI units)."""

from __future__ import annotations

import math
from typing import Final

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError

FloatArray = npt.NDArray[np.float64]

SMOOTHING_WINDOW: Final[float] = 0.065
"""Savitzky-Golay window [s] of the per-recording smoothing (13 frames at 200 Hz)."""

SMOOTHING_ORDER: Final[int] = 3
"""Savitzky-Golay polynomial order."""


def smooth_recording(t: FloatArray, p: FloatArray, window: float, order: int) -> tuple[FloatArray, ...]:
    """Savitzky-Golay smoothing of one recording: uniform resampling at its median
    frame period, then position, velocity and acceleration estimates.

    Returns:
        tu (M,), p (M, 3), v (M, 3), a (M, 3).
    """
    from scipy.signal import savgol_filter

    h = float(np.median(np.diff(t)))
    m = int(math.floor((t[-1] - t[0]) / h + 1e-9)) + 1
    tu = t[0] + h * np.arange(m)
    pu = np.stack([np.interp(tu, t, p[:, j]) for j in range(3)], axis=1)
    n_win = max(int(round(window / h)) | 1, order + 2 + (order + 2 + 1) % 2)
    if n_win > m:
        raise InvalidInputError(f"recording too short ({m} frames) for a {window} s smoothing window")
    ps = savgol_filter(pu, n_win, order, deriv=0, axis=0, mode="interp")
    vs = savgol_filter(pu, n_win, order, deriv=1, delta=h, axis=0, mode="interp")
    as_ = savgol_filter(pu, n_win, order, deriv=2, delta=h, axis=0, mode="interp")
    return tu, ps, vs, as_
