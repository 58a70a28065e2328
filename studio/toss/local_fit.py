"""A recorded toss's ball state in free flight from its own samples: a least-squares
polynomial fitted around the time (used by :meth:`studio.toss.model.TossModel.recorded_state_at`).
SI units."""

from __future__ import annotations

from typing import Final

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError

FloatArray = npt.NDArray[np.float64]

LOCAL_FIT_HALF_WINDOW: Final[float] = 0.06
"""Half width [s] of the window of a recording's own samples from which its ball state
at a time in free flight is fitted (:meth:`studio.toss.model.TossModel.recorded_state_at`): 25 frames at
200 Hz. With the +/-1.5 mm tracking noise of :class:`~studio.toss.noise.TossNoise` the fitted position
scatters by ~0.5 mm and the velocity by ~9 mm/s per axis (the Savitzky-Golay velocity
just after the lift: 46-78 mm/s); the drag's change over the window biases the
velocity of every toss alike by ~2 mm/s."""

LOCAL_FIT_ORDER: Final[int] = 2
"""Polynomial order of that local fit (free flight: about constant acceleration)."""

LOCAL_FIT_LIFT_MARGIN: Final[float] = 0.015
"""The local fit window starts at least this long after ``t_lift`` [s], so that it
holds free flight only (``t_lift`` scatters by ~2.5 ms, the release by ~1 ms)."""

LOCAL_FIT_MIN_SAMPLES: Final[int] = 8
"""Fewest recorded samples a local fit window must hold, else the toss is refused as
not covering the time."""


def local_fit_state(
    t: FloatArray, p: FloatArray, time: float, span: tuple[float, float], *, half_window: float, order: int
) -> tuple[FloatArray, FloatArray]:
    """Ball position [m] and velocity [m/s] (3,) at ``time`` [s] from a least-squares
    polynomial (``order``) fitted per axis to the recorded samples ``t`` (M,) [s],
    ``p`` (M, 3) [m] in ``[time - half_window, time + half_window]``.

    Where that window leaves ``span`` = (lo, hi) [s] (free flight covered by the
    recording) it is shifted inside it (nearest covered window, same width), so near
    the lift or the recording's end the fit is one-sided; ``time`` itself must lie in
    ``span`` (no extrapolation).

    Raises:
        InvalidInputError: ``time`` outside ``span``, ``span`` narrower than the window,
            or fewer than :data:`LOCAL_FIT_MIN_SAMPLES` samples in it.
    """
    lo, hi = span
    if not (lo - 1e-9 <= time <= hi + 1e-9):
        raise InvalidInputError(
            f"time {time:.4f} s is not covered by the recording's free flight [{lo:.4f}, {hi:.4f}] s"
        )
    if hi - lo < 2.0 * half_window:
        raise InvalidInputError(
            f"the recording's free flight [{lo:.4f}, {hi:.4f}] s is shorter than the {2 * half_window:.3f} s fit window"
        )
    w_lo = min(max(time - half_window, lo), hi - 2.0 * half_window)
    sel = (t >= w_lo - 1e-9) & (t <= w_lo + 2.0 * half_window + 1e-9)
    if np.count_nonzero(sel) < max(LOCAL_FIT_MIN_SAMPLES, order + 2):
        raise InvalidInputError(
            f"only {np.count_nonzero(sel)} recorded samples in [{w_lo:.4f}, {w_lo + 2 * half_window:.4f}] s "
            f"(need {LOCAL_FIT_MIN_SAMPLES}): the recording does not cover {time:.4f} s"
        )
    coef = np.polynomial.polynomial.polyfit(t[sel] - time, p[sel], order)  # (order + 1, 3)
    return coef[0].copy(), coef[1].copy()
