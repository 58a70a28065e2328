"""The toss model: statistics of a toss from its recordings (paper: mean path
``p_bar(t)``, ``t_lift`` and the spread of the ball around the mean), and the ball
states the strike planner and the evaluations start from.

Times are on the *command clock* of the toss primitive (``t = 0`` is the first sample of
``u_t``); recordings carry their own clock until aligned. World frame of ``DESIGN.md``
(origin at the centre of the playing surface, +X towards the receiver, +Z up), SI units.

``serve-studio toss --generate ...`` writes the shipped recordings (:func:`studio.toss.defaults.generate_default_recordings`)
(and prints their summary).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final, Literal

import numpy as np
import numpy.typing as npt

from studio import constants as C
from studio.errors import InvalidInputError
from studio.toss.alignment import align_recordings
from studio.toss.flight import hermite_interpolate, spinless_flight
from studio.toss.lift_time import estimate_t_lift
from studio.toss.local_fit import (
    LOCAL_FIT_HALF_WINDOW,
    LOCAL_FIT_LIFT_MARGIN,
    LOCAL_FIT_ORDER,
    local_fit_state,
)
from studio.toss.primitive import TossPrimitive, TossSide
from studio.toss.recordings import TossRecording, TossRecordings
from studio.toss.smoothing import SMOOTHING_ORDER, SMOOTHING_WINDOW, smooth_recording

if TYPE_CHECKING:
    from studio.physics.ball import BallState

FloatArray = npt.NDArray[np.float64]

BACK_FLIGHT_STEP: Final[float] = 0.025
"""Longest RK4 step [s] of the spinless flight integrated back from a recorded state
(:meth:`TossModel.recorded_start_state`): :func:`studio.physics.ball.simulate`'s forward flight
then meets the recorded state within 1e-6 m (0.01 s: 1e-7 m, 2.5 times the cost)."""


@dataclass(frozen=True, eq=False)
class TossModel:
    """Statistical model of a toss from recordings (paper: mean path ``p_bar(t)``,
    ``t_lift`` and the spread of the ball around the mean).

    Per-toss states: in free flight (from ``t_lift`` + :data:`LOCAL_FIT_LIFT_MARGIN`
    to the end of a recording) a recorded toss's state at a time comes from its own
    samples around that time (:meth:`recorded_state_at`, a local polynomial fit), not
    from a state just after the lift flown forward: the velocity estimated there carries
    ~50-80 mm/s of noise per axis, which spreads such predictions ~7 times wider at the
    strike than the recordings themselves. Recordings measure positions only: the
    states carry zero spin (the toss releases the ball without spin, ITTF Law 2.6.2).

    All times are on the primitive's command clock. Arrays are read-only.
    """

    side: TossSide
    """Toss side of the primitive."""
    primitive: TossPrimitive
    """The toss primitive the recordings execute."""
    t: FloatArray
    """Time grid (N,) [s] (command clock, the primitive's step), covered by every recording."""
    p: FloatArray
    """Mean ball path ``p_bar`` (N, 3) [m]: mean of the Savitzky-Golay-smoothed,
    time-aligned recordings."""
    v: FloatArray
    """Mean ball velocity (N, 3) [m/s] (derivative of the smoothed paths)."""
    a: FloatArray
    """Mean ball acceleration (N, 3) [m/s^2] (Savitzky-Golay second derivative)."""
    t_lift: float
    """Time the ball's acceleration reaches free flight (see :func:`~studio.toss.lift_time.estimate_t_lift`) [s]."""
    spread: FloatArray
    """Std. dev. over the tosses of their deviation from the mean path (N, 3) [m]."""
    tosses_p: FloatArray
    """Smoothed aligned path of each toss on the grid (K, N, 3) [m]."""
    tosses_v: FloatArray
    """Smoothed aligned velocity of each toss on the grid (K, N, 3) [m/s]."""
    recordings: TossRecordings
    """The recordings with their times moved to the command clock (truth kept)."""
    clock_offsets: FloatArray
    """Estimated recording-clock minus command-clock offset per toss (K,) [s]."""
    z_bias: FloatArray
    """Estimated height offset of each recording against the predicted cup path (K,) [m]
    (diagnostic of the tracking calibration; not removed from the data)."""
    lift_fit_rms: float
    """RMS residual of the ``t_lift`` fit [m] (about the tracking noise when it fits)."""
    _start_cache: dict[tuple[object, ...], FloatArray] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )
    """Cache of :meth:`_recorded_start_states` per (t_start, t_target, flight) (internal)."""

    def __post_init__(self) -> None:
        for fname in ("t", "p", "v", "a", "spread", "tosses_p", "tosses_v", "clock_offsets", "z_bias"):
            arr = np.array(getattr(self, fname), dtype=float)
            arr.setflags(write=False)
            object.__setattr__(self, fname, arr)

    @property
    def n_tosses(self) -> int:
        """Number of recorded tosses."""
        return int(self.tosses_p.shape[0])

    @property
    def spread_norm(self) -> FloatArray:
        """Spread magnitude (N,) [m]: ``sqrt(sum of the per-axis variances)``."""
        return np.sqrt(np.sum(self.spread**2, axis=1))

    def _check_t(self, time: float) -> float:
        tt = float(time)
        if not (math.isfinite(tt) and self.t[0] - 1e-9 <= tt <= self.t[-1] + 1e-9):
            raise InvalidInputError(
                f"toss model {self.primitive.name!r}: time {time} s outside the recorded range "
                f"[{self.t[0]:.3f}, {self.t[-1]:.3f}] s"
            )
        return min(max(tt, float(self.t[0])), float(self.t[-1]))

    def spread_at(self, time: float) -> FloatArray:
        """Per-axis spread (3,) [m] at ``time`` [s] (linear interpolation)."""
        tt = self._check_t(time)
        return np.array([np.interp(tt, self.t, self.spread[:, j]) for j in range(3)])

    def mean_state(self, time: float) -> BallState:
        """Mean ball state at ``time`` [s] (command clock): position (cubic Hermite),
        velocity (linear), zero spin (the toss releases the ball without spin)."""
        from studio.physics.ball import BallState

        tt = self._check_t(time)
        p = hermite_interpolate(self.t, self.p, self.v, np.array([tt]))[0]
        v = np.array([np.interp(tt, self.t, self.v[:, j]) for j in range(3)])
        return BallState(p=p, v=v, w=np.zeros(3))

    def ball_states_at(self, time: float) -> tuple[BallState, ...]:
        """State of every recorded toss at ``time`` [s] (:meth:`recorded_state_at`), zero spin."""
        return tuple(self.recorded_state_at(time, k) for k in range(self.n_tosses))

    def _check_k(self, k: int) -> int:
        """``k`` as a toss index in ``[0, n_tosses)``, else InvalidInputError."""
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not (0 <= k < self.n_tosses):
            raise InvalidInputError(f"toss index must be an integer in [0, {self.n_tosses}), got {k!r}")
        return int(k)

    @property
    def free_flight_start(self) -> float:
        """Earliest time [s] whose recorded states come from the local fit:
        ``t_lift`` + :data:`LOCAL_FIT_LIFT_MARGIN`."""
        return float(self.t_lift) + LOCAL_FIT_LIFT_MARGIN

    def recorded_state_at(self, time: float, k: int) -> BallState:
        """State of recorded toss ``k`` at ``time`` [s] (command clock), zero spin.

        In free flight (``time >= free_flight_start``): a polynomial of order
        :data:`LOCAL_FIT_ORDER` fitted to the toss's own recorded positions within
        +/- :data:`LOCAL_FIT_HALF_WINDOW` of ``time`` gives the position [m] and its
        derivative the velocity [m/s] (the window is shifted to stay after
        ``free_flight_start`` and before the recording's last sample: one-sided near
        them, no extrapolation). Every time of the model's interval is covered by every
        recording (the interval is their common one). Before that (ball in the cup or
        just leaving it): the Savitzky-Golay-smoothed path, as before.

        Raises:
            InvalidInputError: ``time`` outside the toss model's interval, ``k`` not a
                toss index, or a recording with a gap (too few samples in the window).
        """
        from studio.physics.ball import BallState

        k = self._check_k(k)
        tt = self._check_t(time)
        if tt < self.free_flight_start:
            p = hermite_interpolate(self.t, self.tosses_p[k], self.tosses_v[k], np.array([tt]))[0]
            v = np.array([np.interp(tt, self.t, self.tosses_v[k, :, j]) for j in range(3)])
            return BallState(p=p, v=v, w=np.zeros(3))
        rec = self.recordings.recordings[k]
        span = (self.free_flight_start, float(rec.t[-1]))
        try:
            p, v = local_fit_state(rec.t, rec.p, tt, span, half_window=LOCAL_FIT_HALF_WINDOW, order=LOCAL_FIT_ORDER)
        except InvalidInputError as exc:
            raise InvalidInputError(f"toss model {self.primitive.name!r}, toss {rec.toss_id!r}: {exc}") from exc
        return BallState(p=p, v=v, w=np.zeros(3))

    def recorded_spread_at(self, time: float) -> FloatArray:
        """Per-axis standard deviation (3,) [m] (ddof = 1) of the recorded tosses'
        positions at ``time`` [s] (:meth:`recorded_state_at`): the spread robust
        evaluations fly the ball through at the strike."""
        P = np.array([s.p for s in self.ball_states_at(time)])
        return P.std(axis=0, ddof=1)

    def recorded_start_state(
        self, k: int, t_start: float, t_target: float, *, flight: object | None = None
    ) -> BallState:
        """Ball state of recorded toss ``k`` at ``t_start`` [s] from which a spinless
        flight in still air under ``flight`` (default :data:`studio.physics.ball.DEFAULT_FLIGHT`)
        passes through the toss's recorded state at ``t_target`` [s] (the strike time
        tau): :meth:`recorded_state_at` at ``t_target`` integrated back to ``t_start``
        (RK4, :data:`BACK_FLIGHT_STEP`). Robust evaluations fly the ball forward from it
        with the racket moving, so up to the strike the ball follows this toss's own
        recording (within ~1 mm at ``t_target``; earlier it departs by the room air flow
        and the fitted velocity's noise times the time before ``t_target``, a few mm).

        ``t_target`` before :attr:`free_flight_start` (or not after ``t_start``): the
        toss's state at ``t_start`` itself (no flight to aim at).

        Raises:
            InvalidInputError: times outside the model's interval, bad ``k``.
        """
        from studio.physics.ball import BallState

        k = self._check_k(k)
        t0, t1 = self._check_t(t_start), self._check_t(t_target)
        if t1 <= t0 or t1 < self.free_flight_start:
            return self.recorded_state_at(t0, k)
        X = self._recorded_start_states(t0, t1, flight)
        return BallState(p=X[k, :3], v=X[k, 3:], w=np.zeros(3))

    def mean_start_state(self, t_start: float, t_target: float, *, flight: object | None = None) -> BallState:
        """Ball state at ``t_start`` [s] from which a spinless flight in still air under
        ``flight`` (default :data:`studio.physics.ball.DEFAULT_FLIGHT`) passes through the mean
        path's state at ``t_target`` [s] (the strike time tau): the mean-toss evaluation
        flies from it, so the ball is exactly where the strike target assumes it at tau
        (:func:`studio.serve.evaluate.strike_target`). ``t_target`` before
        :attr:`free_flight_start` (or not after ``t_start``): :meth:`mean_state` at ``t_start``.

        Raises:
            InvalidInputError: times outside the model's interval.
        """
        from studio.physics import ball

        t0, t1 = self._check_t(t_start), self._check_t(t_target)
        if t1 <= t0 or t1 < self.free_flight_start:
            return self.mean_state(t0)
        target = self.mean_state(t1)
        fl = ball.DEFAULT_FLIGHT if flight is None else flight
        p0, v0 = spinless_flight(target.p[None, :], target.v[None, :], t1, t0, fl, step=BACK_FLIGHT_STEP)
        return ball.BallState(p=p0[0], v=v0[0], w=np.zeros(3))

    def _recorded_start_states(self, t_start: float, t_target: float, flight: object | None) -> FloatArray:
        """All tosses' :meth:`recorded_start_state` as (K, 6) ``[p, v]`` [m, m/s], cached
        per (t_start, t_target, flight): a robust evaluation asks for each toss in turn."""
        from studio.physics import ball

        fl = ball.DEFAULT_FLIGHT if flight is None else flight
        try:
            key: tuple[object, ...] | None = (t_start, t_target, fl)
            hash(key)
        except TypeError:
            key = None
        cached = self._start_cache.get(key) if key is not None else None
        if cached is not None:
            return cached
        states = self.ball_states_at(t_target)
        p1 = np.array([s.p for s in states])
        v1 = np.array([s.v for s in states])
        p0, v0 = spinless_flight(p1, v1, t_target, t_start, fl, step=BACK_FLIGHT_STEP)
        X = np.concatenate([p0, v0], axis=1)
        X.setflags(write=False)
        if key is not None:
            if len(self._start_cache) >= 256:
                self._start_cache.clear()
            self._start_cache[key] = X
        return X

    def sample(
        self, time: float, rng: np.random.Generator, *, method: Literal["gaussian", "recorded"] = "gaussian"
    ) -> BallState:
        """A random ball state at ``time`` [s], zero spin.

        ``"gaussian"``: mean state plus a deviation drawn from the recordings' joint
        position-velocity covariance at that time (a random combination of the tosses'
        deviations, so the 6-D correlations are kept); ``"recorded"``: one recorded toss
        picked uniformly.
        """
        from studio.physics.ball import BallState

        if method == "recorded":
            return self.recorded_state_at(time, int(rng.integers(self.n_tosses)))
        states = self.ball_states_at(time)
        if method != "gaussian":
            raise InvalidInputError(f"TossModel.sample: method must be 'gaussian' or 'recorded', got {method!r}")
        X = np.array([np.concatenate([s.p, s.v]) for s in states])
        mean = X.mean(axis=0)
        dev = X - mean
        K = X.shape[0]
        draw = mean + (rng.standard_normal(K) @ dev) / math.sqrt(max(K - 1, 1))
        return BallState(p=draw[:3], v=draw[3:], w=np.zeros(3))

    @classmethod
    def from_recordings(
        cls,
        primitive: TossPrimitive,
        recordings: TossRecordings,
        *,
        smoothing_window: float = SMOOTHING_WINDOW,
        smoothing_order: int = SMOOTHING_ORDER,
    ) -> TossModel:
        """Build the toss model from recordings of ``primitive`` (paper's procedure).

        1. Time alignment (:func:`~studio.toss.alignment.align_recordings`): each
           recording's clock offset is estimated by least squares of its heights while
           the ball rides up in the cup against the primitive's predicted cup height,
           after a coarse match of the half-way crossing; this puts every toss on the
           command clock.
        2. Each aligned recording is smoothed by a Savitzky-Golay filter
           (``smoothing_window`` [s], order ``smoothing_order``), interpolated on the
           primitive's time grid over the interval every recording covers by a cubic
           spline (velocity = its derivative; acceleration = the filter's second
           derivative); the mean over tosses is ``p_bar(t)``.
        3. ``t_lift``: :func:`~studio.toss.lift_time.estimate_t_lift` around the instant
           the mean acceleration drops below ``-g/2`` after the peak upward speed.
        4. Spread: per-axis standard deviation of the tosses' smoothed paths around the
           mean (ddof = 1).

        Raises:
            InvalidInputError: fewer than 3 tosses, a recording that cannot be aligned
                (no in-cup samples) or no common time interval.
        """
        recs = recordings.recordings
        if len(recs) < 3:
            raise InvalidInputError(f"TossModel: need at least 3 recorded tosses, got {len(recs)}")
        aligned, offsets, biases = align_recordings(primitive, recs)
        grid, P, V, Acc = _smoothed_paths(primitive.t, aligned, smoothing_window, smoothing_order)
        p_mean = P.mean(axis=0)
        v_mean = V.mean(axis=0)
        a_mean = Acc.mean(axis=0)
        spread = P.std(axis=0, ddof=1)

        i_peak = int(np.argmax(v_mean[:, 2]))
        below = np.flatnonzero(a_mean[i_peak:, 2] <= -0.5 * C.GRAVITY)
        if below.size == 0:
            raise InvalidInputError("TossModel: the mean path never decelerates like a released ball")
        t_rough = float(grid[i_peak + int(below[0])])
        t_lift, rms = estimate_t_lift(primitive, aligned, t_rough)
        return cls(
            side=primitive.side,
            primitive=primitive,
            t=grid,
            p=p_mean,
            v=v_mean,
            a=a_mean,
            t_lift=t_lift,
            spread=spread,
            tosses_p=P,
            tosses_v=V,
            recordings=TossRecordings(recordings=aligned, truth=recordings.truth),
            clock_offsets=offsets,
            z_bias=biases,
            lift_fit_rms=rms,
        )


