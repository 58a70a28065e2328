"""Local Newton-SQP (Newton-KKT) of the strike planner: the jerk cost minimised with the
racket state at tau at the *centre* of the tolerances (racket errors r(s) = 0), one DAQP
QP per step (:class:`NewtonSqp`, on the data of a :class:`SqpProblem`).

Each iteration linearises r at s and solves one convex QP with DAQP; the s-block of its
Hessian is Hs + sum_i lam_i Hess(r_i) (the Lagrangian Hessian, multipliers of the
previous QP) plus rho J^T J, which leaves the solution of the equality-constrained QP
unchanged and makes it positive definite; it is diagonalised (y = V t) so DAQP sees a
diagonal Hessian. The start must be near the solution (the reduced problem's
Levenberg-Marquardt point): there is no globalisation beyond keeping the best iterate by
(max error, cost). Variables are scaled (:class:`~studio.planning.scaling.LimitScaling`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import daqp
import numpy as np
import numpy.typing as npt

from studio.planning.problem import StrikeProblem

FloatArray = npt.NDArray[np.float64]

_INF: Final[float] = 1e30
_EQ: Final[int] = 5  # DAQP sense flag of an equality row
_FUNNEL: Final[float] = 0.5
"""Full problem: a step may raise the largest racket error (in tolerances) up to
max(_FUNNEL, 2 x current); longer steps are halved."""
REDUCED_STEP_STOP: Final[float] = 5e-2
"""Reduced problem: the Newton-SQP stops after a full step smaller than this (scaled
variables, max norm) once the racket errors are below 1 % of their tolerances. On the
targets of ``benchmarks/planner.py`` it saves a good share of the QPs at a negligible
change of the plan costs, errors at tau unchanged (figures:
``docs/planner.md#planner-benchmark``)."""


@dataclass(frozen=True, eq=False)
class SqpProblem:
    """The problem the Newton-SQP solves, in extra variables w (nw,) and s (16,)::

        min 1/2 w^T diag(Q) w + 1/2 (s - s_hat)^T Hs (s - s_hat)
        s.t. r(s) = 0 (racket errors at tau, the centre of the tolerances),
             lo <= A_w w + A_s s <= hi (rows with eq: equalities), wlo <= w <= whi,
             s within the position/velocity limits.

    The reduced problem has no w and no rows (:meth:`reduced`); the full problem's w
    are the scaled jerks (8n,)."""

    Q: FloatArray
    """Diagonal cost weights of w (nw,)."""
    Hs: FloatArray
    """Cost Hessian of s (16, 16)."""
    s_hat: FloatArray
    """Cost centre of s (16,)."""
    wlo: FloatArray
    """Lower bounds of w (nw,)."""
    whi: FloatArray
    """Upper bounds of w (nw,)."""
    A_w: FloatArray
    """Linear rows, w part (R, nw)."""
    A_s: FloatArray
    """Linear rows, s part (R, 16)."""
    lo: FloatArray
    """Lower bounds of the rows (R,)."""
    hi: FloatArray
    """Upper bounds of the rows (R,)."""
    eq: npt.NDArray[np.bool_]
    """Rows that are equalities (R,)."""

    @classmethod
    def reduced(cls, Hs: FloatArray, s_hat: FloatArray) -> SqpProblem:
        """The reduced problem: s only, cost ``1/2 (s - s_hat)^T Hs (s - s_hat)``."""
        e = np.zeros(0)
        return cls(
            Q=e,
            Hs=Hs,
            s_hat=s_hat,
            wlo=e,
            whi=e,
            A_w=np.zeros((0, 0)),
            A_s=np.zeros((0, 16)),
            lo=e,
            hi=e,
            eq=np.zeros(0, dtype=bool),
        )

    @property
    def nw(self) -> int:
        """Number of extra variables w."""
        return int(self.Q.size)

    def cost(self, w: FloatArray, s: FloatArray) -> float:
        """The objective at (w, s)."""
        d = s - self.s_hat
        return 0.5 * float(w @ (self.Q * w)) + 0.5 * float(d @ self.Hs @ d)


@dataclass(frozen=True, eq=False)
class SqpOutcome:
    """Result of :meth:`NewtonSqp.solve`."""

    w: FloatArray
    """Extra variables (nw,) of the best iterate."""
    s: FloatArray
    """s = (q_tau, qd_tau) (16,) of the best iterate."""
    qps: int
    """QPs solved."""
    reason: str
    """Why it failed ("" when it produced an iterate)."""


def project(
    problem: StrikeProblem, s: FloatArray, s_lo: FloatArray, s_hi: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Pull s back onto r(s) = 0 with up to 4 minimum-norm Gauss-Newton corrections
    (scaled variables, clipped to the limits ``s_lo``, ``s_hi``). Returns (s, r, J)."""
    sig = problem.setup.scaling.sig
    r, J = problem.residuals(s)
    for _ in range(4):
        if float(np.max(np.abs(r))) < 1e-3:
            break
        Jy = J * sig[None, :]
        d = Jy.T @ np.linalg.solve(Jy @ Jy.T + 1e-12 * np.eye(Jy.shape[0]), r)
        s = np.clip(s - sig * d, s_lo, s_hi)
        r, J = problem.residuals(s)
    return s, r, J


class NewtonSqp:
    """The Newton-SQP iteration on ``qp`` for the racket errors of ``problem``."""

    def __init__(self, problem: StrikeProblem, qp: SqpProblem) -> None:
        self.problem = problem
        self.qp = qp
        sig = problem.setup.scaling.sig
        self.sig = sig
        self.s_lo, self.s_hi = problem.s_bounds()
        nw = qp.nw
        self.nw = nw
        self.nr = qp.A_w.shape[0]
        self.Hs_y = qp.Hs * np.outer(sig, sig)
        self.A_ws = qp.A_s * sig[None, :] if self.nr else np.zeros((0, 16))
        self.sense = np.concatenate([np.zeros(nw + 16), np.where(qp.eq, _EQ, 0), np.zeros(16), np.full(8, _EQ)]).astype(
            np.int32
        )

    def solve(self, w0: FloatArray, s0: FloatArray) -> SqpOutcome:
        """Iterate from (w0, s0); keep the best iterate by (max error, cost)."""
        problem, qp, nw = self.problem, self.qp, self.nw
        w, s = w0.copy(), s0.copy()
        r, J = problem.residuals(s)
        lam_r = np.zeros(8)
        qps = 0
        best: tuple[float, float, FloatArray, FloatArray] | None = None
        prev_cost: float | None = None
        for _ in range(problem.setup.options.max_iterations):
            Jy = J * self.sig[None, :]
            lam_h, V = self._hessian(s, lam_r, Jy)
            x, flag, info = self._qp(w, s, r, Jy, lam_h, V)
            qps += 1
            if flag < 1:
                if best is None and self.nr:
                    return SqpOutcome(w, s, qps, f"QP infeasible (DAQP exit flag {flag}): the limits cannot be met")
                break
            lam_r = np.asarray(info["lam"])[-8:]
            y_full = V @ x[nw : nw + 16]
            dw = x[:nw] - w
            r_max = float(np.max(np.abs(r)))
            trial = self._reduced_step(w, s, y_full, r_max) if nw == 0 else self._funnel_step(s, y_full, r_max)
            if trial is None:
                break
            alpha, s_new, r_new, J_new = trial
            step = float(np.max(np.abs(alpha * y_full)))
            w, s, r, J = w + alpha * dw, s_new, r_new, J_new
            key = (float(np.max(np.abs(r))), qp.cost(w, s))
            # a full step, errors within 1 % of their tolerances and a cost change below 1e-4
            # of it: what is left is a Newton polish of no value (the linear rows hold at
            # every iterate; the a-posteriori check verifies the result anyway)
            stalled = (
                alpha == 1.0
                and prev_cost is not None
                and key[0] < 1e-2
                and abs(prev_cost - key[1]) <= 1e-4 * abs(prev_cost)
            )
            # Reduced problem: the full Newton steps converge quadratically (0.4, 0.15,
            # 0.01, 2e-5 typically), so after a full step below REDUCED_STEP_STOP what is
            # left changes the cost by ~1e-5 of it (measured on the benchmark's targets).
            small = REDUCED_STEP_STOP if nw == 0 and alpha == 1.0 else 1e-3
            prev_cost = key[1]
            if best is None or (max(key[0], 0.05), key[1]) < (max(best[0], 0.05), best[1]):
                best = (key[0], key[1], w.copy(), s.copy())
            if step < 1e-7 or (step < small and key[0] < 1e-2) or stalled:
                break
        if best is None:
            return SqpOutcome(w, s, qps, "no QP solved")
        return SqpOutcome(best[2], best[3], qps, "")

    def _hessian(self, s: FloatArray, lam_r: FloatArray, Jy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Eigenvalues (floored) and eigenvectors of the QP's s-block Hessian (scaled):
        the Lagrangian Hessian with negative curvature lifted along the constraint normals."""
        sig = self.sig
        B = self.Hs_y + self.problem.residual_hessian(s, lam_r) * np.outer(sig, sig)
        ev = np.linalg.eigvalsh(B)
        if ev[0] < 1e-9 * max(abs(float(ev[-1])), 1e-9):
            # Lift negative curvature along the constraint normals (this leaves the
            # solution of the equality-constrained QP unchanged); floor the rest.
            JtJ = Jy.T @ Jy
            ej = np.linalg.eigvalsh(JtJ)[-8]  # smallest of the (generically 8) non-zero ones
            B = B + (10.0 * abs(float(ev[0])) / max(float(ej), 1e-12)) * JtJ
        lam_h, V = np.linalg.eigh(B)
        floor = 1e-8 * max(float(lam_h[-1]), 1e-8)
        return np.maximum(lam_h, floor), V

    def _qp(
        self, w: FloatArray, s: FloatArray, r: FloatArray, Jy: FloatArray, lam_h: FloatArray, V: FloatArray
    ) -> tuple[FloatArray, int, dict[str, object]]:
        """One DAQP QP at (w, s) in (w, t) with y = V t: the rows, the s limits and the
        linearised racket errors ``r + Jy y = 0``. Returns (x, exit flag, info)."""
        qp, sig, nw = self.qp, self.sig, self.nw
        g = sig * (qp.Hs @ (s - qp.s_hat))
        base = qp.A_s @ s if self.nr else np.zeros(0)
        A = np.vstack(
            [
                np.hstack([qp.A_w, self.A_ws @ V]) if self.nr else np.zeros((0, nw + 16)),
                np.hstack([np.zeros((24, nw)), np.vstack([V, Jy @ V])]),
            ]
        )
        bu = np.concatenate([qp.whi, np.full(16, _INF), qp.hi - base, (self.s_hi - s) / sig, -r])
        bl = np.concatenate([qp.wlo, np.full(16, -_INF), qp.lo - base, (self.s_lo - s) / sig, -r])
        f = np.concatenate([np.zeros(nw), V.T @ g])
        x, _, flag, info = daqp.solve(np.diag(np.concatenate([qp.Q, lam_h])), f, A, bu, bl, self.sense)
        return x, flag, info

    def _reduced_step(
        self, w: FloatArray, s: FloatArray, y_full: FloatArray, r_max: float
    ) -> tuple[float, FloatArray, FloatArray, FloatArray] | None:
        """Reduced problem: feasible steps. Project each trial point back onto r(s) = 0
        (minimum-norm Gauss-Newton corrections) and accept it if the cost does not
        increase; else halve the step. (alpha, s, r, J) or None if no step is accepted."""
        c_old = self.qp.cost(w, s)
        alpha = 1.0
        for _ in range(8):
            s_new, r_new, J_new = project(self.problem, s + alpha * self.sig * y_full, self.s_lo, self.s_hi)
            if float(np.max(np.abs(r_new))) <= max(0.05, r_max) and self.qp.cost(w, s_new) <= c_old + 1e-12 * abs(
                c_old
            ):
                return alpha, s_new, r_new, J_new
            alpha *= 0.5
        return None

    def _funnel_step(
        self, s: FloatArray, y_full: FloatArray, r_max: float
    ) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        """Full problem: the largest of 1, 1/2, 1/4, ... of the step that keeps the errors
        below max(_FUNNEL, 2 x current) (convex combinations keep the linear rows); the
        last trial is taken as is (w and s move by the same alpha)."""
        alpha = 1.0
        for trial in range(6):
            s_new = s + alpha * self.sig * y_full
            r_new, J_new = self.problem.residuals(s_new)
            if float(np.max(np.abs(r_new))) <= max(_FUNNEL, 2.0 * r_max) or trial == 5:
                break
            alpha *= 0.5
        return alpha, s_new, r_new, J_new
