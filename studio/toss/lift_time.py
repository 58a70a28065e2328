"""``t_lift``: the time at which the recorded ball's acceleration reaches free flight,
fitted to time-aligned recordings (:func:`estimate_t_lift`). Times on the primitive's
command clock, SI units."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.toss.flight import free_flights, hermite_interpolate
from studio.toss.primitive import TossPrimitive
from studio.toss.recordings import TossRecording

FloatArray = npt.NDArray[np.float64]

LIFT_SEARCH: Final[tuple[float, float]] = (-0.03, 0.05)
"""Range [s] around the rough release estimate searched for ``t_lift``."""

LIFT_FIT_WINDOW: Final[tuple[float, float]] = (0.10, 0.25)
"""Data used by the ``t_lift`` fit [s]: from this long before the earliest candidate
to this long after the latest one."""


def estimate_t_lift(
    primitive: TossPrimitive,
    recordings: tuple[TossRecording, ...],
    t_rough: float,
    *,
    flight: object | None = None,
    step: float = 1e-3,
) -> tuple[float, float]:
    """Time at which the ball's acceleration reaches free flight, from aligned recordings.

    While the ball rides in the cup it moves with the cup, so its acceleration is the
    cup's (above free fall: the cup pushes it); once released its acceleration is that
    of free flight (gravity plus drag). For a candidate ``t_c`` every recording (on the
    command clock) is modelled as the predicted cup path before ``t_c`` and the free
    flight started from the cup's state at ``t_c`` after it, plus a per-recording,
    per-axis offset (tracking calibration) and post-release velocity deviation (arm
    vibration), fitted by least squares. ``t_lift`` is the candidate with the smallest
    residual (grid of ``step``, refined by a parabola): the instant from which the
    recorded ball stops following the cup and its acceleration is that of gravity.

    Why not a threshold on the Savitzky-Golay acceleration: with the +/-3 mm tracking
    noise an acceleration estimate good to ~0.5 m/s^2 needs a 60-100 ms window, which
    rounds off the release and delays a threshold crossing by a good part of the
    window (tens of ms), while the acceleration itself is continuous at the release
    (the cup releases the ball when its deceleration reaches g + drag). The fit uses
    the same physics without that bias.

    Accuracy: because the acceleration is continuous at the release, riding a few ms
    longer or shorter changes the path only at third order in the shift; for a
    vertical release (the cup moves only vertically, so x and y carry no information)
    the estimate scatters by ~2.5 ms (std, up to ~5 ms; 20 tosses, default
    :class:`~studio.toss.noise.TossNoise`), about 0.1 ms with tracking noise only. The mean path
    ``p_bar(t)`` does not depend on it.

    Args:
        primitive: the toss (its predicted cup path).
        recordings: recordings already on the command clock.
        t_rough: rough release time [s] (within about -30/+50 ms).
        flight: ball flight model (default :data:`studio.physics.ball.DEFAULT_FLIGHT`).
        step: candidate grid step [s].

    Returns:
        (t_lift [s], rms fit residual per coordinate [m]).
    """
    from studio.physics import ball

    fl = ball.DEFAULT_FLIGHT if flight is None else flight
    lo = max(t_rough + LIFT_SEARCH[0], float(primitive.t[1]))
    hi = min(t_rough + LIFT_SEARCH[1], float(primitive.t[-2]))
    w_lo, w_hi = lo - LIFT_FIT_WINDOW[0], hi + LIFT_FIT_WINDOW[1]
    cand = np.arange(lo, hi + step / 2, step)
    fit = _LiftFit.of(primitive, recordings, cand, (w_lo, w_hi), w_hi - lo + 0.01, fl)
    vals = np.array([fit.rss(c) for c in range(cand.size)])
    i = int(np.argmin(vals))
    t_best = float(cand[i])
    if 0 < i < cand.size - 1:
        y0, y1, y2 = vals[i - 1], vals[i], vals[i + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            t_best += 0.5 * step * (y0 - y2) / den
    return t_best, math.sqrt(float(vals[i]) / fit.p_all.size)


@dataclass(frozen=True, eq=False)
class _LiftFit:
    """The least-squares fit of :func:`estimate_t_lift`: the recorded samples in the fit
    window and, per candidate release time, the free flight from the cup's state then."""

    cand: FloatArray
    """Candidate release times (C,) [s]."""
    flights: tuple[FloatArray, FloatArray, FloatArray]
    """Free flights from each candidate: times (C, M), positions and velocities (C, M, 3)."""
    t_all: FloatArray
    """Recorded sample times in the window, all recordings (S,) [s]."""
    p_all: FloatArray
    """Recorded positions (S, 3) [m]."""
    k_all: npt.NDArray[np.intp]
    """Recording index of each sample (S,)."""
    cup_all: FloatArray
    """Predicted cup centre at each sample time (S, 3) [m]."""
    n_k: FloatArray
    """Samples per recording (K,)."""

    @classmethod
    def of(
        cls,
        primitive: TossPrimitive,
        recordings: tuple[TossRecording, ...],
        cand: FloatArray,
        window: tuple[float, float],
        flight_time: float,
        flight: object,
    ) -> _LiftFit:
        """The fit data of ``recordings`` in ``window`` = (lo, hi) [s] for the candidates
        ``cand``, with free flights of ``flight_time`` [s]."""
        w_lo, w_hi = window
        t = primitive.t
        cup = primitive.cup_p
        cup_v = np.gradient(cup, t, axis=0, edge_order=2)
        p0 = hermite_interpolate(t, cup, cup_v, cand)
        v0 = np.stack([np.interp(cand, t, cup_v[:, j]) for j in range(3)], axis=1)
        flights = free_flights(p0, v0, cand, flight_time, flight)
        ts, ps, ks = [], [], []
        for k, rec in enumerate(recordings):
            sel = (rec.t >= w_lo) & (rec.t <= w_hi)
            ts.append(rec.t[sel])
            ps.append(rec.p[sel])
            ks.append(np.full(np.count_nonzero(sel), k))
        t_all = np.concatenate(ts)
        k_all = np.concatenate(ks)
        K = len(recordings)
        if t_all.size < 4 * K:
            raise InvalidInputError("estimate_t_lift: too few recorded samples around the release")
        n_k = np.bincount(k_all, minlength=K).astype(float)
        return cls(cand, flights, t_all, np.concatenate(ps), k_all, hermite_interpolate(t, cup, cup_v, t_all), n_k)

    def rss(self, c: int) -> float:
        """Residual sum of squares [m^2] of the fit with the release at candidate ``c``.

        Offsets b_k (all samples) and post-release velocity deviations d_k with
        sum_k d_k = 0 (the arm's vibration has zero mean), same design for x, y, z: recording
        k's samples are fitted by b_k + d_k x, x = t - tc after the release (0 before).
        Solved in O(samples), not by a dense least squares on the 2K-1 unknowns (O(K^3), too
        slow for a few hundred recordings: ``docs/measured.md``): per recording the
        unconstrained fit explains r0_k^2 / n_k + cr_k^2 / c2_k (mean, then the centred
        slope: cr_k = sum (x - xbar_k) r, c2_k = sum (x - xbar_k)^2), and the one constraint
        sum d_k = 0 adds (sum_k dhat_k)^2 / sum_k (1 / c2_k) with dhat_k = cr_k / c2_k; it
        costs nothing when some d_k is not determined (c2_k = 0: no sample after tc, or one).
        Equal to the dense least-squares RSS to rounding (tests/test_toss.py).
        """
        FT, FP, FV = self.flights
        K, k_all, t_all, n_k = self.n_k.size, self.k_all, self.t_all, self.n_k
        tc = self.cand[c]
        after = t_all >= tc
        model = self.cup_all.copy()
        model[after] = hermite_interpolate(FT[c], FP[c], FV[c], t_all[after])
        r = self.p_all - model
        x = np.where(after, t_all - tc, 0.0)
        return _constrained_rss(K, k_all, n_k, x, r)


