"""The strike planning problem (paper, problem (eq:nlp)): its data, time grid, affine
maps from the scaled jerks to the chain states, racket errors at tau and limit rows.

Problem
=======
Parameters xi_s = (u0, u0', u0'', X0, tau, p_tau, n_tau, v_tau, tau_f, u_tauf). The
decision variables are the piecewise-constant jerks of the 8 joint commands on
``n_l = 32`` segments of [0, tau_f] (a chain of cubics, continuous up to acceleration).

* Time grid. tau is always a segment boundary: ``n1 = clip(round(n_l tau / tau_f), 4,
  n_l - 4)`` segments of length ``h1 = tau / n1`` on [0, tau] and ``n2 = n_l - n1`` of
  length ``h2 = (tau_f - tau) / n2`` on [tau, tau_f].
* Scaling. Jerks are divided by their limits (``z = j / j_max``, ``|z| <= 1``), every
  limit row by its limit, every racket error by its tolerance; the cost is
  ``1/2 sum_k (h_k / tau_f) |z_k|^2`` (time integral of the squared scaled jerk over
  tau_f). The problem's size and structure never change (only the split n1 moves the
  tau rows); tau and tau_f enter the right-hand sides and the values of the exact
  discretization (two closed-form 5x5 transition matrices per joint,
  :func:`studio.planning.chain.chain_transition`).
* Joint dynamics. Per joint the chain Z = [u, u', u'', q, q'] driven by the jerk is
  discretized exactly (robot model q'' = wn^2 (u - q) - 2 zeta wn q'), so every state,
  in particular the *predicted actual* state s = (q_tau, q'_tau), is an affine
  function of the jerks. The racket constraints act on s, not on the commands.
* Constraints. Hard: jerk bounds; sent commands (position, velocity, acceleration) and
  predicted positions/velocities within the limits at every 1 kHz sample (the solver
  adds the rows of the samples near a limit, solves, re-checks all samples and adds
  newly violated ones, see below); the command reaches ``u_tauf`` with zero velocity
  and acceleration at tau_f. Racket at tau (paper's tolerance table):
  ``|p(q_tau) - p_tau| <= dp`` (5 mm), ``angle(n(q_tau), n_tau) <= dphi`` (0.5 deg),
  ``|J_v(q_tau) q'_tau - v_tau| <= max(dv_a, dv_r |v_tau|)`` (0.01 m/s, 1 %).

World frame, SI units; joint order and units of :mod:`studio.robot.model`. Times are
relative to the start of the strike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from studio.planning.chain import (
    FreeResponseTable,
    chain_transition,
    free_response_terms,
    particular_coefficients,
)
from studio.planning.options import PlannerOptions
from studio.planning.racket_terms import RacketTerms
from studio.planning.scaling import LimitScaling
from studio.planning.strike import StrikeStart, StrikeTarget
from studio.robot.model import JointDynamics, JointLimits, Robot

FloatArray = npt.NDArray[np.float64]

ROW_MARGIN: float = 1e-3
"""Limit rows of the QPs are tightened by this fraction of the limit, so that the 1 kHz
samples next to a constrained one stay within the true limit."""


@dataclass(frozen=True, eq=False)
class PlannerSetup:
    """What every strike problem of one planner shares: the robot, its joint model, the
    limits planned with and their scaling, the racket terms and the free-response table
    of the output grid."""

    robot: Robot
    """The robot (forward kinematics of the a-posteriori check, joint names)."""
    dynamics: JointDynamics
    """Joint model of the command/joint chain."""
    limits: JointLimits
    """Joint limits planned with."""
    options: PlannerOptions
    """Planner options."""
    scaling: LimitScaling
    """Scales and bounds of jerks, limit rows and s."""
    terms: RacketTerms
    """Racket p, n, v, Jacobians and Lagrangian Hessian (casadi buffers)."""
    free_table: FreeResponseTable
    """Free response of the joints on the output grid."""

    @property
    def n(self) -> int:
        """Number of constant-jerk segments n_l."""
        return self.options.n_segments


@dataclass(frozen=True, eq=False)
class StrikeGrid:
    """Time grid and affine boundary-state maps of one planning problem."""

    h: FloatArray  # (n,) segment lengths [s]
    tb: FloatArray  # (n+1,) boundaries [s]
    n1: int  # boundary index of tau
    T: FloatArray  # (8, n+1, 5, n+1): Z_k = T[..., 0] + T[..., 1:] @ z (z: scaled jerks of the joint)
    w: FloatArray  # (n,) cost weights h_k / tau_f


def segment_split(n: int, tau: float, tau_f: float) -> int:
    """Segments before tau: ``clip(round(n tau / tau_f), 4, n - 4)``."""
    return int(min(max(round(n * tau / tau_f), 4), n - 4))


def build_grid(
    dyn: JointDynamics, jmax: FloatArray, start: StrikeStart, tau: float, tau_f: float, n: int
) -> StrikeGrid:
    """The grid of ``n`` segments with tau [s] at a boundary, and the affine maps of the
    boundary states from the start state and the jerks scaled by ``jmax`` (8,)."""
    n1 = segment_split(n, tau, tau_f)
    h1, h2 = tau / n1, (tau_f - tau) / (n - n1)
    h = np.concatenate([np.full(n1, h1), np.full(n - n1, h2)])
    tb = np.concatenate([[0.0], np.cumsum(h)])
    tb[n1], tb[n] = tau, tau_f
    A, B = chain_transition(dyn, np.array([h1, h2]))  # (2, 8, 5, 5), (2, 8, 5)
    Bj = B * jmax[None, :, None]
    T = np.zeros((8, n + 1, 5, n + 1))
    T[:, 0, :, 0] = np.stack([start.u, start.ud, start.udd, start.X[:, 0], start.X[:, 1]], axis=1)
    for k in range(n):
        ph = 0 if k < n1 else 1
        T[:, k + 1] = A[ph] @ T[:, k]
        T[:, k + 1, :, 1 + k] += Bj[ph]
    return StrikeGrid(h=h, tb=tb, n1=n1, T=T, w=h / tau_f)


@dataclass(frozen=True, eq=False)
class ReducedProblem:
    """Per-joint minimum-jerk solution as a function of s = (q_tau, qd_tau), without
    active limits: the reduced cost is ``1/2 (s - s_hat)^T H (s - s_hat)``."""

    K: FloatArray
    """(8, 5, 5) inverse Gram matrices of the per-joint end conditions."""
    N: FloatArray
    """(8, n, 5): the scaled jerks of joint i are ``z_i = N_i r_i``."""
    r0: FloatArray
    """(8, 5) constant part of ``r_i = r0_i + [0, 0, 0, q_i, qd_i]``."""
    s_hat: FloatArray
    """(16,) the unconstrained minimiser."""
    H: FloatArray
    """(16, 16) Hessian of the reduced cost (2x2 blocks per joint)."""

    def z_of_s(self, s: FloatArray) -> FloatArray:
        """The minimum-jerk scaled jerks (8, n) through s (16,)."""
        r = self.r0.copy()
        r[:, 3] += s[:8]
        r[:, 4] += s[8:]
        return np.einsum("ink,ik->in", self.N, r)


class StrikeProblem:
    """The data of one strike planning problem: start, target, tolerances, the time grid
    and the maps from the scaled jerks z (8, n) to the chain states (built on first use),
    the racket errors at tau and the limit rows. The solvers (:mod:`studio.planning.sqp`,
    :mod:`studio.planning.ipopt`) and the a-posteriori check (:mod:`studio.planning.check`)
    work on it."""

    def __init__(self, setup: PlannerSetup, start: StrikeStart, target: StrikeTarget, u_rest: FloatArray) -> None:
        self.setup = setup
        self.start = start
        self.target = target
        self.u_rest = u_rest
        """Final command u_tauf (8,)."""
        self.n = setup.n
        o = setup.options
        tol = o.tolerances
        self.tol = np.array([tol.position, tol.angle, tol.velocity(target.velocity)])
        """Position [m], angle [rad] and velocity [m/s] tolerances at tau."""
        self.cost_slack = (
            o.slack_scale
            * np.array([o.slack_weights.position, o.slack_weights.normal, o.slack_weights.velocity])
            * self.tol
        )
        """Cost of one tolerance of slack (3,) (IPOPT formulation)."""
        nt = target.normal
        a = np.array([1.0, 0.0, 0.0]) if abs(nt[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t1 = np.cross(nt, a)
        t1 /= np.linalg.norm(t1)
        self.tangent = np.stack([t1, np.cross(nt, t1)], axis=0)
        """(2, 3) unit vectors orthogonal to the target normal."""
        self._grid: StrikeGrid | None = None
        self._reduced: ReducedProblem | None = None

    def check_inputs(self) -> str:
        """Reason why the problem cannot be posed, or ''."""
        s, L = self.start, self.setup.limits
        names = self.setup.robot.joint_names
        tiny = 1e-9
        if self.target.tau_f - self.target.tau < 4 * 1e-3 or self.target.tau < 4 * 1e-3:
            return "tau and tau_f - tau must be at least 4 ms"
        for arr, lo, hi, what in (
            (s.u, L.lower, L.upper, "initial command"),
            (s.ud, -L.velocity, L.velocity, "initial command velocity"),
            (s.udd, -L.acceleration, L.acceleration, "initial command acceleration"),
            (self.u_rest, L.lower, L.upper, "final command u_tauf"),
        ):
            bad = np.flatnonzero((arr < lo - tiny * (1 + np.abs(lo))) | (arr > hi + tiny * (1 + np.abs(hi))))
            if bad.size:
                k = int(bad[0])
                return f"{what} of joint {names[k]!r} = {arr[k]:.6g} outside [{lo[k]:.6g}, {hi[k]:.6g}]"
        return ""

    # ------------------------------------------------------------------ grid and maps
    @property
    def grid(self) -> StrikeGrid:
        """The time grid and boundary-state maps (built on first use)."""
        if self._grid is None:
            sp = self.setup
            self._grid = build_grid(
                sp.dynamics, sp.scaling.jmax, self.start, self.target.tau, self.target.tau_f, self.n
            )
        return self._grid

    def s_of_z(self, z: FloatArray) -> FloatArray:
        """(q_tau, qd_tau) (16,) for scaled jerks z (8, n)."""
        g = self.grid
        Tn = g.T[:, g.n1, 3:5]  # (8, 2, n+1)
        val = Tn[:, :, 0] + np.einsum("ick,ik->ic", Tn[:, :, 1:], z)
        return np.concatenate([val[:, 0], val[:, 1]])

    @property
    def reduced(self) -> ReducedProblem:
        """Per-joint min-jerk solution as a function of s (built on first use)."""
        if self._reduced is None:
            g = self.grid
            n = self.n
            C = np.concatenate([g.T[:, n, 0:3, 1:], g.T[:, g.n1, 3:5, 1:]], axis=1)  # (8, 5, n)
            Winv = 1.0 / g.w
            CW = C * Winv[None, None, :]
            Gm = CW @ np.transpose(C, (0, 2, 1))  # (8, 5, 5)
            K = np.linalg.inv(Gm)
            N = np.transpose(CW, (0, 2, 1)) @ K  # (8, n, 5)
            r0 = np.empty((8, 5))
            r0[:, 0] = self.u_rest - g.T[:, n, 0, 0]
            r0[:, 1] = -g.T[:, n, 1, 0]
            r0[:, 2] = -g.T[:, n, 2, 0]
            r0[:, 3] = -g.T[:, g.n1, 3, 0]
            r0[:, 4] = -g.T[:, g.n1, 4, 0]
            Kss = K[:, 3:5, 3:5]
            Kse = K[:, 3:5, 0:3]
            x = -np.linalg.solve(Kss, np.einsum("nij,nj->ni", Kse, r0[:, 0:3])[..., None])[..., 0]
            qs = x - r0[:, 3:5]
            s_hat = np.concatenate([qs[:, 0], qs[:, 1]])
            self._reduced = ReducedProblem(K=K, N=N, r0=r0, s_hat=s_hat, H=_reduced_hessian(K))
        return self._reduced

    def s_bounds(self) -> tuple[FloatArray, FloatArray]:
        """Lower and upper bounds (16,) of s: position and velocity limits."""
        L = self.setup.limits
        return np.concatenate([L.lower, -L.velocity]), np.concatenate([L.upper, L.velocity])

    # ------------------------------------------------------------------ racket errors at tau
    def residuals(self, s: FloatArray, *, full_normal: bool = False) -> tuple[FloatArray, FloatArray]:
        """Racket errors at tau in units of their tolerances, r (8,) =
        [(p - p_tau)/dp (3), T (n - n_tau)/dphi (2), (v - v_tau)/dv (3)] (T: two unit
        vectors orthogonal to n_tau), and their Jacobian (8, 16) in s = (q_tau, qd_tau).
        With ``full_normal`` the normal part is the 3-vector (n - n_tau)/dphi (r (9,)),
        whose only zero is n = +n_tau (used far from the target; the tangential form
        also vanishes at the antipode)."""
        tg = self.target
        o = self.setup.terms.flat(s)  # the casadi buffer: read in place (the outputs below are new arrays)
        jac = o[9:105].reshape(4, 8, 3)  # column-major (3, 8) blocks: jp, jn, jvq, jvqd, transposed
        tp, tn, tv = self.tol
        k = 3 if full_normal else 2
        r = np.empty(6 + k)
        J = np.zeros((6 + k, 16))
        r[0:3] = (o[0:3] - tg.position) / tp
        J[0:3, :8] = jac[0].T / tp
        if full_normal:
            r[3:6] = (o[3:6] - tg.normal) / tn
            J[3:6, :8] = jac[1].T / tn
        else:
            r[3:5] = self.tangent @ o[3:6] / tn
            J[3:5, :8] = (self.tangent / tn) @ jac[1].T
        r[3 + k :] = (o[6:9] - tg.velocity) / tv
        J[3 + k :, :8] = jac[2].T / tv
        J[3 + k :, 8:] = jac[3].T / tv
        return r, J

    def residual_hessian(self, s: FloatArray, lam: FloatArray) -> FloatArray:
        """sum_i lam_i Hessian(r_i) (16, 16) in s, for weights lam (8,)."""
        w = np.concatenate([lam[0:3] / self.tol[0], self.tangent.T @ lam[3:5] / self.tol[1], lam[5:8] / self.tol[2]])
        H = self.setup.terms.lag_hessian(s, w)
        return 0.5 * (H + H.T)

    # ------------------------------------------------------------------ linear rows of the full problem
    def terminal_rows(self) -> tuple[FloatArray, FloatArray]:
        """Rows (24, 8n) and right-hand side (24,) of the rest at tau_f: u = u_tauf,
        u' = u'' = 0 (scaled by the limits)."""
        g, n, row_scale = self.grid, self.n, self.setup.scaling.row_scale
        coef = g.T[:, n, 0:3, 1:] / row_scale[:, 0:3, None]  # (8, 3, n)
        target = np.stack([self.u_rest, np.zeros(8), np.zeros(8)], axis=1)
        rhs = (target - g.T[:, n, 0:3, 0]) / row_scale[:, 0:3]
        A = np.zeros((8, 3, 8, n))
        A[np.arange(8), :, np.arange(8), :] = coef
        return A.reshape(24, 8 * n), rhs.reshape(-1)

    def s_map(self) -> tuple[FloatArray, FloatArray]:
        """s = M z_flat + m0."""
        g, n = self.grid, self.n
        M = np.zeros((16, 8 * n))
        for i in range(8):
            M[i, i * n : (i + 1) * n] = g.T[i, g.n1, 3, 1:]
            M[8 + i, i * n : (i + 1) * n] = g.T[i, g.n1, 4, 1:]
        m0 = np.concatenate([g.T[:, g.n1, 3, 0], g.T[:, g.n1, 4, 0]])
        return M, m0

    def sample_rows(self, pts: list[tuple[int, int, float]]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Limit rows (scaled by the limit) of component c of joint i at time t, for
        pts = [(i, c, t)]: (A (m, 8n), lo (m,), hi (m,)). Rows without any dependence
        on the jerks (after tau_f for the commands) are dropped."""
        g, sc_, n = self.grid, self.setup.scaling, self.n
        tt = np.array([t for _, _, t in pts])
        ks = np.clip(np.searchsorted(g.tb, tt, side="right") - 1, 0, n)
        A_d, B_d = chain_transition(self.setup.dynamics, tt - g.tb[ks])  # (m, 8, 5, 5), (m, 8, 5)
        rows = np.zeros((len(pts), 8 * n))
        lo = np.zeros(len(pts))
        hi = np.zeros(len(pts))
        keep = np.zeros(len(pts), dtype=bool)
        for r, ((i, c, _), k) in enumerate(zip(pts, ks, strict=True)):
            coef = A_d[r, i, c] @ g.T[i, k]  # (n+1,)
            if k < n:
                coef[1 + k] += B_d[r, i, c] * sc_.jmax[i]
            sc = sc_.row_scale[i, c]
            rows[r, i * n : (i + 1) * n] = coef[1:] / sc
            lo[r] = (sc_.row_lo[i, c] - coef[0]) / sc + ROW_MARGIN
            hi[r] = (sc_.row_hi[i, c] - coef[0]) / sc - ROW_MARGIN
            keep[r] = bool(np.any(np.abs(coef[1:]) > 1e-14))
        return rows[keep], lo[keep], hi[keep]

    # ------------------------------------------------------------------ trajectory of the jerks
    def boundary_states(self, z: FloatArray) -> FloatArray:
        """Z at the boundaries (n+1, 8, 5) in physical units."""
        g = self.grid
        Z = g.T[..., 0] + np.einsum("ikcj,ij->ikc", g.T[..., 1:], z)  # (8, n+1, 5)
        return np.transpose(Z, (1, 0, 2))

    def chain_at(
        self, z: FloatArray, times: FloatArray, *, commands_only: bool = False, on_grid: bool = False
    ) -> FloatArray:
        """Exact chain state Z = [u, u', u'', q, q'] (N, 8, 5) at times (N,) [s] for the
        scaled jerks z (8, n); after tau_f the command rests at u_tauf (zero jerk).
        ``on_grid``: times are k dt, k = 0..N-1 (the 1 kHz output), which lets the free
        response come from a cached table (exp(lam d) = exp(lam j dt) exp(lam phi_k) with
        d = j dt + phi_k, phi_k the offset of segment k's first sample)."""
        g, n = self.grid, self.n
        Zb = self.boundary_states(z)  # (n+1, 8, 5)
        jerk = np.vstack([(z * self.setup.scaling.jmax[:, None]).T, np.zeros((1, 8))])  # (n+1, 8)
        k = np.clip(np.searchsorted(g.tb, times, side="right") - 1, 0, n)
        d = (times - g.tb[k])[:, None]  # (N, 1)
        Z0, Z1, Z2, Z3, Z4 = np.transpose(Zb, (2, 0, 1))  # per segment start (n+1, 8) each
        z0, z1, z2, jk = Z0.take(k, axis=0), Z1.take(k, axis=0), Z2.take(k, axis=0), jerk.take(k, axis=0)
        jd = jk * d
        udd = z2 + jd
        ud = z1 + d * (z2 + 0.5 * jd)
        u = z0 + d * (z1 + d * (0.5 * z2 + jd / 6.0))
        if commands_only:
            return np.stack([u, ud, udd], axis=-1)
        wn, zeta = self.setup.dynamics.wn, self.setup.dynamics.zeta
        c1, c3, c4 = particular_coefficients(wn, zeta)
        # tracking error e = q - q_particular and its rate at each segment start, gathered
        e0 = (Z3 - (Z0 - c1 * Z1 + c3 * Z2 + c4 * jerk)).take(k, axis=0)
        e0d = (Z4 - (Z1 - c1 * Z2 + c3 * jerk)).take(k, axis=0)
        table = self.setup.free_table
        if on_grid and table.under and len(times):
            es, ec = _free_response_on_grid(table, times, g.tb, k, n, wn, zeta)
        else:
            es, ec = free_response_terms(wn, zeta, d)  # e^{-a d} s(d), e^{-a d} c(d): (N, 8)
        a = zeta * wn
        out = np.empty(u.shape + (5,))
        out[..., 0] = u
        out[..., 1] = ud
        out[..., 2] = udd
        out[..., 3] = u - c1 * ud + c3 * udd + c4 * jk + (ec + a * es) * e0 + es * e0d
        out[..., 4] = ud - c1 * udd + c3 * jk - (wn**2) * es * e0 + (ec - a * es) * e0d
        return out

    def state_at(self, z: FloatArray, t: float) -> FloatArray:
        """Chain state (8, 5) at time t, propagated exactly with :func:`~studio.planning.chain.chain_transition`
        from the last 1 kHz sample at or before t (an independent path from the
        boundary-state maps used by the solver)."""
        g, n = self.grid, self.n
        dt = self.setup.options.dt
        t0 = math.floor(t / dt + 1e-9) * dt
        Z = self.chain_at(z, np.array([t0]))[0]
        cur_t = t0
        jerk = z * self.setup.scaling.jmax[:, None]
        while t - cur_t > 1e-15:
            k = min(max(int(np.searchsorted(g.tb, cur_t + 1e-12, side="right")) - 1, 0), n - 1)
            t_end = min(t, float(g.tb[k + 1]))
            A, B = chain_transition(self.setup.dynamics, t_end - cur_t)
            Z = np.einsum("nij,nj->ni", A, Z) + B * jerk[:, k][:, None]
            cur_t = t_end
        return Z


def _reduced_hessian(K: FloatArray) -> FloatArray:
    """H (16, 16) of the reduced cost 1/2 (s - s_hat)^T H (s - s_hat) (2x2 blocks)."""
    H = np.zeros((16, 16))
    idx = np.arange(8)
    H[idx, idx] = K[:, 3, 3]
    H[idx, idx + 8] = K[:, 3, 4]
    H[idx + 8, idx] = K[:, 4, 3]
    H[idx + 8, idx + 8] = K[:, 4, 4]
    return H


def _free_response_on_grid(
    table: FreeResponseTable,
    times: FloatArray,
    tb: FloatArray,
    k: npt.NDArray[np.intp],
    n: int,
    wn: FloatArray,
    zeta: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """(e^{-a d} s(d), e^{-a d} c(d)) (N, 8) at the 1 kHz ``times`` (N,) from the table:
    exp(lam d) = exp(lam j dt) exp(lam phi_k), d = j dt + phi_k, phi_k the offset of the
    first sample of segment ``k`` (N,) from its start ``tb[k]``."""
    first = np.searchsorted(k, np.arange(n + 1))  # index of each segment's first sample
    first_of = first[k]
    j = np.arange(len(times)) - first_of
    phi = times[np.minimum(first, len(times) - 1)] - tb  # (n+1,) offset of that sample
    er, ei = table.steps(int(j.max()) + 1)
    er, ei = er.take(j, axis=0), ei.take(j, axis=0)
    p = np.exp(table.lam[None, :] * phi[:, None])  # (n+1, 8)
    pr, pi = p.real.take(k, axis=0), p.imag.take(k, axis=0)
    return (er * pi + ei * pr) / (wn * np.sqrt(1.0 - zeta**2)), er * pr - ei * pi
