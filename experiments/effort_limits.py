"""Derive the robot's peak effort limits (``effort`` in ``robots/serve_robot.toml``).

KUKA publishes no joint torques for the KR 6 R900 sixx, and the gantry is no specific
product, so the limits are stated estimates from a rule on published and stated data:

    effort_j = 1.25 * max over poses q of ( |g_j(q)| + M_jj(q) * a_j )

with the arm carrying its maximum payload (6 kg: the "6" of KR 6, Spez KR AGILUS sixx)
at an assumed load point 100 mm out from the flange face and 60 mm off its axis; g the
gravity torques and M the joint-space inertia (pinocchio, URDF rigid links plus the
payload, no drive inertia), a_j the joint's acceleration limit of the TOML; the maximum
over 20,000 uniformly random poses inside the joint ranges; 1.25 a reserve for the
coupling terms the single-axis rule leaves out (Coriolis and centrifugal forces, several
axes accelerating at once, the arm's reaction on the gantry). Rounded up to 2
significant digits. In words: each axis can hold the maximum payload anywhere and
accelerate it at its own acceleration limit, with a quarter in reserve. The serve robot
carries a 0.3 kg racket instead, which is where the headroom for the paper's "dynamic
limit expansion" comes from; a plan that still exceeds a limit is flagged and refused by
export unless the user raises that joint's limit (``studio.serve.efforts``).

    .venv/bin/python experiments/effort_limits.py [--samples 20000] [--seed 0]

Prints the table and the values to put into the TOML (then
``serve-studio robot-files`` regenerates the URDF).
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import pinocchio as pin

from studio.paths import robots_dir
from studio.robot.description import load_spec

PAYLOAD_KG = 6.0
"""Maximum payload of the KR 6 R900 sixx [kg] (Spez KR AGILUS sixx)."""
PAYLOAD_POINT = (0.06, 0.0, 0.10)
"""Assumed load point in the flange frame [m]: 60 mm off the flange axis, 100 mm out."""
RESERVE = 1.25
"""Factor for the coupling terms the single-axis rule leaves out [-]."""


def model_with_payload() -> pin.Model:
    """The URDF's model with the payload as a point mass fixed to the flange."""
    model = pin.buildModelFromUrdf(str(robots_dir() / "serve_robot.urdf"))
    flange = model.frames[model.getFrameId("flange")]
    payload = pin.Inertia(PAYLOAD_KG, np.array(PAYLOAD_POINT), np.zeros((3, 3)))
    model.appendBodyToJoint(flange.parentJoint, payload, flange.placement)
    return model


def single_axis_efforts(model: pin.Model, acceleration: np.ndarray, samples: int, seed: int) -> np.ndarray:
    """max over random poses of |g_j| + M_jj a_j per joint (nv,) [N | N m]."""
    data = model.createData()
    rng = np.random.default_rng(seed)
    worst = np.zeros(model.nv)
    for _ in range(samples):
        q = rng.uniform(model.lowerPositionLimit, model.upperPositionLimit)
        need = np.abs(pin.computeGeneralizedGravity(model, data, q)) + np.diag(pin.crba(model, data, q)) * acceleration
        worst = np.maximum(worst, need)
    return worst


def round_up_2(x: float) -> float:
    """``x`` rounded up to 2 significant digits."""
    step = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.ceil(x / step - 1e-9) * step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=20000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    joints = load_spec().actuated_joints
    acceleration = np.array([j.acceleration for j in joints])
    need = single_axis_efforts(model_with_payload(), acceleration, args.samples, args.seed)
    print(f"payload {PAYLOAD_KG} kg at {PAYLOAD_POINT} m (flange frame), reserve x{RESERVE}, {args.samples} poses\n")
    print("| joint | accel. limit | max |g| + M_jj a | x reserve | TOML effort (rounded up) | in the TOML now |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for j, a, n in zip(joints, acceleration, need):
        print(f"| {j.name} | {a:g} | {n:.1f} | {RESERVE * n:.1f} | {round_up_2(RESERVE * n):g} | {j.effort:g} |")


if __name__ == "__main__":
    main()
