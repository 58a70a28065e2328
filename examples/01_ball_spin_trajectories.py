"""Ball trajectories with topspin, backspin, sidespin and no spin, side and top views.

The same launch (a serve just after the strike: 0.3 m above the table behind the
server's end line, 5.1 m/s forward and down) with four spins of 200 rad/s is simulated
with :func:`studio.physics.ball.simulate` until the second table bounce, and drawn in a side view
(x-z) and a top view (x-y) with the table, net and bounce points. A table of the bounce
points and of the spin after the second bounce (paper's velocity-aligned components) is
printed.

Run: ``.venv/bin/python examples/01_ball_spin_trajectories.py [out.png]``
(default ``examples/out/01_ball_spin_trajectories.png``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import Rectangle

import studio

SPIN = 200.0
"""Spin magnitude of the examples [rad/s]."""

CASES = {
    "no spin": (0.0, 0.0, 0.0),
    "topspin (w_y > 0)": (0.0, SPIN, 0.0),
    "backspin (w_y < 0)": (0.0, -SPIN, 0.0),
    "sidespin (w_z > 0, curves left)": (0.0, 0.0, SPIN),
}
COLORS = ("0.3", "tab:red", "tab:blue", "tab:green")


def main(out: Path) -> None:
    court = studio.DEFAULT_COURT
    launch_p, launch_v = (-1.5, 0.0, 0.3), (4.5, 0.0, -2.5)
    fig, (ax_side, ax_top) = plt.subplots(
        2, 1, figsize=(12, 7.5), constrained_layout=True, gridspec_kw={"height_ratios": [1.0, 1.6]}
    )
    hl, hw = court.half_length, court.half_width

    ax_side.add_patch(Rectangle((-hl, -court.thickness), court.length, court.thickness, color="tab:green", alpha=0.4))
    ax_side.plot([0, 0], [0, court.net_height], color="k", lw=2)
    ax_top.add_patch(Rectangle((-hl, -hw), court.length, court.width, fc="tab:green", alpha=0.25, ec="k"))
    ax_top.plot([0, 0], [-court.net_half_span, court.net_half_span], color="k", lw=2)
    ax_top.plot([-hl, hl], [0, 0], color="w", lw=1)

    print(
        f"{'case':<34} {'1st bounce (x, y) [m]':>24} {'2nd bounce (x, y) [m]':>24} {'after 2nd: top/back, side [rad/s]':>36}"
    )
    for (label, w), color in zip(CASES.items(), COLORS, strict=True):
        traj = studio.simulate(
            studio.BallState(np.array(launch_p), np.array(launch_v), np.array(w)), 1.5, max_table_bounces=2
        )
        ax_side.plot(traj.p[:, 0], traj.p[:, 2], color=color, label=label)
        ax_top.plot(traj.p[:, 0], traj.p[:, 1], color=color, label=label)
        bounces = traj.table_bounces
        for e in bounces:
            ax_side.plot(e.p[0], e.p[2] - studio.DEFAULT_FLIGHT.radius, "o", color=color, ms=5)
            ax_top.plot(e.p[0], e.p[1], "o", color=color, ms=5)
        cells = [f"({e.p[0]:+.2f}, {e.p[1]:+.2f})" for e in bounces[:2]] + ["-"] * (2 - len(bounces[:2]))
        if len(bounces) >= 2:
            tb, ss, _ = studio.spin_components(bounces[1].v_after, bounces[1].w_after)
            spin = f"{float(tb):+7.1f}, {float(ss):+7.1f}"
        else:
            spin = "-"
        print(f"{label:<34} {cells[0]:>24} {cells[1]:>24} {spin:>36}")

    ax_side.set(
        xlabel="x [m] (towards the receiver)", ylabel="z [m]", title="Side view", xlim=(-1.7, 1.7), ylim=(-0.05, 0.45)
    )
    ax_side.set_aspect("equal")
    ax_top.set(xlabel="x [m]", ylabel="y [m]", title="Top view", xlim=(-1.7, 1.7), ylim=(-0.95, 0.95))
    ax_top.set_aspect("equal")
    ax_side.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"Same launch p={launch_p} m, v={launch_v} m/s; spin {SPIN:.0f} rad/s (dots: table bounces)")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    print(f"saved {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "out" / "01_ball_spin_trajectories.png")
