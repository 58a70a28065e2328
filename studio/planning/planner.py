"""Strike motion planner: minimum-jerk joint commands that bring the racket to a desired
position, face normal and velocity at a desired time (paper, section "Parametrized
motion planner for dynamic ball intersection", problem (eq:nlp)).

:class:`StrikePlanner` is built once per robot and option set and plans one strike per
call. The pieces, one module each:

- :mod:`studio.planning.strike`: the start state, the target and the :class:`~studio.planning.strike.Plan`;
- :mod:`studio.planning.options`: tolerances, slack weights, solver settings;
- :mod:`studio.planning.problem`: the problem (time grid, exact discretization of the
  command/joint chain from :mod:`studio.planning.chain`, racket errors at tau, limit
  rows), with the limit scaling of :mod:`studio.planning.scaling` and the casadi racket
  terms of :mod:`studio.planning.racket_terms`;
- :mod:`studio.planning.sqp` (default ``"sqp-daqp"``, the fast one: Levenberg-Marquardt and the
  Newton-SQP of :mod:`studio.planning.newton_sqp`) and :mod:`studio.planning.ipopt` (the
  paper's formulation with IPOPT: reference and fallback): the solvers (timings:
  ``docs/planner.md#planner-benchmark``);
- :mod:`studio.planning.check`: the a-posteriori check at 1 kHz; failures give an
  invalid :class:`~studio.planning.strike.Plan` with a reason, never an exception.

Frames and units: world frame of ``DESIGN.md`` (origin at the centre of the playing
surface, +X to the receiver, +Z up), SI units; joint order and units of
:mod:`studio.robot.model` (gantry x, y [m]; a1..a6 [rad]). Times are relative to the start
of the strike (t = 0 at the switch from the toss).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.planning.chain import FreeResponseTable
from studio.planning.check import SolveResult, better, check_jerks
from studio.planning.ipopt import IpoptSolver
from studio.planning.kinematics_casadi import CasadiKinematics, build_kinematics
from studio.planning.options import PlannerOptions, SolverName
from studio.planning.problem import PlannerSetup, StrikeProblem
from studio.planning.racket_terms import RacketTerms
from studio.planning.scaling import LimitScaling
from studio.planning.sqp import solve_sqp
from studio.planning.strike import Plan, StrikeStart, StrikeTarget, checked_vector
from studio.robot.description import RACKET_FRAME
from studio.robot.model import JointLimits, Robot

FloatArray = npt.NDArray[np.float64]


class StrikePlanner:
    """Minimum-jerk strike planner of the paper, built once per robot and option set.

    Holds the casadi kinematics of the racket frame, the scaled limit data and (lazily)
    one IPOPT problem per tau split. Not thread-safe (casadi buffers, pinocchio data):
    use one planner per thread.

    Example::

        planner = StrikePlanner(load_robot())
        plan = planner.plan(StrikeStart.at_rest(robot.q_flat), target)
        if plan.ok: send(plan.u)
    """

    def __init__(self, robot: Robot, *, options: PlannerOptions | None = None) -> None:
        self.robot = robot
        self.options = options if options is not None else PlannerOptions()
        self.limits: JointLimits = self.options.limits if self.options.limits is not None else robot.limits
        self.dynamics = robot.dynamics
        self.kin: CasadiKinematics = build_kinematics(robot.model, RACKET_FRAME)
        self.n = self.options.n_segments
        self.setup = PlannerSetup(
            robot=robot,
            dynamics=self.dynamics,
            limits=self.limits,
            options=self.options,
            scaling=LimitScaling.of(self.limits, self.options.limit_tolerance),
            terms=RacketTerms(self.kin),
            free_table=FreeResponseTable(self.dynamics, self.options.dt),
        )
        """What every strike problem of this planner shares."""
        self.ipopt = IpoptSolver(self.kin, self.options)
        """The IPOPT solver (NLPs cached per tau split)."""

    def plan(
        self,
        start: StrikeStart,
        target: StrikeTarget,
        *,
        solver: SolverName | None = None,
        warm_start: Plan | None = None,
    ) -> Plan:
        """Plan the strike from ``start`` to ``target``.

        Args:
            start: initial command and joint state (e.g. from the toss at the switch).
            target: racket state at tau and end of the strike.
            solver: "sqp-daqp" or "ipopt" (default: ``options.solver``).
            warm_start: a previous plan (e.g. of a neighbouring target): its
                (q_tau, q'_tau) seeds the solver, which selects among the local minima
                (the roll about the racket normal is free).

        Returns:
            A :class:`~studio.planning.strike.Plan`; invalid targets give a plan with
            ``ok == False`` and a reason.

        Raises:
            InvalidInputError: non-finite or mis-shaped inputs, unknown solver.
        """
        t0 = time.perf_counter()
        if not isinstance(start, StrikeStart):
            raise InvalidInputError(f"plan: start must be a StrikeStart, got {type(start).__name__}")
        if not isinstance(target, StrikeTarget):
            raise InvalidInputError(f"plan: target must be a StrikeTarget, got {type(target).__name__}")
        solver = solver if solver is not None else self.options.solver
        if solver not in ("sqp-daqp", "ipopt"):
            raise InvalidInputError(f"plan: solver must be 'sqp-daqp' or 'ipopt', got {solver!r}")
        problem = self._problem(start, target)
        bad = problem.check_inputs()
        if bad:
            return Plan.empty("infeasible", bad, target, start, _elapsed_ms(t0))
        seed = None
        if warm_start is not None and warm_start.q_tau.shape == (8,) and np.all(np.isfinite(warm_start.q_tau)):
            seed = np.concatenate([warm_start.q_tau, warm_start.qd_tau])
        if solver == "ipopt":
            res = self.ipopt.solve(problem, seed_z=None, seed_s=seed)
        else:
            res = solve_sqp(problem, seed)
            if self.options.fallback and res.status != "ok":
                alt = self.ipopt.solve(problem, seed_z=res.z, seed_s=seed)
                if better(alt, res):
                    res = replace(alt, iterations=alt.iterations + res.iterations)
        return _make_plan(problem, res, t0)

    def plan_joint_target(
        self, start: StrikeStart, target: StrikeTarget, q_tau: npt.ArrayLike, qd_tau: npt.ArrayLike
    ) -> Plan:
        """Minimum-jerk plan through a given *joint* state at tau (no end-effector
        constraints): the closed-form solution of the reduced problem at s = (q_tau,
        qd_tau), checked like :meth:`plan` (limits at 1 kHz, racket errors against
        ``target``). A plan with status "ok" certifies that ``target`` is reachable
        within the limits (used by the benchmark to build reachable targets)."""
        t0 = time.perf_counter()
        qa = checked_vector(q_tau, (8,), "plan_joint_target q_tau")
        qda = checked_vector(qd_tau, (8,), "plan_joint_target qd_tau")
        problem = self._problem(start, target)
        bad = problem.check_inputs()
        if bad:
            return Plan.empty("infeasible", bad, target, start, _elapsed_ms(t0))
        z = problem.reduced.z_of_s(np.concatenate([qa, qda]))
        check = check_jerks(problem, z)
        return _make_plan(problem, SolveResult(check.status, check.reason, z, "joint-space", 0, check.score, check), t0)

    def evaluate(self, q: npt.ArrayLike, qd: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Racket position [m], normal and velocity [m/s] (world) at (q, qd) (casadi FK)."""
        p, n, v = self.setup.terms.terms(np.asarray(q, dtype=float), np.asarray(qd, dtype=float))[:3]
        return p, n, v

    def _problem(self, start: StrikeStart, target: StrikeTarget) -> StrikeProblem:
        """The problem of one call, ending at ``target.u_rest`` (default: the robot's q_rest)."""
        u_rest = target.u_rest if target.u_rest is not None else self.robot.q_rest
        return StrikeProblem(self.setup, start, target, np.asarray(u_rest, dtype=float))


def _elapsed_ms(t0: float) -> float:
    """Wall time since ``t0`` (``time.perf_counter``) [ms]."""
    return 1e3 * (time.perf_counter() - t0)


def _make_plan(problem: StrikeProblem, res: SolveResult, t0: float) -> Plan:
    """The :class:`~studio.planning.strike.Plan` of a solver's result (empty without a check)."""
    g = problem.grid
    check = res.check
    if check is None or res.z is None:
        return Plan.empty(res.status, res.reason, problem.target, problem.start, _elapsed_ms(t0))
    Z, Cm = check.Z, check.C
    jc = 0.5 * float(np.sum(g.w[None, :] * res.z**2))

    def ro(a: FloatArray) -> FloatArray:
        a = np.ascontiguousarray(a)
        a.setflags(write=False)
        return a

    return Plan(
        status=res.status,
        reason=res.reason,
        target=problem.target,
        start=problem.start,
        t=ro(check.t),
        u=ro(Cm[..., 0]),
        ud=ro(Cm[..., 1]),
        udd=ro(Cm[..., 2]),
        q=ro(Z[..., 3]),
        qd=ro(Z[..., 4]),
        segment_times=ro(g.tb.copy()),
        n_tau=g.n1,
        jerk=ro((res.z * problem.setup.scaling.jmax[:, None]).T),
        q_tau=ro(check.q_tau),
        qd_tau=ro(check.qd_tau),
        position_error=float(check.ep),
        angle_error=float(check.ang),
        velocity_error=float(check.ev),
        slacks=ro(check.slacks),
        jerk_cost=jc,
        solver=res.solver,
        iterations=res.iterations,
        solve_time_ms=_elapsed_ms(t0),
    )
