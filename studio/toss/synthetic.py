"""Synthetic toss recordings: the noise-free ball path of a primitive and simulated
camera recordings of repeated executions (vibration, release jitter, air flow, tracking
noise, camera rate, phase and clock offset; :class:`~studio.toss.noise.TossNoise`).

Times on the primitive's command clock unless stated; world frame, SI units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.toss.flight import free_flights, hermite_interpolate, single_flight
from studio.toss.noise import DEFAULT_NOISE, TossNoise
from studio.toss.primitive import TossPrimitive
from studio.toss.recordings import TossRecording, TossRecordings, TossTruth
from studio.toss.release import Release, find_release

if TYPE_CHECKING:
    from studio.robot.model import Robot

FloatArray = npt.NDArray[np.float64]


def nominal_ball_path(
    primitive: TossPrimitive, *, flight: object | None = None, end_height: float = 0.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Noise-free ball path of a toss on the command grid: in the cup until the
    predicted release, then free flight (still air, no spin) until the ball falls
    below ``end_height`` [m] or the primitive ends.

    Returns:
        t (M,), p (M, 3) [m], v (M, 3) [m/s] on ``primitive.t[:M]``.
    """
    from studio.physics import ball

    fl = ball.DEFAULT_FLIGHT if flight is None else flight
    rel = primitive.release
    t = primitive.t
    v_cup = np.gradient(primitive.cup_p, t, axis=0, edge_order=2)
    ft, fp, fv = single_flight(rel.position, rel.velocity, rel.time, float(t[-1]), np.zeros(3), fl)
    after = t > rel.time
    tq = t[after]
    tq = tq[tq <= ft[-1]]
    p = np.concatenate([primitive.cup_p[~after], hermite_interpolate(ft, fp, fv, tq)])
    v = np.concatenate([v_cup[~after], np.stack([np.interp(tq, ft, fv[:, j]) for j in range(3)], axis=1)])
    below = np.flatnonzero((p[:, 2] < end_height) & (np.arange(len(p)) > np.count_nonzero(~after)))
    m = int(below[0]) if below.size else len(p)
    return t[:m].copy(), p[:m], v[:m]


def simulate_tosses(
    robot: Robot,
    primitive: TossPrimitive,
    n: int,
    rng: np.random.Generator,
    *,
    noise: TossNoise = DEFAULT_NOISE,
    flight: object | None = None,
    id_prefix: str | None = None,
) -> TossRecordings:
    """Execute a toss ``n`` times in simulation and record the ball like a camera would.

    Per toss: the primitive's commands run through ``robot.dynamics`` (predicted joint
    motion; the same every time), the ball rides in the cup and leaves it at the
    :func:`~studio.toss.release.find_release` instant plus a random jitter, with the cup's velocity plus a
    random arm-vibration perturbation; it then flies (drag relative to a random
    constant air flow, no spin; the equations of :class:`studio.physics.ball.FlightModel`)
    until it falls below
    ``noise.end_height`` or ``noise.t_max``. The camera samples it at
    ``noise.camera_rate`` with a random phase, from a random time before the release,
    adds Gaussian tracking noise and stamps the samples with its own clock (a random
    offset from the command clock).

    Args:
        robot: the robot (its joint dynamics and kinematics give the cup path).
        primitive: the toss primitive to execute.
        n: number of tosses (>= 1).
        rng: random generator (use a seeded one for reproducible data).
        noise: the randomness (:class:`~studio.toss.noise.TossNoise`).
        flight: ball flight model (default :data:`studio.physics.ball.DEFAULT_FLIGHT`).
        id_prefix: toss ids are ``f"{id_prefix}_{k:02d}"`` (default: the primitive name).

    Returns:
        :class:`TossRecordings` with the ground truth of every toss.
    """
    from studio.physics import ball

    if not (isinstance(n, int) and n >= 1):
        raise InvalidInputError(f"simulate_tosses: n must be an int >= 1, got {n!r}")
    fl = ball.DEFAULT_FLIGHT if flight is None else flight
    t = primitive.t
    cup, cup_v, rel = _executed_cup_motion(robot, primitive, fl)
    draws = _TossDraws.draw(rng, n, noise, rel.time, t)
    p_rel = hermite_interpolate(t, cup, cup_v, draws.t_rel)
    v_rel = np.stack([np.interp(draws.t_rel, t, cup_v[:, j]) for j in range(3)], axis=1) + draws.v_dev
    FT, FP, FV = free_flights(
        p_rel, v_rel, draws.t_rel, noise.t_max - float(np.min(draws.t_rel)), fl, wind=draws.wind, h=1e-3
    )
    prefix = id_prefix or primitive.name
    recs: list[TossRecording] = []
    truths: list[TossTruth] = []
    for k in range(n):
        tc, pc = _camera_samples(k, draws, noise, t, cup, cup_v, (FT[k], FP[k], FV[k]))
        pc = pc + noise.measurement * rng.standard_normal(pc.shape)
        recs.append(TossRecording(toss_id=f"{prefix}_{k:02d}", t=tc + draws.offset[k], p=pc))
        truths.append(
            TossTruth(
                clock_offset=float(draws.offset[k]),
                release_time=float(draws.t_rel[k]),
                release_p=p_rel[k],
                release_v=v_rel[k],
                wind=draws.wind[k],
            )
        )
    return TossRecordings(recordings=tuple(recs), truth=tuple(truths))


