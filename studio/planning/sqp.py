"""The ``"sqp-daqp"`` solver of the strike planner (the default, and the fast one).

1. Reduced problem in s (16 variables). Without active limits the minimum jerk for a
   given s is a quadratic in s (per joint a 2x2 block; jerks in closed form,
   :attr:`~studio.planning.problem.StrikeProblem.reduced`). Levenberg-Marquardt on the
   racket errors (regularised towards the unconstrained minimum-jerk s) brings s to the
   target from the seed (``warm_start`` or the minimum-jerk s); a Newton-SQP
   (:mod:`studio.planning.newton_sqp`: exact Lagrangian Hessian of the casadi kinematics,
   one 16-variable DAQP QP per step, each step projected back onto the target by
   Gauss-Newton corrections and accepted when the jerk cost decreases) then minimises
   the jerk with the racket state at the *centre* of the tolerances.
2. If the closed-form jerks break a limit at 1 kHz: the full problem on the 256 jerks,
   by the same Newton-SQP (racket errors linearised at the current s, one dense QP
   per step, DAQP with a diagonal Hessian: the s-block is diagonalised), with the
   limit rows of the samples within 10 % of a limit; rounds add newly violated
   samples (``limit_rounds``). Rows are tightened by 0.1 % of the limit.

The paper's tolerances and slacks are thus handled by aiming at the centre (errors
~1e-6 tolerances) and checking the tolerances a posteriori
(:mod:`studio.planning.check`); the jerk is minimal for that centre, slightly above the
optimum that uses the tolerances. Timings and that gap: ``docs/planner.md#planner-benchmark``.
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np
import numpy.typing as npt

from studio.planning.check import SolveResult, check_jerks, jerk_ok, near_limit_samples
from studio.planning.newton_sqp import NewtonSqp, SqpProblem
from studio.planning.problem import StrikeProblem

FloatArray = npt.NDArray[np.float64]

_LM_STOP: Final[float] = 0.5
"""Levenberg-Marquardt hands over to the Newton-SQP once every racket error is below
this many tolerances."""
_NEAR: Final[float] = 0.1
"""1 kHz samples within this fraction of a limit become QP rows of the full problem."""


def solve_sqp(problem: StrikeProblem, seed: FloatArray | None) -> SolveResult:
    """sqp-daqp: the reduced problem, then (if a limit is broken) the full problem
    with the limit rows of the 1 kHz samples near or beyond a limit (screening),
    adding newly violated samples until none is left (``limit_rounds``). ``seed``: s
    (16,) to start the reduced problem from (default: the minimum-jerk s)."""
    s, qps, _ = solve_reduced(problem, seed)
    z = problem.reduced.z_of_s(s)
    check = check_jerks(problem, z)
    if check.status == "ok" or (check.status == "tolerance" and not check.violations and jerk_ok(z)):
        return SolveResult(check.status, check.reason, z, "sqp-daqp", qps, check.score, check)
    rows: set[tuple[int, int, float]] = set()
    delta = _NEAR
    for _ in range(problem.setup.options.limit_rounds + 1):
        added = set(near_limit_samples(problem, check, delta)) - rows
        if not added and rows and jerk_ok(z) and not check.violations:
            break
        rows |= added
        keys = sorted(rows)
        extra = problem.sample_rows(keys) if keys else None
        zn, k, reason2 = solve_full(problem, problem.s_of_z(z), z, extra)
        qps += k
        if zn is None:
            return SolveResult("infeasible", reason2, z, "sqp-daqp", qps, math.inf, None)
        z = zn
        check = check_jerks(problem, z)
        if not check.violations:
            break
    return SolveResult(check.status, check.reason, z, "sqp-daqp", qps, check.score, check)


def solve_reduced(problem: StrikeProblem, seed: FloatArray | None) -> tuple[FloatArray, int, bool]:
    """The 16-variable problem in s = (q_tau, qd_tau): Levenberg-Marquardt from the
    seed (default: the unconstrained minimum-jerk s_hat) to the target, then
    Newton-SQP polishing. Returns (s, QPs, converged)."""
    red = problem.reduced
    s_lo, s_hi = problem.s_bounds()
    s = np.clip(seed if seed is not None else red.s_hat, s_lo, s_hi)
    s, _ = levenberg_marquardt(problem, s, red.s_hat, red.H, s_lo, s_hi)
    out = NewtonSqp(problem, SqpProblem.reduced(red.H, red.s_hat)).solve(np.zeros(0), s)
    return out.s, out.qps, not out.reason


def solve_full(
    problem: StrikeProblem, s0: FloatArray, z0: FloatArray, extra: tuple[FloatArray, FloatArray, FloatArray] | None
) -> tuple[FloatArray | None, int, str]:
    """The full problem on the jerks (jerk bounds, terminal rest, the limit rows
    ``extra`` = (A (R, 8n), lo, hi) of selected 1 kHz samples) with the Newton-SQP,
    starting from z0 (8, n), s0. Returns (z or None, QPs, reason)."""
    n = problem.n
    nz = 8 * n
    if extra is not None:
        A_lim, lo_lim, hi_lim = extra
    else:
        A_lim, lo_lim, hi_lim = np.zeros((0, nz)), np.zeros(0), np.zeros(0)
    A_eq, b_eq = problem.terminal_rows()
    M, m0 = problem.s_map()
    nl = A_lim.shape[0]
    qp = SqpProblem(
        Q=np.tile(problem.grid.w, 8),
        Hs=np.zeros((16, 16)),
        s_hat=s0,
        wlo=-np.ones(nz),
        whi=np.ones(nz),
        A_w=np.vstack([A_eq, A_lim, M]),
        A_s=np.vstack([np.zeros((24 + nl, 16)), -np.eye(16)]),
        lo=np.concatenate([b_eq, lo_lim, -m0]),
        hi=np.concatenate([b_eq, hi_lim, -m0]),
        eq=np.concatenate([np.ones(24, dtype=bool), np.zeros(nl, dtype=bool), np.ones(16, dtype=bool)]),
    )
    out = NewtonSqp(problem, qp).solve(z0.reshape(-1), s0)
    if out.reason:
        return None, out.qps, out.reason
    return out.w.reshape(8, n), out.qps, ""


def levenberg_marquardt(
    problem: StrikeProblem, s: FloatArray, s_hat: FloatArray, H: FloatArray, s_lo: FloatArray, s_hi: FloatArray
) -> tuple[FloatArray, int]:
    """Reach the target from a far seed: Levenberg-Marquardt on
    1/2 |r(s)|^2 + 1/2 (s - s_hat)^T H (s - s_hat) (errors in tolerances, regularised
    towards the minimum-jerk s_hat, so that it lands near the cheapest solution),
    with s clipped into its limits. Returns (s, iterations)."""
    sig = problem.setup.scaling.sig
    Hy = H * np.outer(sig, sig)

    def F(sv: FloatArray, r: FloatArray) -> float:
        d = sv - s_hat
        return 0.5 * float(r @ r) + 0.5 * float(d @ H @ d)

    r, J = problem.residuals(s, full_normal=True)
    f = F(s, r)
    lam = 1e-3
    it = 0
    for it in range(3 * problem.setup.options.max_iterations):  # noqa: B007  (the count is returned)
        Jy = J * sig[None, :]
        g = Jy.T @ r + sig * (H @ (s - s_hat))
        A = Jy.T @ Jy + Hy
        dscale = np.diag(A).copy() + 1e-12
        improved = False
        for _ in range(12):
            y = np.linalg.solve(A + lam * np.diag(dscale), -g)
            s_new = np.clip(s + sig * y, s_lo, s_hi)
            r_new, J_new = problem.residuals(s_new, full_normal=True)
            f_new = F(s_new, r_new)
            if f_new < f:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        rel = (f - f_new) / max(f, 1e-300)
        s, r, J, f = s_new, r_new, J_new, f_new
        lam = max(lam / 3.0, 1e-9)
        if float(np.max(np.abs(r))) < _LM_STOP or (rel < 1e-12 and float(np.max(np.abs(r))) < 1.0):
            break
    return s, it + 1
