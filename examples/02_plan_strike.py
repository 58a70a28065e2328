"""Plan the strike of a serve with the minimum-jerk planner, then sweep its racket speed.

The strike of an example serve (``examples/serves/topspin_right.json``) is planned from the
robot's moving state 60 ms after the toss releases the ball (as evaluations do) to the
racket position, face normal and velocity at the contact time tau, then back to rest.
The plan is checked for collisions with coal. The same target is then planned with the
racket velocity scaled from 0.25x to 5x (warm-started from the first plan): faster strikes
put more joint limits into play (more QPs), and beyond what the joints can do the plan
comes back invalid with the planner's reason (after the IPOPT fallback tried too).

Run: ``.venv/bin/python examples/02_plan_strike.py [SERVE.json]``
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import studio

DEFAULT_SERVE = Path(__file__).resolve().parent / "serves" / "topspin_right.json"
SPEED_SCALES = (0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0)
"""Racket velocity scales of the sweep [-]."""


def describe(plan: studio.Plan) -> str:
    """One line: status, solve time, QPs, errors at tau (or the reason)."""
    if not plan.ok:
        return f"{plan.status:<10} {plan.solve_time_ms:7.1f} ms  {plan.reason}"
    return (
        f"{plan.status:<10} {plan.solve_time_ms:7.1f} ms  {plan.iterations:2d} QPs  errors at tau: "
        f"{1e3 * plan.position_error:.2f} mm, {np.degrees(plan.angle_error):.3f} deg, {plan.velocity_error:.4f} m/s"
    )


def main(serve_path: Path) -> None:
    robot = studio.load_robot()
    planner = studio.StrikePlanner(robot)
    checker = studio.CollisionChecker(robot)
    serve = studio.load_serve(serve_path)
    toss = studio.load_default_toss_model(serve.side, robot)
    prim = toss.primitive
    t_switch = float(prim.t[prim.index_at(toss.t_lift + studio.SWITCH_DELAY)])
    start, _ = studio.start_from_toss(prim, t_switch)  # commands and predicted joint state at the hand-over
    racket = studio.strike_target(serve, toss)  # world frame, from the toss's mean path at tau
    p = serve.params
    print(
        f"serve {serve.name!r} ({serve.side} toss): contact at tau = {p.tau:.3f} s, racket at {np.round(racket.position, 3)} m"
    )
    print(
        f"  normal {np.round(racket.normal, 3)}, velocity {np.round(racket.velocity, 2)} m/s, back at rest {p.t_return:.2f} s later\n"
    )

    def target(scale: float) -> studio.StrikeTarget:
        return studio.StrikeTarget(
            tau=p.tau - t_switch,  # on the strike's own clock (0 = hand-over)
            position=np.asarray(racket.position),
            normal=np.asarray(racket.normal),
            velocity=scale * np.asarray(racket.velocity),
            tau_f=p.tau - t_switch + p.t_return,
            u_rest=robot.q_rest,
        )

    plan = planner.plan(start, target(1.0))
    print("plan:     ", describe(plan))
    if plan.ok:
        report = checker.check(plan.t, plan.q)
        print("collision:", report.describe())
        print(f"           {len(plan.t)} samples at 1 kHz, jerk cost {plan.jerk_cost:.4f}\n")
    print(f"{'speed x':>8}  {'|v| [m/s]':>9}  result")
    for scale in SPEED_SCALES:
        tg = target(scale)
        print(f"{scale:8.2f}  {np.linalg.norm(tg.velocity):9.2f}  {describe(planner.plan(start, tg, warm_start=plan))}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_SERVE)
