"""The a-posteriori check of a strike plan, and the solvers' common result.

The commands are sampled at 1 kHz (``u[k]`` is held over [t_k, t_k + dt): it is the cubic
at the interval midpoint, so the zero-order-hold response equals the planned one to
O(dt^2), ~1e-6 rad), the predicted joint state is propagated exactly to tau from the last
1 kHz sample, the racket errors are re-evaluated with pinocchio and every limit is checked
at every sample (:func:`check_jerks`); failures give an invalid plan with a reason, never
an exception. World frame, SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from studio.planning.problem import StrikeProblem
from studio.planning.strike import PlanStatus

FloatArray = npt.NDArray[np.float64]

Violation = tuple[int, int, float, float]
"""A limit violation: (joint, chain component 0..4 of [u, u', u'', q, q'], time of the
value [s], excess / limit)."""


@dataclass(frozen=True, eq=False)
class PlanCheck:
    """The a-posteriori check of scaled jerks z: verdict, the 1 kHz samples and the racket
    errors at tau."""

    status: PlanStatus
    """"ok", "tolerance" (racket errors at tau above tolerance) or "limits"."""
    reason: str
    """Why the status is not "ok" (empty when ok)."""
    score: float
    """Normalised tolerance excess (lower is better, for choosing among results)."""
    t: FloatArray
    """Sample times (N,) = k dt on [0, tau_f] [s]."""
    C: FloatArray
    """Commands sent at t_k (N, 8, 3): (u, u', u'') of the cubic at the interval midpoint."""
    Z: FloatArray
    """Exact planned chain state (N, 8, 5) at t_k (predicted q, q' in ``Z[..., 3:5]``)."""
    q_tau: FloatArray
    """Predicted joint positions at tau (8,)."""
    qd_tau: FloatArray
    """Predicted joint velocities at tau (8,)."""
    ep: float
    """Position error at tau [m] (pinocchio)."""
    ang: float
    """Normal error at tau [rad]."""
    ev: float
    """Velocity error at tau [m/s]."""
    slacks: FloatArray
    """The paper's slacks (3,): position excess [m], ``cos(dphi) - n.n_tau`` excess,
    velocity excess [m/s]."""
    violations: list[Violation]
    """Limit violations at 1 kHz (the worst per joint, component and segment)."""


@dataclass(frozen=True, eq=False)
class SolveResult:
    """What a solver produced for a strike problem."""

    status: PlanStatus
    """Status of the result (the check's, or "infeasible" / "failed")."""
    reason: str
    """Why the status is not "ok"."""
    z: FloatArray | None
    """Scaled jerks (8, n), None when the solver produced none."""
    solver: str
    """"sqp-daqp", "ipopt" or "joint-space"."""
    iterations: int
    """QPs solved (sqp-daqp) or IPOPT iterations."""
    score: float
    """Lower is better (normalised tolerance excess, for choosing among results)."""
    check: PlanCheck | None = None
    """The a-posteriori check of ``z`` (None: no trajectory to report)."""


def better(a: SolveResult, b: SolveResult) -> bool:
    """Whether ``a`` is a better result than ``b`` (status rank, then score)."""
    rank = {"ok": 0, "limits": 1, "tolerance": 2, "infeasible": 3, "failed": 4, "collision": 5}
    return (rank[a.status], a.score) < (rank[b.status], b.score)


def sample(problem: StrikeProblem, z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The 1 kHz output of jerks z (8, n).

    Returns:
        t (N,) = k dt on [0, tau_f]; C (N, 8, 3) the commands sent at t_k and held
        for dt, (u, u', u'') of the cubic at the interval midpoint t_k + dt/2 (so
        that the zero-order-hold response equals the planned one to O(dt^2));
        Z (N, 8, 5) the exact planned chain state at t_k (predicted q, q' in Z[..., 3:5]).
    """
    dt = problem.setup.options.dt
    N = int(math.floor(problem.target.tau_f / dt + 1e-9)) + 1
    t = np.arange(N, dtype=np.float64) * dt
    Z = problem.chain_at(z, t, on_grid=True)
    C = problem.chain_at(z, t + 0.5 * dt, commands_only=True)
    return t, C, Z


def check_values(C: FloatArray, Z: FloatArray) -> FloatArray:
    """(N, 8, 5) values subject to limits: sent commands (u, u', u'') and predicted (q, q')."""
    return np.concatenate([C, Z[..., 3:5]], axis=-1)


def limit_violations(problem: StrikeProblem, V: FloatArray, t: FloatArray) -> list[Violation]:
    """Samples of V = :func:`check_values` (N, 8, 5) beyond the limits: [(joint,
    component, time of the value, excess/limit)], the worst per (joint, component,
    segment). Command values are taken at t + dt/2, predicted ones at t."""
    sc = problem.setup.scaling
    rtol = problem.setup.options.limit_tolerance
    excess = np.maximum(V - sc.row_hi[None], sc.row_lo[None] - V) / sc.row_scale[None]
    bad = np.argwhere(excess > rtol)
    if bad.size == 0:
        return []
    return [(i, c, tv, e) for (i, c, _), (tv, e) in _worst_per_segment(problem, excess, t, bad).items()]


def _worst_per_segment(
    problem: StrikeProblem, excess: FloatArray, t: FloatArray, idx: npt.NDArray[np.int64]
) -> dict[tuple[int, int, int], tuple[float, float]]:
    """For sample indices idx (m, 3) = (sample, joint, component): the worst
    (time of the value, excess) per (joint, component, segment)."""
    g, dt, n = problem.grid, problem.setup.options.dt, problem.n
    si, ii, cc = idx[:, 0], idx[:, 1], idx[:, 2]
    tv = t[si] + np.where(cc < 3, 0.5 * dt, 0.0)
    seg = np.clip(np.searchsorted(g.tb, tv, side="right") - 1, 0, n)
    key = (ii * 5 + cc) * (n + 1) + seg
    e = excess[si, ii, cc]
    order = np.lexsort((-e, key))
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    out: dict[tuple[int, int, int], tuple[float, float]] = {}
    for o in order[first]:
        out[(int(ii[o]), int(cc[o]), int(seg[o]))] = (float(tv[o]), float(e[o]))
    return out


def check_jerks(problem: StrikeProblem, z: FloatArray) -> PlanCheck:
    """A-posteriori check of scaled jerks z (8, n): racket errors at tau against the
    tolerances, every limit at every 1 kHz sample, the jerk bounds."""
    robot, tg, tol = problem.setup.robot, problem.target, problem.tol
    t, C, Z = sample(problem, z)
    Zt = problem.state_at(z, tg.tau)
    q_tau, qd_tau = Zt[:, 3], Zt[:, 4]
    pose = robot.fk(q_tau)
    v, _ = robot.racket_velocity(q_tau, qd_tau)
    ep = float(np.linalg.norm(pose.position - tg.position))
    cosang = float(np.clip(pose.normal @ tg.normal, -1.0, 1.0))
    ang = math.acos(cosang)
    ev = float(np.linalg.norm(v - tg.velocity))
    excess = np.array([ep, ang, ev]) / tol
    slacks = np.array([max(0.0, ep - tol[0]), max(0.0, math.cos(tol[1]) - cosang), max(0.0, ev - tol[2])])
    score = float(np.sum(np.maximum(excess - 1.0, 0.0)))
    viol = limit_violations(problem, check_values(C, Z), t) if _beyond_limits(problem, C, Z) else []
    status, reason = _verdict(problem, z, excess, (ep, ang, ev), viol)
    return PlanCheck(status, reason, score, t, C, Z, q_tau, qd_tau, ep, ang, ev, slacks, viol)


def _beyond_limits(problem: StrikeProblem, C: FloatArray, Z: FloatArray) -> bool:
    """Whether any sample may be beyond a limit (fast path: most plans have nothing
    beyond; per-(joint, component) extremes over time: column reductions of contiguous
    arrays)."""
    sc = problem.setup.scaling
    lo, hi = sc.check_lo, sc.check_hi
    N = len(C)
    if N == 0:
        return False
    cmax, cmin = C.reshape(N, 24).max(axis=0).reshape(8, 3), C.reshape(N, 24).min(axis=0).reshape(8, 3)
    zmax, zmin = Z.reshape(N, 40).max(axis=0).reshape(8, 5)[:, 3:], Z.reshape(N, 40).min(axis=0).reshape(8, 5)[:, 3:]
    return bool(
        np.any(cmax > hi[:, :3]) or np.any(cmin < lo[:, :3]) or np.any(zmax > hi[:, 3:]) or np.any(zmin < lo[:, 3:])
    )


def _verdict(
    problem: StrikeProblem, z: FloatArray, excess: FloatArray, errors: tuple[float, float, float], viol: list[Violation]
) -> tuple[PlanStatus, str]:
    """Status and reason: racket errors at tau beyond tolerance (``excess`` (3,) in
    tolerances), else limits broken at 1 kHz (``viol``), else jerks beyond their bounds."""
    names, tol = problem.setup.robot.joint_names, problem.tol
    ep, ang, ev = errors
    if np.any(excess > 1.0):
        parts = []
        if excess[0] > 1:
            parts.append(f"position error {1e3 * ep:.2f} mm > {1e3 * tol[0]:.2f} mm")
        if excess[1] > 1:
            parts.append(f"normal error {math.degrees(ang):.3f} deg > {math.degrees(tol[1]):.3f} deg")
        if excess[2] > 1:
            parts.append(f"velocity error {ev:.4f} m/s > {tol[2]:.4f} m/s")
        return "tolerance", "racket state at tau outside tolerance: " + ", ".join(parts)
    if viol:
        i, c, tv, e = max(viol, key=lambda x: x[3])
        what = (
            "command position",
            "command velocity",
            "command acceleration",
            "predicted position",
            "predicted velocity",
        )[c]
        return "limits", (
            f"{what} of joint {names[i]!r} exceeds its limit by {100 * e:.3g} % "
            f"of the limit at t = {tv:.3f} s ({len(viol)} violation(s))"
        )
    zmax = np.max(np.abs(z), axis=1)
    if np.any(zmax > 1.0 + problem.setup.options.limit_tolerance):
        k = int(np.argmax(zmax))
        return "limits", (
            f"command jerk of joint {names[k]!r} exceeds its limit by {100 * (zmax[k] - 1):.3g} % of the limit"
        )
    return "ok", ""


def near_limit_samples(problem: StrikeProblem, check: PlanCheck, delta: float) -> dict[tuple[int, int, float], float]:
    """Values checked at 1 kHz (sent commands, predicted q, q' of ``check``) within
    ``delta`` (fraction of the limit) of a limit or beyond: the worst per (joint,
    component, segment), {(joint, component, time): excess}."""
    sc = problem.setup.scaling
    V = check_values(check.C, check.Z)
    excess = np.maximum(V - sc.row_hi[None], sc.row_lo[None] - V) / sc.row_scale[None]
    near = np.argwhere(excess > -delta)
    if near.size == 0:
        return {}
    return {(i, c, tv): e for (i, c, _), (tv, e) in _worst_per_segment(problem, excess, check.t, near).items()}


def jerk_ok(z: FloatArray) -> bool:
    """Every scaled jerk within its bound (1e-9 slack)."""
    return bool(np.all(np.abs(z) <= 1.0 + 1e-9))
