"""Benchmark of studio.sim.rollout: rollouts per second on two serve-like scenarios.

Scenarios (1 kHz command grid, the shipped robot, default ball models):

- ``toss``: the toss primitive ``make_toss(robot, "right", duration=1.5)`` with the ball
  in the cup: release, flight up and down, the ball falling back onto the racket.
- ``strike``: a 2.0 s gantry sweep whose racket (face B) hits a falling ball, which then
  bounces on the server's and the receiver's half and reaches the floor (the rollout
  runs on to 2.0 s: ``stop_on_floor=False``).

Each is timed with the joint commands ``u`` (includes the joint-model simulation
``JointDynamics.simulate``) and with the predicted joint states ``X`` given. Prints a
table; the last line is one JSON object.

Run: ``.venv/bin/python benchmarks/rollout.py [--repeat 15]``
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np

from studio.physics import ball as B
from studio.toss import synthesis as T
from studio.robot.model import load_robot
from studio.sim.options import RolloutOptions
from studio.sim.rollout import RolloutResult, rollout
from studio.sim.scene import build_scene

DT = 1e-3


def _timed(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """Median and minimum wall time [s] of ``repeat`` calls (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times)


def _strike_scenario(robot) -> tuple[np.ndarray, np.ndarray, np.ndarray, B.BallState]:
    t = np.arange(2001) * DT
    s = np.clip((t - 0.25) / 0.45, 0.0, 1.0)
    u = np.tile(robot.q_rest, (t.size, 1))
    u[:, 0] = -0.8 + 0.9 * (10 * s**3 - 15 * s**4 + 6 * s**5)
    X = robot.dynamics.simulate(u, DT, np.stack([u[0], np.zeros(8)], axis=1))
    k = int(np.argmax(X[:, 0, 1]))
    target = robot.fk(X[k, :, 0]).position + np.array([0.025, 0.0, 0.0])
    z0 = target[2] + 0.5 * 9.81 * t[k] ** 2
    for _ in range(4):
        z0 += target[2] - B.simulate(B.BallState(np.array([*target[:2], z0]), np.zeros(3), np.zeros(3)), t[k]).p[-1, 2]
    return t, u, X, B.BallState(np.array([*target[:2], z0]), np.zeros(3), np.zeros(3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15, help="timed calls per row (median reported)")
    args = parser.parse_args()

    t0 = time.perf_counter()
    scene = build_scene()
    t_scene = time.perf_counter() - t0
    robot = load_robot()
    dyn = robot.dynamics

    prim = T.make_toss(robot, "right", duration=1.5)
    t_s, u_s, X_s, ball_s = _strike_scenario(robot)
    no_floor_stop = RolloutOptions(stop_on_floor=False)

    cases: list[tuple[str, str, Callable[[], RolloutResult]]] = [
        ("toss 1.5 s", "u", lambda: rollout(scene, t=prim.t, u=prim.u, X0=prim.X[0], ball="cup")),
        ("toss 1.5 s", "X", lambda: rollout(scene, t=prim.t, X=prim.X, ball="cup")),
        ("strike + 2 bounces 2.0 s", "u", lambda: rollout(scene, t=t_s, u=u_s, ball=ball_s, options=no_floor_stop)),
        ("strike + 2 bounces 2.0 s", "X", lambda: rollout(scene, t=t_s, X=X_s, ball=ball_s, options=no_floor_stop)),
    ]
    rows = []
    for name, given, fn in cases:
        res = fn()
        med, best = _timed(fn, args.repeat)
        rows.append(
            {
                "scenario": name,
                "input": given,
                "simulated_s": round(float(res.t_final - res.t[0]), 4),
                "contacts": " ".join(c.kind for c in res.contacts),
                "end": res.end_reason,
                "median_ms": round(med * 1e3, 2),
                "min_ms": round(best * 1e3, 2),
                "rollouts_per_s": round(1.0 / med, 1),
            }
        )
    sim_med, _ = _timed(lambda: dyn.simulate(u_s, DT, np.stack([u_s[0], np.zeros(8)], axis=1)), args.repeat)

    header = f"{'scenario':<26}{'input':<7}{'sim [s]':>8}{'median [ms]':>13}{'min [ms]':>10}{'rollouts/s':>12}  end / contacts"
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['scenario']:<26}{r['input']:<7}{r['simulated_s']:>8.3f}{r['median_ms']:>13.2f}{r['min_ms']:>10.2f}"
            f"{r['rollouts_per_s']:>12.1f}  {r['end']}: {r['contacts']}"
        )
    print(f"scene build (cold compile): {t_scene * 1e3:.1f} ms; JointDynamics.simulate of 2001 samples: {sim_med * 1e3:.2f} ms")
    print(
        json.dumps(
            {
                "benchmark": "rollout",
                "python": platform.python_version(),
                "repeat": args.repeat,
                "scene_build_ms": round(t_scene * 1e3, 2),
                "joint_model_simulate_2001_ms": round(sim_med * 1e3, 3),
                "rows": rows,
            }
        )
    )


if __name__ == "__main__":
    main()