def _smoothed_paths(
    t: FloatArray, aligned: tuple[TossRecording, ...], window: float, order: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The aligned recordings smoothed (Savitzky-Golay, ``window`` [s], ``order``) and
    interpolated by a cubic spline on the part of the primitive's grid ``t`` every
    recording covers: grid (N,) [s], positions, velocities (the spline's derivative) and
    accelerations (the filter's second derivative), each (K, N, 3).

    Raises:
        InvalidInputError: no common time interval (fewer than 10 grid points).
    """
    from scipy.interpolate import CubicSpline

    smoothed = [smooth_recording(r.t, r.p, window, order) for r in aligned]
    t_lo = max(s[0][0] for s in smoothed)
    t_hi = min(s[0][-1] for s in smoothed)
    grid = t[(t >= t_lo) & (t <= t_hi)]
    if grid.size < 10:
        raise InvalidInputError("TossModel: the recordings have no common time interval")
    P = np.empty((len(smoothed), grid.size, 3))
    V = np.empty_like(P)
    Acc = np.empty_like(P)
    for k, (tu, ps, _, as_) in enumerate(smoothed):
        # C^2 spline through the smoothed frames: position and velocity consistent.
        spline = CubicSpline(tu, ps, axis=0)
        P[k] = spline(grid)
        V[k] = spline(grid, 1)
        for j in range(3):
            Acc[k, :, j] = np.interp(grid, tu, as_[:, j])
    return grid, P, V, Acc
