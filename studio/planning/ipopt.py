"""The ``"ipopt"`` solver of the strike planner: the paper's formulation itself
(tolerance constraints in smooth squared form with slacks weighted as the paper's table,
radius ``margin * tolerance``), in a sparse states-as-variables form, solved with IPOPT
through casadi (one NLP per split n1, built once and reused with parameters); the
reference for tests and the fallback (``options.fallback``) when the fast solver ends
outside the tolerances.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import numpy.typing as npt

from studio.planning.chain import chain_transition
from studio.planning.check import SolveResult, check_jerks
from studio.planning.kinematics_casadi import CasadiKinematics
from studio.planning.options import PlannerOptions
from studio.planning.problem import StrikeProblem

FloatArray = npt.NDArray[np.float64]


class IpoptSolver:
    """The IPOPT NLPs of one planner (one per tau split n1, built on first use and
    cached) and their solution for a strike problem. Not thread-safe (casadi)."""

    def __init__(self, kin: CasadiKinematics, options: PlannerOptions) -> None:
        self.kin = kin
        """Casadi kinematics of the racket frame."""
        self.options = options
        self._cache: dict[int, tuple[ca.Function, dict[str, FloatArray]]] = {}

    def nlp(self, n1: int) -> tuple[ca.Function, dict[str, FloatArray]]:
        """The IPOPT NLP for tau at boundary n1 (built once, cached; all numbers that
        depend on tau, tau_f, the start and the target are parameters or bounds).

        Variables x = [Zs (8, n, 5) scaled chain states at boundaries 1..n, z (8, n)
        scaled jerks, eps (3) normalised slacks]; constraints: exact discrete dynamics
        (equalities) and the three end-effector constraints of the paper in smooth form
        (squared norms, normalised by the squared tolerances).
        """
        if n1 in self._cache:
            return self._cache[n1]
        n = self.options.n_segments
        nZ, nz = 8 * n * 5, 8 * n
        x = ca.SX.sym("x", nZ + nz + 3)
        p = ca.SX.sym("p", 400 + 80 + 40 + 40 + 9 + 4 + 2 + 3)
        o = 0

        def take(k: int) -> ca.SX:
            nonlocal o
            v = p[o : o + k]
            o += k
            return v

        As, Bs, Z0s, S = take(400), take(80), take(40), take(40)
        p_tau, n_tau, v_tau, tol4, w, cs = take(3), take(3), take(3), take(4), take(2), take(3)
        Zs = x[:nZ]
        z = x[nZ : nZ + nz]
        eps = x[nZ + nz :]

        def Z_of(i: int, k: int) -> ca.SX:  # state of joint i at boundary k (1..n)
            if k == 0:
                return Z0s[i * 5 : (i + 1) * 5]
            b = (i * n + (k - 1)) * 5
            return Zs[b : b + 5]

        g: list[ca.SX] = []
        for i in range(8):
            for k in range(n):
                ph = 0 if k < n1 else 1
                A = ca.reshape(As[(ph * 8 + i) * 25 : (ph * 8 + i + 1) * 25], 5, 5).T  # row-major input
                Bv = Bs[(ph * 8 + i) * 5 : (ph * 8 + i + 1) * 5]
                g.append(Z_of(i, k + 1) - (A @ Z_of(i, k) + Bv * z[i * n + k]))
        q = ca.vertcat(*[S[i * 5 + 3] * Z_of(i, n1)[3] for i in range(8)])
        qd = ca.vertcat(*[S[i * 5 + 4] * Z_of(i, n1)[4] for i in range(8)])
        pos, rot = self.kin.pose(q)
        nrm = rot[:, 2]
        vel = self.kin.velocity(q, qd)
        g_p = ca.sumsqr(pos - p_tau) / tol4[0] ** 2 - (1 + eps[0]) ** 2
        g_n = (2 - 2 * ca.dot(nrm, n_tau)) / (2 * tol4[2]) - (1 + eps[1]) ** 2
        g_v = ca.sumsqr(vel - v_tau) / tol4[3] ** 2 - (1 + eps[2]) ** 2
        zz = ca.reshape(z, n, 8)  # column i = joint i
        cost = 0.5 * (w[0] * ca.sumsqr(zz[:n1, :]) + w[1] * ca.sumsqr(zz[n1:, :])) + ca.dot(cs, eps)
        gg = ca.vertcat(*g, g_p, g_n, g_v)
        ndyn = 8 * n * 5
        solver = ca.nlpsol(
            f"strike_ipopt_{n1}",
            "ipopt",
            {"x": x, "p": p, "f": cost, "g": gg},
            {
                "ipopt.print_level": 0,
                "print_time": False,
                "ipopt.sb": "yes",
                "ipopt.max_iter": self.options.ipopt_max_iter,
                "ipopt.tol": 1e-8,
                "error_on_fail": False,
            },
        )
        bounds = {
            "lbg": np.concatenate([np.zeros(ndyn), np.full(3, -np.inf)]),
            "ubg": np.zeros(ndyn + 3),
        }
        self._cache[n1] = (solver, bounds)
        return solver, bounds

    def solve(self, problem: StrikeProblem, seed_z: FloatArray | None, seed_s: FloatArray | None) -> SolveResult:
        """Solve ``problem`` from the scaled jerks ``seed_z`` (8, n) (default: the
        minimum-jerk jerks through ``seed_s`` (16,), else the unconstrained ones, clipped
        to the jerk bounds). A failed evaluation gives status "failed" without jerks."""
        n = problem.n
        g = problem.grid
        solver, sl = self.nlp(g.n1)
        S = problem.setup.scaling.row_scale  # (8, 5)
        lbx, ubx = _bounds(problem)
        if seed_z is None:
            red = problem.reduced
            seed_z = np.clip(red.z_of_s(seed_s if seed_s is not None else red.s_hat), -1.0, 1.0)
        Zb = problem.boundary_states(seed_z)[1:]  # (n, 8, 5)
        x0 = np.concatenate(
            [(np.transpose(Zb, (1, 0, 2)) / S[:, None, :]).reshape(-1), seed_z.reshape(-1), np.zeros(3)]
        )
        x0 = np.clip(x0, lbx, ubx)
        try:
            sol = solver(x0=x0, p=_parameters(problem), lbx=lbx, ubx=ubx, lbg=sl["lbg"], ubg=sl["ubg"])
        except RuntimeError as exc:  # casadi raises on evaluation errors
            return SolveResult("failed", f"IPOPT failed: {exc}", None, "", 0, math.inf)
        stats = solver.stats()
        iters = int(stats.get("iter_count", 0))
        x = np.asarray(sol["x"]).reshape(-1)
        z = x[8 * n * 5 : 8 * n * 5 + 8 * n].reshape(8, n)
        rs = stats.get("return_status", "")
        if not stats.get("success", False) and rs not in ("Solved_To_Acceptable_Level",):
            if rs in ("Infeasible_Problem_Detected", "Restoration_Failed"):
                return SolveResult("infeasible", f"IPOPT: {rs}: the limits cannot be met", z, "ipopt", iters, math.inf)
            check = check_jerks(problem, z)
            status, reason = check.status, check.reason
            if status == "ok":
                status, reason = "failed", f"IPOPT did not converge ({rs})"
            return SolveResult(status, reason, z, "ipopt", iters, check.score + 1.0, check)
        check = check_jerks(problem, z)
        return SolveResult(check.status, check.reason, z, "ipopt", iters, check.score, check)


def _parameters(problem: StrikeProblem) -> FloatArray:
    """The NLP's parameters: scaled discrete matrices (Zs = S^-1 Z, j = jmax z) of both
    segment lengths, the scaled start state, the scales, the target, the constraint radii
    (``margin`` x tolerances), the cost weights and the slack costs."""
    g, sp, tol = problem.grid, problem.setup, problem.tol
    S = sp.scaling.row_scale  # (8, 5)
    h1, h2 = g.h[0], g.h[-1]
    A, B = chain_transition(sp.dynamics, np.array([h1, h2]))
    As = A * (S[None, :, None, :] / S[None, :, :, None])  # S^-1 A S
    Bs = B * (sp.scaling.jmax[None, :, None] / S[None])
    Z0s = g.T[:, 0, :, 0] / S
    tg = problem.target
    m = sp.options.margin
    return np.concatenate(
        [
            As.reshape(-1),
            Bs.reshape(-1),
            Z0s.reshape(-1),
            S.reshape(-1),
            tg.position,
            tg.normal,
            tg.velocity,
            [m * tol[0], math.cos(m * tol[1]), 1.0 - math.cos(m * tol[1]), m * tol[2]],
            [g.w[0], g.w[-1]],
            problem.cost_slack,
        ]
    )


def _bounds(problem: StrikeProblem) -> tuple[FloatArray, FloatArray]:
    """Bounds of x = [Zs (8, n, 5), z (8, n), eps (3)]: the limits (scaled), the rest at
    u_tauf at the last boundary, the jerk bounds, non-negative slacks."""
    n, sc = problem.n, problem.setup.scaling
    S = sc.row_scale
    lbZ = np.broadcast_to((sc.row_lo / S)[:, None, :], (8, n, 5)).copy()
    ubZ = np.broadcast_to((sc.row_hi / S)[:, None, :], (8, n, 5)).copy()
    lbZ[:, n - 1, 0] = ubZ[:, n - 1, 0] = problem.u_rest / S[:, 0]
    lbZ[:, n - 1, 1:3] = ubZ[:, n - 1, 1:3] = 0.0
    lbx = np.concatenate([lbZ.reshape(-1), -np.ones(8 * n), np.zeros(3)])
    ubx = np.concatenate([ubZ.reshape(-1), np.ones(8 * n), np.full(3, np.inf)])
    return lbx, ubx
