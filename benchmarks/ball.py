"""Benchmark of the ball simulator (:func:`studio.physics.ball.simulate`).

Prints a table of simulations per second for typical serve flights, without and with a
moving racket, and as the last line one JSON object with the figures.

Run: ``.venv/bin/python benchmarks/ball.py [--repeat N]``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable

import numpy as np
from scipy.special import erf

from studio.physics import ball as B


def serve_racket(tilt_deg: float = 20.0, velocity: tuple[float, float, float] = (4.0, 0.0, -1.0)) -> tuple[B.BallState, B.SampledRacketMotion]:
    """A falling ball at x = -1.6 m and a racket (face A tilted down by ``tilt_deg``) that
    strikes it at t = 0.1 s with a Gaussian speed profile of peak ``velocity`` [m/s];
    the racket path is sampled at 1 kHz over 0.3 s like a planner output."""
    x, z0, t_hit, sig = -1.6, 0.3, 0.1, 0.05
    ball = B.BallState([x, 0.0, z0], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0])
    z_hit = z0 - 0.5 * 0.1 - 0.5 * 9.81 * t_hit**2
    a = math.radians(tilt_deg)
    n = np.array([math.cos(a), 0.0, -math.sin(a)])
    y = np.array([math.sin(a), 0.0, math.cos(a)])
    R = np.stack([np.cross(y, n), y, n], axis=1)
    t = np.linspace(0.0, 0.3, 301)
    p_hit = np.array([x, 0.0, z_hit]) - n * 0.028
    s = sig * math.sqrt(math.pi) / 2 * erf((t - t_hit) / sig)
    p = p_hit[None] + s[:, None] * np.asarray(velocity)[None]
    return ball, B.SampledRacketMotion(t, p, np.repeat(R[None], len(t), axis=0))


def _rate(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    fn()  # warm-up
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(repeat):
            fn()
        best = min(best, (time.perf_counter() - t0) / repeat)
    return 1.0 / best, best * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=100, help="simulations per timing run (best of 3)")
    args = parser.parse_args()

    ball, racket = serve_racket()
    hit = B.simulate(ball, 1.5, racket=racket)
    strike = hit.events_of("racket")[0]
    after = B.BallState(strike.p, strike.v_after, strike.w_after)
    flight = B.simulate(after, 1.5, t0=strike.t)
    two = B.simulate(after, 1.5, t0=strike.t, max_table_bounces=2)

    cases: list[tuple[str, str, Callable[[], object], B.Trajectory]] = [
        ("serve_flight_1.5s", "serve after the strike, 1.5 s, all events", lambda: B.simulate(after, 1.5, t0=strike.t), flight),
        ("serve_to_2nd_bounce", "serve after the strike, stop at 2nd bounce", lambda: B.simulate(after, 1.5, t0=strike.t, max_table_bounces=2), two),
        ("serve_with_racket_1.5s", "falling ball + sampled racket, 1.5 s", lambda: B.simulate(ball, 1.5, racket=racket), hit),
    ]
    results: dict[str, dict[str, float | int | str]] = {}
    print(f"{'case':<24} {'description':<44} {'events':>22} {'sims/s':>9} {'ms/sim':>8}")
    print("-" * 112)
    for key, desc, fn, traj in cases:
        rate, ms = _rate(fn, args.repeat)
        kinds = ",".join(e.kind[0] for e in traj.events)
        results[key] = {"sims_per_s": round(rate, 1), "ms_per_sim": round(ms, 3), "events": kinds, "samples": int(len(traj.t))}
        print(f"{key:<24} {desc:<44} {kinds:>22} {rate:>9.0f} {ms:>8.2f}")
    print("(events: r = racket, t = table, n = net, f = floor)")
    print(json.dumps({"benchmark": "ball", **results}))


if __name__ == "__main__":
    main()
