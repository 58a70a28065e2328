"""MuJoCo rollouts of a planned serve (robot, ball and table as native MuJoCo bodies).

One concept per module: :mod:`~studio.sim.scene` (the MuJoCo scene), :mod:`~studio.sim.options`,
:mod:`~studio.sim.contact` (a ball contact), :mod:`~studio.sim.robot_track` (the robot's
predicted motion, posed), :mod:`~studio.sim.contact_search` (when the ball touches a geom),
:mod:`~studio.sim.impact` (the rebound) and :mod:`~studio.sim.rollout`
(:func:`~studio.sim.rollout.rollout` and its result).
"""