def _executed_cup_motion(
    robot: Robot, primitive: TossPrimitive, flight: object
) -> tuple[FloatArray, FloatArray, Release]:
    """Cup centre (N, 3) [m] and velocity (N, 3) [m/s] of the primitive's commands run
    through ``robot.dynamics``, and the release on that motion under ``flight``."""
    t = primitive.t
    X = robot.dynamics.simulate(primitive.u, primitive.dt, primitive.X[0])
    # FloatArray, not the 2-D type: numpy's 2-D np.gradient overload returns a tuple even with axis=
    cup: FloatArray = np.empty((t.size, 3))
    rot = np.empty((t.size, 3, 3))
    for k in range(t.size):
        cup[k] = robot.cup_position(X[k, :, 0])
        rot[k] = robot.fk(X[k, :, 0]).rotation
    cup_v = np.gradient(cup, t, axis=0, edge_order=2)
    rel = find_release(t, cup, rot[:, :, 2], rotation=rot, gravity=flight.gravity, drag_k=flight.drag_constant)  # type: ignore[attr-defined]
    if rel is None:
        raise InvalidInputError(f"simulate_tosses: the ball never leaves the cup in toss {primitive.name!r}")
    return cup, cup_v, rel


@dataclass(frozen=True, eq=False)
class _TossDraws:
    """The random draws of ``n`` tosses (toss by toss, in a fixed order: reproducible for a seed)."""

    t_rel: FloatArray
    """Release times (n,) [s] (command clock)."""
    v_dev: FloatArray
    """Release velocity perturbations (n, 3) [m/s]."""
    wind: FloatArray
    """Air velocities (n, 3) [m/s]."""
    t_start: FloatArray
    """Start of each recording (n,) [s] (command clock)."""
    phase: FloatArray
    """Camera frame phase of each recording (n,) [s]."""
    offset: FloatArray
    """Recording clock minus command clock (n,) [s]."""

    @classmethod
    def draw(cls, rng: np.random.Generator, n: int, noise: TossNoise, release_time: float, t: FloatArray) -> _TossDraws:
        """Draws around the predicted ``release_time`` [s], on the command grid ``t``."""
        frame = 1.0 / noise.camera_rate
        t_rel = np.empty(n)
        v_dev = np.empty((n, 3))
        wind = np.empty((n, 3))
        t_start = np.empty(n)
        phase = np.empty(n)
        offset = np.empty(n)
        for k in range(n):
            t_rel[k] = np.clip(release_time + noise.release_jitter * rng.standard_normal(), t[1], t[-2])
            v_dev[k] = noise.vibration * rng.standard_normal(3)
            wind[k] = [
                noise.wind * rng.standard_normal(),
                noise.wind * rng.standard_normal(),
                noise.wind_vertical * rng.standard_normal(),
            ]
            t_start[k] = max(0.0, t_rel[k] - rng.uniform(*noise.visible_before_release))
            phase[k] = rng.uniform(0.0, frame)
            offset[k] = rng.uniform(*noise.clock_offset)
        return cls(t_rel=t_rel, v_dev=v_dev, wind=wind, t_start=t_start, phase=phase, offset=offset)


def _camera_samples(
    k: int,
    draws: _TossDraws,
    noise: TossNoise,
    t: FloatArray,
    cup: FloatArray,
    cup_v: FloatArray,
    flight: tuple[FloatArray, FloatArray, FloatArray],
) -> tuple[FloatArray, FloatArray]:
    """Noise-free camera samples of toss ``k`` on the command clock: times (M,) [s] and
    ball positions (M, 3) [m], in the cup before its release, then on its free flight
    (times, positions, velocities), until the ball falls below ``noise.end_height``."""
    frame = 1.0 / noise.camera_rate
    t_start, phase, t_rel = draws.t_start[k], draws.phase[k], draws.t_rel[k]
    tc = t_start + phase + frame * np.arange(int((noise.t_max - t_start - phase) / frame) + 1)
    tc = tc[tc <= noise.t_max]
    pc = np.empty((tc.size, 3))
    inside = tc < t_rel
    pc[inside] = hermite_interpolate(t, cup, cup_v, tc[inside])
    pc[~inside] = hermite_interpolate(*flight, tc[~inside])
    falling = np.flatnonzero((pc[:, 2] < noise.end_height) & ~inside)
    if falling.size:
        tc, pc = tc[: falling[0]], pc[: falling[0]]
    return tc, pc
