"""The minimum-jerk strike planner (racket position, normal and velocity at tau, back to rest, within limits).

One concept per module: :mod:`~studio.planning.planner` (:class:`~studio.planning.planner.StrikePlanner`);
:mod:`~studio.planning.strike` (start, target, plan); :mod:`~studio.planning.options`;
:mod:`~studio.planning.problem` (the problem, with :mod:`~studio.planning.chain`,
:mod:`~studio.planning.scaling` and :mod:`~studio.planning.racket_terms`); the solvers
:mod:`~studio.planning.sqp` (with :mod:`~studio.planning.newton_sqp`) and
:mod:`~studio.planning.ipopt`; :mod:`~studio.planning.check` (the a-posteriori check);
:mod:`~studio.planning.kinematics_casadi`. A whole serve: :mod:`~studio.planning.preparation`,
:mod:`~studio.planning.settle`, :mod:`~studio.planning.serve_plan`
(:func:`~studio.planning.serve_plan.plan_serve`).
"""