def _constrained_rss(K: int, k_all: npt.NDArray[np.intp], n_k: FloatArray, x: FloatArray, r: FloatArray) -> float:
    """RSS of the fit of :meth:`_LiftFit.rss` (residuals ``r`` (S, 3), slopes ``x`` (S,),
    recording ``k_all`` (S,) of each sample, ``n_k`` (K,) samples per recording)."""
    has = n_k > 0
    xbar = np.divide(np.bincount(k_all, weights=x, minlength=K), n_k, out=np.zeros(K), where=has)
    cx = x - xbar[k_all]
    c2 = np.bincount(k_all, weights=cx * cx, minlength=K)
    r0 = np.stack([np.bincount(k_all, weights=r[:, j], minlength=K) for j in range(3)], axis=1)  # (K, 3)
    cr = np.stack([np.bincount(k_all, weights=cx * r[:, j], minlength=K) for j in range(3)], axis=1)
    sloped = c2 > 1e-18  # d_k determined
    explained = np.sum(r0[has] ** 2 / n_k[has, None]) + np.sum(cr[sloped] ** 2 / c2[sloped, None])
    penalty = 0.0
    if np.all(sloped):  # otherwise an undetermined d_k (also of a recording without samples) takes up the constraint
        dhat = cr[sloped] / c2[sloped, None]
        penalty = float(np.sum(np.sum(dhat, axis=0) ** 2) / np.sum(1.0 / c2[sloped]))
    return float(np.sum(r * r) - explained + penalty)
