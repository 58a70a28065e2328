"""Strike motion planner: minimum-jerk joint commands that bring the racket to a desired
position, face normal and velocity at a desired time (paper, section "Parametrized
motion planner for dynamic ball intersection", problem (eq:nlp)).

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
  :func:`chain_transition`).
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

Solvers
=======
``"sqp-daqp"`` (default, ~5 ms):

1. Reduced problem in s (16 variables). Without active limits the minimum jerk for a
   given s is a quadratic in s (per joint a 2x2 block; jerks in closed form).
   Levenberg-Marquardt on the racket errors (regularised towards the unconstrained
   minimum-jerk s) brings s to the target from the seed (``warm_start`` or the
   minimum-jerk s); a Newton-SQP (exact Lagrangian Hessian of the casadi kinematics,
   one 16-variable DAQP QP per step, each step projected back onto the target by
   Gauss-Newton corrections and accepted when the jerk cost decreases) then minimises
   the jerk with the racket state at the *centre* of the tolerances.
2. If the closed-form jerks break a limit at 1 kHz: the full problem on the 256 jerks,
   by the same Newton-SQP (racket errors linearised at the current s, one dense QP
   per step, DAQP with a diagonal Hessian: the s-block is diagonalised), with the
   limit rows of the samples within 10 % of a limit; rounds add newly violated
   samples (``limit_rounds``). Rows are tightened by 0.1 % of the limit.

The paper's tolerances and slacks are thus handled by aiming at the centre (errors
~1e-6 tolerances) and checking the tolerances a posteriori; the jerk is minimal for
that centre, slightly above the optimum that uses the tolerances (measured: ~1-3 %).
``"ipopt"``: the paper's formulation itself (tolerance constraints in smooth squared
form with slacks weighted as the paper's table, radius ``margin * tolerance``), in a
sparse states-as-variables form, solved with IPOPT through casadi (one NLP per split
n1, built once and reused with parameters); the reference for tests and the fallback
(``options.fallback``) when the fast solver ends outside the tolerances.

A-posteriori check: the commands are sampled at 1 kHz (``u[k]`` is held over
[t_k, t_k + dt): it is the cubic at the interval midpoint, so the zero-order-hold
response equals the planned one to O(dt^2), ~1e-6 rad), the predicted joint state is
propagated exactly to tau from the last 1 kHz sample, the racket errors are
re-evaluated with pinocchio and every limit is checked at every sample; failures give
an invalid :class:`Plan` with a reason, never an exception.

Frames and units: world frame of ``DESIGN.md`` (origin at the centre of the playing
surface, +X to the receiver, +Z up), SI units; joint order and units of
:mod:`studio.robot.model` (gantry x, y [m]; a1..a6 [rad]). Times are relative to the start
of the strike (t = 0 at the switch from the toss).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Final, Literal

import casadi as ca
import daqp
import numpy as np
import numpy.typing as npt

from studio.robot.cup_hold import CupGrip, CupHoldCheck, check_cup_hold
from studio.errors import InvalidInputError, checked_array
from studio.planning.kinematics_casadi import CasadiKinematics, build_kinematics
from studio.robot.model import JointDynamics, JointLimits, Robot
from studio.robot.description import RACKET_FRAME

FloatArray = npt.NDArray[np.float64]

N_SEGMENTS: Final[int] = 32
"""Number of constant-jerk segments n_l on [0, tau_f] (paper: 32)."""

COMMAND_DT: Final[float] = 1e-3
"""Command period [s]: the robot takes joint commands at 1 kHz (paper)."""

SolverName = Literal["sqp-daqp", "ipopt"]
PlanStatus = Literal["ok", "infeasible", "tolerance", "limits", "collision", "failed"]

_INF: Final[float] = 1e30
_ROW_MARGIN: Final[float] = 1e-3
"""Limit rows of the QPs are tightened by this fraction of the limit, so that the 1 kHz
samples next to a constrained one stay within the true limit."""
_LM_STOP: Final[float] = 0.5
"""Levenberg-Marquardt hands over to the Newton-SQP once every racket error is below
this many tolerances."""
_NEAR: Final[float] = 0.1
"""1 kHz samples within this fraction of a limit become QP rows of the full problem."""
_FUNNEL: Final[float] = 0.5
"""Full problem: a step may raise the largest racket error (in tolerances) up to
max(_FUNNEL, 2 x current); longer steps are halved."""
_REDUCED_STEP_STOP: Final[float] = 5e-2
"""Reduced problem: the Newton-SQP stops after a full step smaller than this (scaled
variables, max norm) once the racket errors are below 1 % of their tolerances. On the
200 targets of ``benchmarks/planner.py`` (QPs of both problems): 1117 QPs with the
session-9 stops (step 1e-3, stall 1e-5), 1021 with the stall threshold at 1e-4 (both
problems), 899 with this stop as well; plan costs within 1e-5 of the longest polish at
the 95th percentile (1.6e-4 at most), errors at tau unchanged."""
_EQ: Final[int] = 5  # DAQP sense flag of an equality row


# ======================================================================================
# Parameters and results
# ======================================================================================


@dataclass(frozen=True, slots=True)
class StrikeTolerances:
    """Racket-state tolerances at tau (paper, Table "NMPC racket state tolerances")."""

    position: float = 5e-3
    """Delta p_tau [m]: radius of the position ball."""
    angle: float = math.radians(0.5)
    """Delta phi_tau [rad]: largest angle between the racket normal and n_tau."""
    velocity_abs: float = 0.01
    """Delta v_a,tau [m/s]: absolute velocity tolerance."""
    velocity_rel: float = 0.01
    """Delta v_r,tau [-]: velocity tolerance relative to |v_tau|."""

    def velocity(self, v_tau: FloatArray) -> float:
        """Velocity tolerance [m/s] for the target velocity ``v_tau`` (3,):
        ``max(velocity_abs, velocity_rel * |v_tau|)``."""
        return max(self.velocity_abs, self.velocity_rel * float(np.linalg.norm(v_tau)))


@dataclass(frozen=True, slots=True)
class SlackWeights:
    """Slack weights lambda_p, lambda_n, lambda_v (paper, same table)."""

    position: float = 2.0
    """lambda_p [1/m]."""
    normal: float = 1.0
    """lambda_n [-] (here per rad of normal error, see :class:`PlannerOptions`)."""
    velocity: float = 0.2
    """lambda_v [s/m]."""


@dataclass(frozen=True, slots=True)
class PlannerOptions:
    """Options of :class:`StrikePlanner` (keyword-only construction recommended)."""

    n_segments: int = N_SEGMENTS
    """Number of constant-jerk segments on [0, tau_f] (paper: 32)."""
    dt: float = COMMAND_DT
    """Output sample period [s] (1 kHz)."""
    tolerances: StrikeTolerances = field(default_factory=StrikeTolerances)
    """Tolerances of the a-posteriori check (and, times ``margin``, of IPOPT's constraints)."""
    slack_weights: SlackWeights = field(default_factory=SlackWeights)
    """Slack weights of the paper's table (IPOPT formulation)."""
    slack_scale: float = 1e3
    """Factor on the slack weights relative to the scaled jerk cost (dimensionless, at
    most ~4 with every jerk at its limit), so that the slacks act as an exact penalty:
    zero whenever the tolerances can be met. A slack of one tolerance costs
    ``slack_scale * lambda * tolerance`` (IPOPT formulation)."""
    margin: float = 0.85
    """Fraction of each tolerance used as IPOPT's constraint radius (room for the 1 kHz
    re-evaluation); the a-posteriori check uses the full tolerance. The sqp-daqp
    solver aims at the centre (zero error)."""
    max_iterations: int = 40
    """Iteration cap of each solver stage (reduced and full)."""
    limit_rounds: int = 4
    """How many times violations found at 1 kHz may be added as rows and re-solved."""
    limit_tolerance: float = 1e-6
    """Relative tolerance of the 1 kHz limit check (fraction of each limit)."""
    solver: SolverName = "sqp-daqp"
    """Default solver ("sqp-daqp" or "ipopt")."""
    fallback: bool = True
    """With "sqp-daqp": run IPOPT when the SQP ends outside the tolerances or fails."""
    ipopt_max_iter: int = 300
    """Iteration cap of IPOPT."""
    limits: JointLimits | None = None
    """Joint limits to plan with (None: the robot's; e.g. ``robot.limits.expanded(1.2)``)."""

    def __post_init__(self) -> None:
        if self.n_segments < 10:
            raise InvalidInputError(f"PlannerOptions.n_segments must be >= 10, got {self.n_segments}")
        for name in ("dt", "slack_scale", "margin", "limit_tolerance"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInputError(f"PlannerOptions.{name} must be finite and > 0, got {v!r}")
        if self.margin > 1.0:
            raise InvalidInputError(f"PlannerOptions.margin must be <= 1, got {self.margin}")
        if self.solver not in ("sqp-daqp", "ipopt"):
            raise InvalidInputError(f"PlannerOptions.solver must be 'sqp-daqp' or 'ipopt', got {self.solver!r}")


def _vec(x: npt.ArrayLike, shape: tuple[int, ...], name: str) -> FloatArray:
    """Validated read-only float array (shape, finite) or InvalidInputError naming ``name``."""
    return checked_array(x, shape, name)  # type: ignore[no-any-return]


@dataclass(frozen=True, slots=True)
class StrikeStart:
    """Initial, generally moving, state of the robot at the start of the strike.

    Usually taken from the toss trajectory at the switch time (commands and predicted
    joint state). Joint order of :mod:`studio.robot.model`, units m / rad.
    """

    u: FloatArray
    """Joint commands u0 (8,) [m | rad]."""
    ud: FloatArray
    """Command velocities u0' (8,) [m/s | rad/s]."""
    udd: FloatArray
    """Command accelerations u0'' (8,) [m/s^2 | rad/s^2]."""
    X: FloatArray
    """Predicted joint state X0 (8, 2): columns actual position q and velocity q'."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "u", _vec(self.u, (8,), "StrikeStart.u"))
        object.__setattr__(self, "ud", _vec(self.ud, (8,), "StrikeStart.ud"))
        object.__setattr__(self, "udd", _vec(self.udd, (8,), "StrikeStart.udd"))
        object.__setattr__(self, "X", _vec(self.X, (8, 2), "StrikeStart.X"))

    @classmethod
    def at_rest(cls, q: npt.ArrayLike) -> StrikeStart:
        """The robot standing still at configuration q (8,) (command = position)."""
        qa = _vec(q, (8,), "StrikeStart.at_rest q")
        z = np.zeros(8)
        return cls(u=qa, ud=z, udd=z, X=np.stack([qa, z], axis=1))


@dataclass(frozen=True, slots=True)
class StrikeTarget:
    """Desired racket state at tau and the end of the strike (paper's xi_s minus the
    initial state). World frame, SI units; times from the start of the strike."""

    tau: float
    """Contact time tau [s] (0 < tau < tau_f)."""
    position: FloatArray
    """p_tau (3,) [m]: racket origin (blade centre) at tau."""
    normal: FloatArray
    """n_tau (3,): racket face-A normal at tau (normalised here)."""
    velocity: FloatArray
    """v_tau (3,) [m/s]: velocity of the racket origin at tau."""
    tau_f: float
    """End of the strike [s]: the command is at rest at u_tauf."""
    u_rest: FloatArray | None = None
    """u_tauf (8,) [m | rad]: final command (None: the robot's q_rest)."""

    def __post_init__(self) -> None:
        for name in ("tau", "tau_f"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(float(v)):
                raise InvalidInputError(f"StrikeTarget.{name}: must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        object.__setattr__(self, "position", _vec(self.position, (3,), "StrikeTarget.position"))
        n = _vec(self.normal, (3,), "StrikeTarget.normal")
        nn = float(np.linalg.norm(n))
        if nn < 1e-9:
            raise InvalidInputError("StrikeTarget.normal: zero vector")
        n = n / nn
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "velocity", _vec(self.velocity, (3,), "StrikeTarget.velocity"))
        if self.u_rest is not None:
            object.__setattr__(self, "u_rest", _vec(self.u_rest, (8,), "StrikeTarget.u_rest"))
        if not (0.0 < self.tau < self.tau_f):
            raise InvalidInputError(f"StrikeTarget: need 0 < tau < tau_f, got tau={self.tau}, tau_f={self.tau_f}")


@dataclass(frozen=True, eq=False)
class Plan:
    """Result of :meth:`StrikePlanner.plan` (also for infeasible or invalid targets).

    Trajectories are sampled at ``t = k dt`` (1 kHz) on [0, tau_f], relative to the
    start of the strike; joint order of :mod:`studio.robot.model`. Arrays are empty (shape
    (0, 8)) when no trajectory was produced (status "infeasible" before solving).
    """

    status: PlanStatus
    """"ok", or why the plan is not valid: "infeasible" (no trajectory within the
    limits / bad inputs), "tolerance" (racket errors at tau above tolerance),
    "limits" (a limit broken at 1 kHz), "collision" (set by a collision check),
    "failed" (solver breakdown)."""
    reason: str
    """Human-readable explanation (empty when ok)."""
    target: StrikeTarget
    """The target planned for."""
    start: StrikeStart
    """The initial state planned from."""
    t: FloatArray
    """Sample times (N,) [s]."""
    u: FloatArray
    """Commands (N, 8) [m | rad]."""
    ud: FloatArray
    """Command velocities (N, 8)."""
    udd: FloatArray
    """Command accelerations (N, 8)."""
    q: FloatArray
    """Predicted joint positions (N, 8) (joint dynamics model, exact)."""
    qd: FloatArray
    """Predicted joint velocities (N, 8)."""
    segment_times: FloatArray
    """Segment boundaries (n_l + 1,) [s]; tau is ``segment_times[n_tau]``."""
    n_tau: int
    """Index of the boundary at tau (segments before tau)."""
    jerk: FloatArray
    """Piecewise-constant command jerks (n_l, 8) [m/s^3 | rad/s^3]."""
    q_tau: FloatArray
    """Predicted joint positions at tau (8,)."""
    qd_tau: FloatArray
    """Predicted joint velocities at tau (8,)."""
    position_error: float
    """|p(q_tau) - p_tau| [m] (pinocchio, a posteriori)."""
    angle_error: float
    """Angle between n(q_tau) and n_tau [rad]."""
    velocity_error: float
    """|v(q_tau, qd_tau) - v_tau| [m/s]."""
    slacks: FloatArray
    """Paper's slacks at the solution (3,): position excess [m], ``cos(dphi) - n.n_tau``
    excess [-], velocity excess [m/s] (0 when within tolerance)."""
    jerk_cost: float
    """Scaled jerk cost 1/2 sum_k (h_k / tau_f) |j_k / j_max|^2 [-]."""
    solver: str
    """Solver that produced the trajectory ("sqp-daqp", "ipopt", or "" if none)."""
    iterations: int
    """QPs solved (sqp-daqp) or IPOPT iterations, summed over stages."""
    solve_time_ms: float
    """Wall time of :meth:`StrikePlanner.plan` [ms] (checks included)."""

    @property
    def ok(self) -> bool:
        """True when the plan is valid (status "ok")."""
        return self.status == "ok"

    @property
    def tau(self) -> float:
        """Contact time [s]."""
        return self.target.tau

    def with_status(self, status: PlanStatus, reason: str) -> Plan:
        """A copy with another status and reason (e.g. after a collision check)."""
        return replace(self, status=status, reason=reason)


# ======================================================================================
# Exact discretization of the command/joint chain
# ======================================================================================


def chain_transition(dynamics: JointDynamics, delta: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Closed-form exact transition of the chain Z = [u, u', u'', q, q'] under a jerk
    held constant for ``delta`` seconds (same result as ``dynamics.jerk_chain(delta)``,
    vectorised and ~100x faster).

    The command part is the cubic; the joint part is split into the polynomial
    particular solution ``q_p = u - c1 u' + c3 u'' + c4 u'''`` of
    ``q'' + 2 zeta wn q' + wn^2 q = wn^2 u`` (c1 = 2 zeta / wn, c2 = 1 / wn^2,
    c3 = c1^2 - c2, c4 = 2 c1 c2 - c1^3) and the free response of ``e = q - q_p``.

    Args:
        dynamics: joint model (n joints).
        delta: durations [s], any shape S.

    Returns:
        A (S + (n, 5, 5)), B (S + (n, 5)) with Z(t + delta) = A Z(t) + B j.
    """
    wn, zeta = dynamics.wn, dynamics.zeta
    d = np.asarray(delta, dtype=float)[..., None]
    n = wn.shape[0]
    phi = _free_response(wn, zeta, d)
    c1, c3, c4 = _particular_coefficients(wn, zeta)
    dd = d[..., 0]
    Au = np.zeros(dd.shape + (3, 3))
    Au[..., 0, 0] = Au[..., 1, 1] = Au[..., 2, 2] = 1.0
    Au[..., 0, 1] = Au[..., 1, 2] = dd
    Au[..., 0, 2] = 0.5 * dd**2
    Bu = np.stack([dd**3 / 6.0, 0.5 * dd**2, dd], axis=-1)
    Pu = np.zeros((n, 2, 3))
    Pu[:, 0, 0] = 1.0
    Pu[:, 0, 1] = -c1
    Pu[:, 0, 2] = c3
    Pu[:, 1, 1] = 1.0
    Pu[:, 1, 2] = -c1
    pj = np.stack([c4, c3], axis=-1)
    A = np.zeros(dd.shape + (n, 5, 5))
    B = np.zeros(dd.shape + (n, 5))
    A[..., :3, :3] = Au[..., None, :, :]
    B[..., :3] = Bu[..., None, :]
    A[..., 3:, :3] = np.einsum("nij,...jk->...nik", Pu, Au) - phi @ Pu
    A[..., 3:, 3:] = phi
    B[..., 3:] = np.einsum("nij,...j->...ni", Pu, Bu) + pj - np.einsum("...nij,nj->...ni", phi, pj)
    return A, B


def _particular_coefficients(wn: FloatArray, zeta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    c1 = 2.0 * zeta / wn
    c2 = 1.0 / wn**2
    return c1, c1**2 - c2, 2.0 * c1 * c2 - c1**3


def _free_response(wn: FloatArray, zeta: FloatArray, d: FloatArray) -> FloatArray:
    """Transition (..., n, 2, 2) of e'' + 2 zeta wn e' + wn^2 e = 0 over d (..., 1) [s]
    (closed form per damping regime: under-, over- or critically damped)."""
    a = zeta * wn
    es, ec = _free_response_terms(wn, zeta, d)
    phi = np.empty(es.shape + (2, 2))
    phi[..., 0, 0] = ec + a * es
    phi[..., 0, 1] = es
    phi[..., 1, 0] = -(wn**2) * es
    phi[..., 1, 1] = ec - a * es
    return phi


def _free_response_terms(wn: FloatArray, zeta: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(e^{-a d} s(d), e^{-a d} c(d)) (..., n) with a = zeta wn, s = sin(w d)/w, c = cos(w d)
    (under-damped; sinh/cosh over-damped; series near critical damping), d (..., 1)."""
    a = zeta * wn
    om = wn * np.sqrt(np.abs(zeta**2 - 1.0))
    under = zeta < 1.0 - 1e-6
    if np.all(under):  # every joint under-damped (the serve robot): one complex exp, no masked writes
        e = np.exp((1j * om - a) * d)
        return e.imag / om, e.real
    ex = np.exp(-a * d)
    shape = np.broadcast_shapes(d.shape, wn.shape)
    s = np.empty(shape)
    c = np.empty(shape)
    over = zeta > 1.0 + 1e-6
    crit = ~(under | over)
    if np.any(under):
        x = om[under] * d
        s[..., under] = np.sin(x) / om[under]
        c[..., under] = np.cos(x)
    if np.any(over):
        x = np.minimum(om[over] * d, 700.0)
        s[..., over] = np.sinh(x) / om[over]
        c[..., over] = np.cosh(x)
    if np.any(crit):  # (near-)critical: series in (om d)^2 (|om d| is tiny here)
        x2 = np.sign(zeta[crit] - 1.0) * (om[crit] * d) ** 2
        s[..., crit] = d * (1.0 + x2 / 6.0)
        c[..., crit] = 1.0 + x2 / 2.0
    return ex * s, ex * c


@dataclass(frozen=True, eq=False)
class _Grid:
    """Time grid and affine boundary-state maps of one planning problem."""

    h: FloatArray  # (n,) segment lengths [s]
    tb: FloatArray  # (n+1,) boundaries [s]
    n1: int  # boundary index of tau
    T: FloatArray  # (8, n+1, 5, n+1): Z_k = T[..., 0] + T[..., 1:] @ z (z: scaled jerks of the joint)
    w: FloatArray  # (n,) cost weights h_k / tau_f


def _segment_split(n: int, tau: float, tau_f: float) -> int:
    return int(min(max(round(n * tau / tau_f), 4), n - 4))


def _build_grid(dyn: JointDynamics, jmax: FloatArray, start: StrikeStart, tau: float, tau_f: float, n: int) -> _Grid:
    n1 = _segment_split(n, tau, tau_f)
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
    return _Grid(h=h, tb=tb, n1=n1, T=T, w=h / tau_f)


# ======================================================================================
# The planner
# ======================================================================================


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
        n = self.options.n_segments
        self.n = n
        L = self.limits
        self._jmax = np.array(L.jerk, dtype=float)
        self._half = 0.5 * (L.upper - L.lower)
        self._mid = 0.5 * (L.upper + L.lower)
        # Scale of s = (q_tau, qd_tau) in the reduced problem.
        self._sig = np.concatenate([np.minimum(self._half, 1.0), L.velocity])
        # Row scales and bounds of the per-boundary limit rows: component c of Z.
        self._row_scale = np.stack([self._half, L.velocity, L.acceleration, self._half, L.velocity], axis=1)  # (8, 5)
        self._row_lo = np.stack([L.lower, -L.velocity, -L.acceleration, L.lower, -L.velocity], axis=1)
        self._row_hi = np.stack([L.upper, L.velocity, L.acceleration, L.upper, L.velocity], axis=1)
        tol = self.options.limit_tolerance * self._row_scale  # the 1 kHz check's bounds (fast path)
        self._check_lo, self._check_hi = self._row_lo - tol, self._row_hi + tol
        # Fast evaluation buffer of the strike terms (p, n, v and Jacobians).
        q = ca.SX.sym("q", 8)
        qd = ca.SX.sym("qd", 8)
        out = self.kin.strike_terms(q, qd)
        flat = ca.vertcat(*[ca.vec(ca.densify(o)) for o in out])
        self._terms_fn = ca.Function("terms_flat", [ca.vertcat(q, qd)], [flat], {"cse": True})
        self._terms_in = np.zeros(16)
        self._terms_out = np.zeros(9 + 4 * 24)
        buf, self._terms_trigger = self._terms_fn.buffer()
        buf.set_arg(0, memoryview(self._terms_in))
        buf.set_res(0, memoryview(self._terms_out))
        self._terms_buf = buf  # keep alive
        # Hessian of w . [p, n, v] in (q, qd), for the SQP's Lagrangian Hessian.
        w = ca.SX.sym("w", 9)
        xs = ca.vertcat(q, qd)
        lag = ca.dot(w[0:3], out[0]) + ca.dot(w[3:6], out[1]) + ca.dot(w[6:9], out[2])
        hess = ca.densify(ca.hessian(lag, xs)[0])
        self._hess_fn = ca.Function("lag_hess", [xs, w], [ca.vec(hess)], {"cse": True})
        self._hess_in = np.zeros(16)
        self._hess_w = np.zeros(9)
        self._hess_out = np.zeros(256)
        hbuf, self._hess_trigger = self._hess_fn.buffer()
        hbuf.set_arg(0, memoryview(self._hess_in))
        hbuf.set_arg(1, memoryview(self._hess_w))
        hbuf.set_res(0, memoryview(self._hess_out))
        self._hess_buf = hbuf
        self._ipopt_cache: dict[int, tuple[ca.Function, dict[str, slice]]] = {}
        # Free response on the 1 kHz grid: exp(lam j dt), lam = -zeta wn + i wd (under-damped joints).
        dyn = self.dynamics
        self._under = bool(np.all(dyn.zeta < 1.0 - 1e-6))
        self._lam = -dyn.zeta * dyn.wn + 1j * dyn.wn * np.sqrt(np.abs(1.0 - dyn.zeta**2))
        self._exp_re, self._exp_im = np.ones((1, 8)), np.zeros((1, 8))

    def _exp_steps(self, count: int) -> tuple[FloatArray, FloatArray]:
        """Real and imaginary parts of exp(lam j dt) (count, 8), j = 0..count-1 (cached,
        grown on demand; real arrays because numpy's complex product is ~6x slower)."""
        if len(self._exp_re) < count:
            j = np.arange(max(count, 2 * len(self._exp_re)))[:, None]
            e = np.exp(self._lam[None, :] * (j * self.options.dt))
            self._exp_re, self._exp_im = np.ascontiguousarray(e.real), np.ascontiguousarray(e.imag)
        return self._exp_re, self._exp_im

    # ---------------------------------------------------------------- kinematics
    def _terms(self, q: FloatArray, qd: FloatArray) -> tuple[FloatArray, ...]:
        self._terms_in[:8] = q
        self._terms_in[8:] = qd
        self._terms_trigger()
        o = self._terms_out
        # casadi stores matrices column-major.
        jp = o[9:33].reshape(8, 3).T
        jn = o[33:57].reshape(8, 3).T
        jvq = o[57:81].reshape(8, 3).T
        jvqd = o[81:105].reshape(8, 3).T
        return o[0:3].copy(), o[3:6].copy(), o[6:9].copy(), jp.copy(), jn.copy(), jvq.copy(), jvqd.copy()

    def _lag_hessian(self, s: FloatArray, w: FloatArray) -> FloatArray:
        """Hessian (16, 16) of w . [p, n, v](q, qd) at s = (q, qd)."""
        self._hess_in[:] = s
        self._hess_w[:] = w
        self._hess_trigger()
        return self._hess_out.reshape(16, 16).copy()

    # ---------------------------------------------------------------- public API
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
            A :class:`Plan`; invalid targets give a plan with ``ok == False`` and a reason.

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
        u_rest = target.u_rest if target.u_rest is not None else self.robot.q_rest
        ctx = _Context(self, start, target, np.asarray(u_rest, dtype=float))
        bad = ctx.check_inputs()
        if bad:
            return ctx.empty_plan("infeasible", bad, t0)
        seed = None
        if warm_start is not None and warm_start.q_tau.shape == (8,) and np.all(np.isfinite(warm_start.q_tau)):
            seed = np.concatenate([warm_start.q_tau, warm_start.qd_tau])
        if solver == "ipopt":
            res = ctx.solve_ipopt(seed_z=None, seed_s=seed)
        else:
            res = ctx.solve_sqp(seed)
            if self.options.fallback and (res is None or res.status != "ok"):
                alt = ctx.solve_ipopt(seed_z=res.z if res is not None else None, seed_s=seed)
                if alt is not None and (res is None or _better(alt, res)):
                    alt = replace(alt, iterations=alt.iterations + (res.iterations if res else 0))
                    res = alt
        if res is None:
            return ctx.empty_plan("failed", ctx.fail_reason or "no solver produced a trajectory", t0)
        return ctx.make_plan(res, t0)

    def plan_joint_target(
        self, start: StrikeStart, target: StrikeTarget, q_tau: npt.ArrayLike, qd_tau: npt.ArrayLike
    ) -> Plan:
        """Minimum-jerk plan through a given *joint* state at tau (no end-effector
        constraints): the closed-form solution of the reduced problem at s = (q_tau,
        qd_tau), checked like :meth:`plan` (limits at 1 kHz, racket errors against
        ``target``). A plan with status "ok" certifies that ``target`` is reachable
        within the limits (used by the benchmark to build reachable targets)."""
        t0 = time.perf_counter()
        qa = _vec(q_tau, (8,), "plan_joint_target q_tau")
        qda = _vec(qd_tau, (8,), "plan_joint_target qd_tau")
        u_rest = target.u_rest if target.u_rest is not None else self.robot.q_rest
        ctx = _Context(self, start, target, np.asarray(u_rest, dtype=float))
        bad = ctx.check_inputs()
        if bad:
            return ctx.empty_plan("infeasible", bad, t0)
        _, N, r0, _ = ctx.reduced_matrices()
        z = ctx.z_of_s(np.concatenate([qa, qda]), N, r0)
        status, reason, score, info = ctx.evaluate_result(z)
        return ctx.make_plan(_Result(status, reason, z, "joint-space", 0, score, info), t0)

    def _ipopt_solver(self, n1: int) -> tuple[ca.Function, dict[str, FloatArray]]:
        """The IPOPT NLP for tau at boundary n1 (built once, cached; all numbers that
        depend on tau, tau_f, the start and the target are parameters or bounds).

        Variables x = [Zs (8, n, 5) scaled chain states at boundaries 1..n, z (8, n)
        scaled jerks, eps (3) normalised slacks]; constraints: exact discrete dynamics
        (equalities) and the three end-effector constraints of the paper in smooth form
        (squared norms, normalised by the squared tolerances).
        """
        if n1 in self._ipopt_cache:
            return self._ipopt_cache[n1]
        n = self.n
        nZ, nz = 8 * n * 5, 8 * n
        x = ca.SX.sym("x", nZ + nz + 3)
        p = ca.SX.sym("p", 400 + 80 + 40 + 40 + 9 + 4 + 2 + 3)
        o = 0

        def take(k: int) -> ca.SX:
            nonlocal o
            v = p[o:o + k]
            o += k
            return v

        As, Bs, Z0s, S = take(400), take(80), take(40), take(40)
        p_tau, n_tau, v_tau, tol4, w, cs = take(3), take(3), take(3), take(4), take(2), take(3)
        Zs = x[:nZ]
        z = x[nZ:nZ + nz]
        eps = x[nZ + nz:]

        def Z_of(i: int, k: int) -> ca.SX:  # state of joint i at boundary k (1..n)
            if k == 0:
                return Z0s[i * 5:(i + 1) * 5]
            b = (i * n + (k - 1)) * 5
            return Zs[b:b + 5]

        g: list[ca.SX] = []
        for i in range(8):
            for k in range(n):
                ph = 0 if k < n1 else 1
                A = ca.reshape(As[(ph * 8 + i) * 25:(ph * 8 + i + 1) * 25], 5, 5).T  # row-major input
                Bv = Bs[(ph * 8 + i) * 5:(ph * 8 + i + 1) * 5]
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
        self._ipopt_cache[n1] = (solver, bounds)
        return solver, bounds

    def evaluate(self, q: npt.ArrayLike, qd: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Racket position [m], normal and velocity [m/s] (world) at (q, qd) (casadi FK)."""
        p, n, v = self._terms(np.asarray(q, dtype=float), np.asarray(qd, dtype=float))[:3]
        return p, n, v


@dataclass(frozen=True, eq=False)
class _Result:
    status: PlanStatus
    reason: str
    z: FloatArray  # (8, n) scaled jerks
    solver: str
    iterations: int
    score: float  # lower is better (normalised tolerance excess, for choosing among results)
    info: dict[str, object] | None = None  # a-posteriori evaluation (samples, errors)


def _better(a: _Result, b: _Result) -> bool:
    rank = {"ok": 0, "limits": 1, "tolerance": 2, "infeasible": 3, "failed": 4, "collision": 5}
    return (rank[a.status], a.score) < (rank[b.status], b.score)


class _Context:
    """Numeric data of one call of :meth:`StrikePlanner.plan`."""

    def __init__(self, pl: StrikePlanner, start: StrikeStart, target: StrikeTarget, u_rest: FloatArray) -> None:
        self.pl = pl
        self.start = start
        self.target = target
        self.u_rest = u_rest
        self.n = pl.n
        o = pl.options
        tol = o.tolerances
        self.tol = np.array([tol.position, tol.angle, tol.velocity(target.velocity)])
        self.cost_slack = o.slack_scale * np.array(
            [o.slack_weights.position, o.slack_weights.normal, o.slack_weights.velocity]
        ) * self.tol
        self.fail_reason = ""
        self.grid: _Grid | None = None
        # Tangent basis of the target normal.
        nt = target.normal
        a = np.array([1.0, 0.0, 0.0]) if abs(nt[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t1 = np.cross(nt, a)
        t1 /= np.linalg.norm(t1)
        self.tangent = np.stack([t1, np.cross(nt, t1)], axis=0)  # (2, 3)

    # ------------------------------------------------------------------ inputs
    def check_inputs(self) -> str:
        """Reason why the problem cannot be posed, or ''."""
        pl, s, L = self.pl, self.start, self.pl.limits
        names = pl.robot.joint_names
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

    def empty_plan(self, status: PlanStatus, reason: str, t0: float) -> Plan:
        e8 = np.zeros((0, 8))
        nanv = np.full(8, np.nan)
        return Plan(
            status=status, reason=reason, target=self.target, start=self.start, t=np.zeros(0), u=e8, ud=e8,
            udd=e8, q=e8, qd=e8, segment_times=np.zeros(0), n_tau=0, jerk=np.zeros((0, 8)), q_tau=nanv,
            qd_tau=nanv, position_error=math.nan, angle_error=math.nan, velocity_error=math.nan,
            slacks=np.full(3, np.nan), jerk_cost=math.nan, solver="", iterations=0,
            solve_time_ms=1e3 * (time.perf_counter() - t0),
        )

    # ------------------------------------------------------------------ grid helpers
    def get_grid(self) -> _Grid:
        if self.grid is None:
            pl = self.pl
            self.grid = _build_grid(pl.dynamics, pl._jmax, self.start, self.target.tau, self.target.tau_f, self.n)
        return self.grid

    def s_of_z(self, z: FloatArray) -> FloatArray:
        """(q_tau, qd_tau) (16,) for scaled jerks z (8, n)."""
        g = self.get_grid()
        Tn = g.T[:, g.n1, 3:5]  # (8, 2, n+1)
        val = Tn[:, :, 0] + np.einsum("ick,ik->ic", Tn[:, :, 1:], z)
        return np.concatenate([val[:, 0], val[:, 1]])

    # ------------------------------------------------------------------ racket errors at tau
    def residuals(self, s: FloatArray, *, full_normal: bool = False) -> tuple[FloatArray, FloatArray]:
        """Racket errors at tau in units of their tolerances, r (8,) =
        [(p - p_tau)/dp (3), T (n - n_tau)/dphi (2), (v - v_tau)/dv (3)] (T: two unit
        vectors orthogonal to n_tau), and their Jacobian (8, 16) in s = (q_tau, qd_tau).
        With ``full_normal`` the normal part is the 3-vector (n - n_tau)/dphi (r (9,)),
        whose only zero is n = +n_tau (used far from the target; the tangential form
        also vanishes at the antipode)."""
        tg, pl = self.target, self.pl
        pl._terms_in[:] = s  # the casadi buffer: read in place (the outputs below are new arrays)
        pl._terms_trigger()
        o = pl._terms_out
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
        r[3 + k:] = (o[6:9] - tg.velocity) / tv
        J[3 + k:, :8] = jac[2].T / tv
        J[3 + k:, 8:] = jac[3].T / tv
        return r, J

    def residual_hessian(self, s: FloatArray, lam: FloatArray) -> FloatArray:
        """sum_i lam_i Hessian(r_i) (16, 16) in s, for weights lam (8,)."""
        w = np.concatenate([lam[0:3] / self.tol[0], self.tangent.T @ lam[3:5] / self.tol[1], lam[5:8] / self.tol[2]])
        H = self.pl._lag_hessian(s, w)
        return 0.5 * (H + H.T)

    # ------------------------------------------------------------------ reduced problem
    def reduced_matrices(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Per-joint min-jerk solution as a function of s.

        Returns:
            K (8, 5, 5), N (8, n, 5) with z_i = N_i r_i, r0 (8, 5) the constant part of
            r_i = r0_i + [0, 0, 0, q_i, qd_i]; s_hat (16,) the unconstrained minimiser.
        """
        g = self.get_grid()
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
        return K, N, r0, s_hat

    def z_of_s(self, s: FloatArray, N: FloatArray, r0: FloatArray) -> FloatArray:
        r = r0.copy()
        r[:, 3] += s[:8]
        r[:, 4] += s[8:]
        return np.einsum("ink,ik->in", N, r)

    def reduced_hessian(self, K: FloatArray) -> FloatArray:
        """H (16, 16) of the reduced cost 1/2 (s - s_hat)^T H (s - s_hat) (2x2 blocks)."""
        H = np.zeros((16, 16))
        idx = np.arange(8)
        H[idx, idx] = K[:, 3, 3]
        H[idx, idx + 8] = K[:, 3, 4]
        H[idx + 8, idx] = K[:, 4, 3]
        H[idx + 8, idx + 8] = K[:, 4, 4]
        return H

    def _levenberg_marquardt(
        self, s: FloatArray, s_hat: FloatArray, H: FloatArray, s_lo: FloatArray, s_hi: FloatArray
    ) -> tuple[FloatArray, int]:
        """Reach the target from a far seed: Levenberg-Marquardt on
        1/2 |r(s)|^2 + 1/2 (s - s_hat)^T H (s - s_hat) (errors in tolerances, regularised
        towards the minimum-jerk s_hat, so that it lands near the cheapest solution),
        with s clipped into its limits. Returns (s, iterations)."""
        sig = self.pl._sig
        Hy = H * np.outer(sig, sig)

        def F(sv: FloatArray, r: FloatArray) -> float:
            d = sv - s_hat
            return 0.5 * float(r @ r) + 0.5 * float(d @ H @ d)

        r, J = self.residuals(s, full_normal=True)
        f = F(s, r)
        lam = 1e-3
        it = 0
        for it in range(3 * self.pl.options.max_iterations):
            Jy = J * sig[None, :]
            g = Jy.T @ r + sig * (H @ (s - s_hat))
            A = Jy.T @ Jy + Hy
            dscale = np.diag(A).copy() + 1e-12
            improved = False
            for _ in range(12):
                y = np.linalg.solve(A + lam * np.diag(dscale), -g)
                s_new = np.clip(s + sig * y, s_lo, s_hi)
                r_new, J_new = self.residuals(s_new, full_normal=True)
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

    def project(self, s: FloatArray, s_lo: FloatArray, s_hi: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Pull s back onto r(s) = 0 with up to 4 minimum-norm Gauss-Newton corrections
        (scaled variables, clipped to the limits). Returns (s, r, J)."""
        sig = self.pl._sig
        r, J = self.residuals(s)
        for _ in range(4):
            if float(np.max(np.abs(r))) < 1e-3:
                break
            Jy = J * sig[None, :]
            d = Jy.T @ np.linalg.solve(Jy @ Jy.T + 1e-12 * np.eye(Jy.shape[0]), r)
            s = np.clip(s - sig * d, s_lo, s_hi)
            r, J = self.residuals(s)
        return s, r, J

    def s_bounds(self) -> tuple[FloatArray, FloatArray]:
        L = self.pl.limits
        return np.concatenate([L.lower, -L.velocity]), np.concatenate([L.upper, L.velocity])

    def solve_reduced(self, seed: FloatArray | None) -> tuple[FloatArray, int, bool]:
        """The 16-variable problem in s = (q_tau, qd_tau): Levenberg-Marquardt from the
        seed (default: the unconstrained minimum-jerk s_hat) to the target, then
        Newton-SQP polishing (:meth:`newton_sqp`). Returns (s, QPs, converged)."""
        K, N, r0, s_hat = self.reduced_matrices()
        self._reduced = (N, r0)
        H = self.reduced_hessian(K)
        s_lo, s_hi = self.s_bounds()
        s = np.clip(seed if seed is not None else s_hat, s_lo, s_hi)
        s, _ = self._levenberg_marquardt(s, s_hat, H, s_lo, s_hi)
        _, s, qps, reason = self.newton_sqp(
            w0=np.zeros(0), s0=s, Q=np.zeros(0), Hs=H, s_hat=s_hat, wlo=np.zeros(0), whi=np.zeros(0),
            A_w=np.zeros((0, 0)), A_s=np.zeros((0, 16)), lo=np.zeros(0), hi=np.zeros(0), eq=np.zeros(0, dtype=bool),
        )
        return s, qps, not reason

    def newton_sqp(
        self,
        *,
        w0: FloatArray,
        s0: FloatArray,
        Q: FloatArray,
        Hs: FloatArray,
        s_hat: FloatArray,
        wlo: FloatArray,
        whi: FloatArray,
        A_w: FloatArray,
        A_s: FloatArray,
        lo: FloatArray,
        hi: FloatArray,
        eq: npt.NDArray[np.bool_],
    ) -> tuple[FloatArray, FloatArray, int, str]:
        """Local SQP (Newton-KKT) for

            min 1/2 w^T diag(Q) w + 1/2 (s - s_hat)^T Hs (s - s_hat)
            s.t. r(s) = 0 (racket errors at tau, the centre of the tolerances),
                 lo <= A_w w + A_s s <= hi (rows with eq: equalities), wlo <= w <= whi,
                 s within the position/velocity limits.

        Each iteration linearises r at s and solves one convex QP with DAQP; the
        s-block of its Hessian is Hs + sum_i lam_i Hess(r_i) (the Lagrangian Hessian,
        multipliers of the previous QP) plus rho J^T J, which leaves the solution of the
        equality-constrained QP unchanged and makes it positive definite; it is
        diagonalised (y = V t) so DAQP sees a diagonal Hessian. The start must be near
        the solution (the reduced problem's Levenberg-Marquardt point): there is no
        globalisation beyond keeping the best iterate by (max error, cost).

        Returns:
            (w, s, QPs solved, failure reason or "").
        """
        pl = self.pl
        o = pl.options
        sig = pl._sig
        s_lo, s_hi = self.s_bounds()
        nw = w0.size
        nx = nw + 16
        iy = slice(nw, nx)
        Hs_y = Hs * np.outer(sig, sig)
        nr = A_w.shape[0]
        A_ws = A_s * sig[None, :] if nr else np.zeros((0, 16))
        sense = np.concatenate([np.zeros(nx), np.where(eq, _EQ, 0), np.zeros(16), np.full(8, _EQ)]).astype(np.int32)
        zeros_w = np.zeros((24, nw))

        def cost(w: FloatArray, s: FloatArray) -> float:
            d = s - s_hat
            return 0.5 * float(w @ (Q * w)) + 0.5 * float(d @ Hs @ d)

        w, s = w0.copy(), s0.copy()
        r, J = self.residuals(s)
        lam_r = np.zeros(8)
        qps = 0
        best: tuple[float, float, FloatArray, FloatArray] | None = None
        prev_cost: float | None = None
        for _ in range(o.max_iterations):
            Jy = J * sig[None, :]
            B = Hs_y + self.residual_hessian(s, lam_r) * np.outer(sig, sig)
            ev = np.linalg.eigvalsh(B)
            if ev[0] < 1e-9 * max(abs(float(ev[-1])), 1e-9):
                # Lift negative curvature along the constraint normals (this leaves the
                # solution of the equality-constrained QP unchanged); floor the rest.
                JtJ = Jy.T @ Jy
                ej = np.linalg.eigvalsh(JtJ)[-8]  # smallest of the (generically 8) non-zero ones
                B = B + (10.0 * abs(float(ev[0])) / max(float(ej), 1e-12)) * JtJ
            lam_h, V = np.linalg.eigh(B)
            floor = 1e-8 * max(float(lam_h[-1]), 1e-8)
            lam_h = np.maximum(lam_h, floor)
            g = sig * (Hs @ (s - s_hat))
            base = A_s @ s if nr else np.zeros(0)
            A = np.vstack([
                np.hstack([A_w, A_ws @ V]) if nr else np.zeros((0, nx)),
                np.hstack([zeros_w, np.vstack([V, Jy @ V])]),
            ])
            bu = np.concatenate([whi, np.full(16, _INF), hi - base, (s_hi - s) / sig, -r])
            bl = np.concatenate([wlo, np.full(16, -_INF), lo - base, (s_lo - s) / sig, -r])
            f = np.concatenate([np.zeros(nw), V.T @ g])
            x, _, flag, info = daqp.solve(np.diag(np.concatenate([Q, lam_h])), f, A, bu, bl, sense)
            qps += 1
            if flag < 1:
                if best is None and nr:
                    return w, s, qps, f"QP infeasible (DAQP exit flag {flag}): the limits cannot be met"
                break
            lam_r = np.asarray(info["lam"])[-8:]
            # Funnel: take the largest of 1, 1/2, 1/4, ... of the step that keeps the
            # errors below max(funnel, 2 x current) (convex combinations keep the
            # linear rows); the Newton step is accepted in the end game.
            y_full = V @ x[iy]
            dw = x[:nw] - w
            r_max = float(np.max(np.abs(r)))
            alpha = 1.0
            if nw == 0:
                # Reduced problem: feasible steps. Project each trial point back onto
                # r(s) = 0 (minimum-norm Gauss-Newton corrections) and accept it if the
                # cost does not increase; else halve the step.
                c_old = cost(w, s)
                accepted = False
                for _ in range(8):
                    s_new, r_new, J_new = self.project(s + alpha * sig * y_full, s_lo, s_hi)
                    if float(np.max(np.abs(r_new))) <= max(0.05, r_max) and cost(w, s_new) <= c_old + 1e-12 * abs(c_old):
                        accepted = True
                        break
                    alpha *= 0.5
                if not accepted:
                    break
            else:
                for trial in range(6):
                    s_new = s + alpha * sig * y_full
                    r_new, J_new = self.residuals(s_new)
                    if float(np.max(np.abs(r_new))) <= max(_FUNNEL, 2.0 * r_max) or trial == 5:
                        break  # (the last trial is taken as is: w and s move by the same alpha)
                    alpha *= 0.5
            y = alpha * y_full
            w_new = w + alpha * dw
            step = float(np.max(np.abs(y)))
            w, s, r, J = w_new, s_new, r_new, J_new
            key = (float(np.max(np.abs(r))), cost(w, s))
            # a full step, errors within 1 % of their tolerances and a cost change below 1e-4
            # of it: what is left is a Newton polish of no value (the linear rows hold at
            # every iterate; the a-posteriori check verifies the result anyway)
            stalled = alpha == 1.0 and prev_cost is not None and key[0] < 1e-2 and abs(prev_cost - key[1]) <= 1e-4 * abs(prev_cost)
            # Reduced problem: the full Newton steps converge quadratically (0.4, 0.15,
            # 0.01, 2e-5 typically), so after a full step below _REDUCED_STEP_STOP what is
            # left changes the cost by ~1e-5 of it (measured on the benchmark's targets).
            small = _REDUCED_STEP_STOP if nw == 0 and alpha == 1.0 else 1e-3
            prev_cost = key[1]
            if best is None or (max(key[0], 0.05) , key[1]) < (max(best[0], 0.05), best[1]):
                best = (key[0], key[1], w.copy(), s.copy())
            if step < 1e-7 or (step < small and key[0] < 1e-2) or stalled:
                break
        if best is None:
            return w, s, qps, "no QP solved"
        return best[2], best[3], qps, ""

    # ------------------------------------------------------------------ full problem
    def terminal_rows(self) -> tuple[FloatArray, FloatArray]:
        g, n = self.get_grid(), self.n
        coef = g.T[:, n, 0:3, 1:] / self.pl._row_scale[:, 0:3, None]  # (8, 3, n)
        target = np.stack([self.u_rest, np.zeros(8), np.zeros(8)], axis=1)
        rhs = (target - g.T[:, n, 0:3, 0]) / self.pl._row_scale[:, 0:3]
        A = np.zeros((8, 3, 8, n))
        A[np.arange(8), :, np.arange(8), :] = coef
        return A.reshape(24, 8 * n), rhs.reshape(-1)

    def s_map(self) -> tuple[FloatArray, FloatArray]:
        """s = M z_flat + m0."""
        g, n = self.get_grid(), self.n
        M = np.zeros((16, 8 * n))
        for i in range(8):
            M[i, i * n:(i + 1) * n] = g.T[i, g.n1, 3, 1:]
            M[8 + i, i * n:(i + 1) * n] = g.T[i, g.n1, 4, 1:]
        m0 = np.concatenate([g.T[:, g.n1, 3, 0], g.T[:, g.n1, 4, 0]])
        return M, m0

    def sample_rows(self, pts: list[tuple[int, int, float]]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Limit rows (scaled by the limit) of component c of joint i at time t, for
        pts = [(i, c, t)]: (A (m, 8n), lo (m,), hi (m,)). Rows without any dependence
        on the jerks (after tau_f for the commands) are dropped."""
        g, pl, n = self.get_grid(), self.pl, self.n
        tt = np.array([t for _, _, t in pts])
        ks = np.clip(np.searchsorted(g.tb, tt, side="right") - 1, 0, n)
        A_d, B_d = chain_transition(pl.dynamics, tt - g.tb[ks])  # (m, 8, 5, 5), (m, 8, 5)
        rows = np.zeros((len(pts), 8 * n))
        lo = np.zeros(len(pts))
        hi = np.zeros(len(pts))
        keep = np.zeros(len(pts), dtype=bool)
        for r, ((i, c, _), k) in enumerate(zip(pts, ks, strict=True)):
            coef = A_d[r, i, c] @ g.T[i, k]  # (n+1,)
            if k < n:
                coef[1 + k] += B_d[r, i, c] * pl._jmax[i]
            sc = pl._row_scale[i, c]
            rows[r, i * n:(i + 1) * n] = coef[1:] / sc
            lo[r] = (pl._row_lo[i, c] - coef[0]) / sc + _ROW_MARGIN
            hi[r] = (pl._row_hi[i, c] - coef[0]) / sc - _ROW_MARGIN
            keep[r] = bool(np.any(np.abs(coef[1:]) > 1e-14))
        return rows[keep], lo[keep], hi[keep]

    def solve_full(
        self, s0: FloatArray, z0: FloatArray, extra: tuple[FloatArray, FloatArray, FloatArray] | None
    ) -> tuple[FloatArray | None, int, str]:
        """The full problem on the jerks (jerk bounds, terminal rest, the limit rows
        ``extra`` = (A (R, 8n), lo, hi) of selected 1 kHz samples) with the trust-region
        SQP :meth:`sqp`, starting from z0 (8, n), s0. Returns (z or None, QPs, reason)."""
        n = self.n
        nz = 8 * n
        if extra is not None:
            A_lim, lo_lim, hi_lim = extra
        else:
            A_lim, lo_lim, hi_lim = np.zeros((0, nz)), np.zeros(0), np.zeros(0)
        A_eq, b_eq = self.terminal_rows()
        M, m0 = self.s_map()
        g = self.get_grid()
        nl = A_lim.shape[0]
        A_w = np.vstack([A_eq, A_lim, M])
        A_s = np.vstack([np.zeros((24 + nl, 16)), -np.eye(16)])
        lo = np.concatenate([b_eq, lo_lim, -m0])
        hi = np.concatenate([b_eq, hi_lim, -m0])
        eq = np.concatenate([np.ones(24, dtype=bool), np.zeros(nl, dtype=bool), np.ones(16, dtype=bool)])
        w, _, qps, reason = self.newton_sqp(
            w0=z0.reshape(-1), s0=s0, Q=np.tile(g.w, 8), Hs=np.zeros((16, 16)), s_hat=s0,
            wlo=-np.ones(nz), whi=np.ones(nz), A_w=A_w, A_s=A_s, lo=lo, hi=hi, eq=eq,
        )
        if reason:
            return None, qps, reason
        return w.reshape(8, n), qps, ""

    # ------------------------------------------------------------------ sampling & checks
    def boundary_states(self, z: FloatArray) -> FloatArray:
        """Z at the boundaries (n+1, 8, 5) in physical units."""
        g = self.get_grid()
        Z = g.T[..., 0] + np.einsum("ikcj,ij->ikc", g.T[..., 1:], z)  # (8, n+1, 5)
        return np.transpose(Z, (1, 0, 2))

    def chain_at(self, z: FloatArray, times: FloatArray, *, commands_only: bool = False, on_grid: bool = False) -> FloatArray:
        """Exact chain state Z = [u, u', u'', q, q'] (N, 8, 5) at times (N,) [s] for the
        scaled jerks z (8, n); after tau_f the command rests at u_tauf (zero jerk).
        ``on_grid``: times are k dt, k = 0..N-1 (the 1 kHz output), which lets the free
        response come from a cached table (exp(lam d) = exp(lam j dt) exp(lam phi_k) with
        d = j dt + phi_k, phi_k the offset of segment k's first sample)."""
        g, pl, n = self.get_grid(), self.pl, self.n
        Zb = self.boundary_states(z)  # (n+1, 8, 5)
        jerk = np.vstack([(z * pl._jmax[:, None]).T, np.zeros((1, 8))])  # (n+1, 8)
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
        wn, zeta = pl.dynamics.wn, pl.dynamics.zeta
        c1, c3, c4 = _particular_coefficients(wn, zeta)
        # tracking error e = q - q_particular and its rate at each segment start, gathered
        e0 = (Z3 - (Z0 - c1 * Z1 + c3 * Z2 + c4 * jerk)).take(k, axis=0)
        e0d = (Z4 - (Z1 - c1 * Z2 + c3 * jerk)).take(k, axis=0)
        if on_grid and pl._under and len(times):
            first = np.searchsorted(k, np.arange(n + 1))  # index of each segment's first sample
            first_of = first[k]
            j = np.arange(len(times)) - first_of
            phi = times[np.minimum(first, len(times) - 1)] - g.tb  # (n+1,) offset of that sample
            er, ei = pl._exp_steps(int(j.max()) + 1)
            er, ei = er.take(j, axis=0), ei.take(j, axis=0)
            p = np.exp(pl._lam[None, :] * phi[:, None])  # (n+1, 8)
            pr, pi = p.real.take(k, axis=0), p.imag.take(k, axis=0)
            es, ec = (er * pi + ei * pr) / (wn * np.sqrt(1.0 - zeta**2)), er * pr - ei * pi
        else:
            es, ec = _free_response_terms(wn, zeta, d)  # e^{-a d} s(d), e^{-a d} c(d): (N, 8)
        a = zeta * wn
        out = np.empty(u.shape + (5,))
        out[..., 0] = u
        out[..., 1] = ud
        out[..., 2] = udd
        out[..., 3] = u - c1 * ud + c3 * udd + c4 * jk + (ec + a * es) * e0 + es * e0d
        out[..., 4] = ud - c1 * udd + c3 * jk - (wn**2) * es * e0 + (ec - a * es) * e0d
        return out

    def sample(self, z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The 1 kHz output of jerks z (8, n).

        Returns:
            t (N,) = k dt on [0, tau_f]; C (N, 8, 3) the commands sent at t_k and held
            for dt, (u, u', u'') of the cubic at the interval midpoint t_k + dt/2 (so
            that the zero-order-hold response equals the planned one to O(dt^2));
            Z (N, 8, 5) the exact planned chain state at t_k (predicted q, q' in Z[..., 3:5]).
        """
        dt = self.pl.options.dt
        N = int(math.floor(self.target.tau_f / dt + 1e-9)) + 1
        t = np.arange(N) * dt
        Z = self.chain_at(z, t, on_grid=True)
        C = self.chain_at(z, t + 0.5 * dt, commands_only=True)
        return t, C, Z

    def check_values(self, C: FloatArray, Z: FloatArray) -> FloatArray:
        """(N, 8, 5) values subject to limits: sent commands (u, u', u'') and predicted (q, q')."""
        return np.concatenate([C, Z[..., 3:5]], axis=-1)

    def state_at(self, z: FloatArray, t: float) -> FloatArray:
        """Chain state (8, 5) at time t, propagated exactly with :func:`chain_transition`
        from the last 1 kHz sample at or before t (an independent path from the
        boundary-state maps used by the solver)."""
        g, pl, n = self.get_grid(), self.pl, self.n
        dt = pl.options.dt
        t0 = math.floor(t / dt + 1e-9) * dt
        Z = self.chain_at(z, np.array([t0]))[0]
        cur_t = t0
        jerk = z * pl._jmax[:, None]
        while t - cur_t > 1e-15:
            k = int(min(max(np.searchsorted(g.tb, cur_t + 1e-12, side="right") - 1, 0), n - 1))
            t_end = min(t, float(g.tb[k + 1]))
            A, B = chain_transition(pl.dynamics, t_end - cur_t)
            Z = np.einsum("nij,nj->ni", A, Z) + B * jerk[:, k][:, None]
            cur_t = t_end
        return Z

    def limit_violations(self, V: FloatArray, t: FloatArray) -> list[tuple[int, int, float, float]]:
        """Samples of V = :meth:`check_values` (N, 8, 5) beyond the limits: [(joint,
        component, time of the value, excess/limit)], the worst per (joint, component,
        segment). Command values are taken at t + dt/2, predicted ones at t."""
        pl = self.pl
        rtol = pl.options.limit_tolerance
        excess = np.maximum(V - pl._row_hi[None], pl._row_lo[None] - V) / pl._row_scale[None]
        bad = np.argwhere(excess > rtol)
        if bad.size == 0:
            return []
        return [(i, c, tv, e) for (i, c, _), (tv, e) in self._worst_per_segment(excess, t, bad).items()]

    def _worst_per_segment(
        self, excess: FloatArray, t: FloatArray, idx: npt.NDArray[np.int64]
    ) -> dict[tuple[int, int, int], tuple[float, float]]:
        """For sample indices idx (m, 3) = (sample, joint, component): the worst
        (time of the value, excess) per (joint, component, segment)."""
        g, dt = self.get_grid(), self.pl.options.dt
        si, ii, cc = idx[:, 0], idx[:, 1], idx[:, 2]
        tv = t[si] + np.where(cc < 3, 0.5 * dt, 0.0)
        seg = np.clip(np.searchsorted(g.tb, tv, side="right") - 1, 0, self.n)
        key = (ii * 5 + cc) * (self.n + 1) + seg
        e = excess[si, ii, cc]
        order = np.lexsort((-e, key))
        first = np.ones(order.size, dtype=bool)
        first[1:] = key[order][1:] != key[order][:-1]
        out: dict[tuple[int, int, int], tuple[float, float]] = {}
        for o in order[first]:
            out[(int(ii[o]), int(cc[o]), int(seg[o]))] = (float(tv[o]), float(e[o]))
        return out

    def evaluate_result(self, z: FloatArray) -> tuple[PlanStatus, str, float, dict[str, object]]:
        """A-posteriori check of scaled jerks z (8, n): status, reason, score, samples."""
        pl, tg = self.pl, self.target
        t, C, Z = self.sample(z)
        Zt = self.state_at(z, tg.tau)
        q_tau, qd_tau = Zt[:, 3], Zt[:, 4]
        pose = pl.robot.fk(q_tau)
        v, _ = pl.robot.racket_velocity(q_tau, qd_tau)
        ep = float(np.linalg.norm(pose.position - tg.position))
        cosang = float(np.clip(pose.normal @ tg.normal, -1.0, 1.0))
        ang = math.acos(cosang)
        ev = float(np.linalg.norm(v - tg.velocity))
        tol = self.tol
        excess = np.array([ep, ang, ev]) / tol
        info: dict[str, object] = dict(
            t=t, C=C, Z=Z, q_tau=q_tau, qd_tau=qd_tau, ep=ep, ang=ang, ev=ev,
            slacks=np.array([max(0.0, ep - tol[0]), max(0.0, math.cos(tol[1]) - cosang), max(0.0, ev - tol[2])]),
        )
        score = float(np.sum(np.maximum(excess - 1.0, 0.0)))
        lo, hi = self.pl._check_lo, self.pl._check_hi  # fast path: most plans have nothing beyond
        N = len(t)  # per-(joint, component) extremes over time: column reductions of contiguous arrays
        beyond = False
        if N > 0:
            cmax, cmin = C.reshape(N, 24).max(axis=0).reshape(8, 3), C.reshape(N, 24).min(axis=0).reshape(8, 3)
            zmax, zmin = Z.reshape(N, 40).max(axis=0).reshape(8, 5)[:, 3:], Z.reshape(N, 40).min(axis=0).reshape(8, 5)[:, 3:]
            beyond = bool(np.any(cmax > hi[:, :3]) or np.any(cmin < lo[:, :3]) or np.any(zmax > hi[:, 3:]) or np.any(zmin < lo[:, 3:]))
        viol = self.limit_violations(self.check_values(C, Z), t) if beyond else []
        info["violations"] = viol
        if np.any(excess > 1.0):
            parts = []
            if excess[0] > 1:
                parts.append(f"position error {1e3 * ep:.2f} mm > {1e3 * tol[0]:.2f} mm")
            if excess[1] > 1:
                parts.append(f"normal error {math.degrees(ang):.3f} deg > {math.degrees(tol[1]):.3f} deg")
            if excess[2] > 1:
                parts.append(f"velocity error {ev:.4f} m/s > {tol[2]:.4f} m/s")
            return "tolerance", "racket state at tau outside tolerance: " + ", ".join(parts), score, info
        if viol:
            i, c, tv, e = max(viol, key=lambda x: x[3])
            what = ("command position", "command velocity", "command acceleration", "predicted position",
                    "predicted velocity")[c]
            return "limits", (
                f"{what} of joint {pl.robot.joint_names[i]!r} exceeds its limit by {100 * e:.3g} % "
                f"of the limit at t = {tv:.3f} s ({len(viol)} violation(s))"
            ), score, info
        zmax = np.max(np.abs(z), axis=1)
        if np.any(zmax > 1.0 + pl.options.limit_tolerance):
            k = int(np.argmax(zmax))
            return "limits", (
                f"command jerk of joint {pl.robot.joint_names[k]!r} exceeds its limit by "
                f"{100 * (zmax[k] - 1):.3g} % of the limit"
            ), score, info
        return "ok", "", score, info

    # ------------------------------------------------------------------ SQP driver
    def near_limit_samples(self, info: dict[str, object], delta: float) -> dict[tuple[int, int, float], float]:
        """Values checked at 1 kHz (sent commands, predicted q, q'; ``info`` of
        :meth:`evaluate_result`) within ``delta`` (fraction of the limit) of a limit or
        beyond: the worst per (joint, component, segment), {(joint, component, time): excess}."""
        t, C, Z = info["t"], info["C"], info["Z"]
        assert isinstance(t, np.ndarray) and isinstance(C, np.ndarray) and isinstance(Z, np.ndarray)
        pl = self.pl
        V = self.check_values(C, Z)
        excess = np.maximum(V - pl._row_hi[None], pl._row_lo[None] - V) / pl._row_scale[None]
        near = np.argwhere(excess > -delta)
        if near.size == 0:
            return {}
        return {(i, c, tv): e for (i, c, _), (tv, e) in self._worst_per_segment(excess, t, near).items()}

    def jerk_ok(self, z: FloatArray) -> bool:
        return bool(np.all(np.abs(z) <= 1.0 + 1e-9))

    def solve_sqp(self, seed: FloatArray | None) -> _Result | None:
        """sqp-daqp: the reduced problem, then (if a limit is broken) the full problem
        with the limit rows of the 1 kHz samples near or beyond a limit (screening),
        adding newly violated samples until none is left (``limit_rounds``)."""
        pl = self.pl
        s, qps, _ = self.solve_reduced(seed)
        N, r0 = self._reduced
        z = self.z_of_s(s, N, r0)
        status, reason, score, info = self.evaluate_result(z)
        if status == "ok" or (status == "tolerance" and not info["violations"] and self.jerk_ok(z)):
            return _Result(status, reason, z, "sqp-daqp", qps, score, info)
        rows: set[tuple[int, int, float]] = set()
        delta = _NEAR
        for _ in range(pl.options.limit_rounds + 1):
            added = set(self.near_limit_samples(info, delta)) - rows
            if not added and rows and self.jerk_ok(z) and not info["violations"]:
                break
            rows |= added
            keys = sorted(rows)
            extra = self.sample_rows(keys) if keys else None
            zn, k, reason2 = self.solve_full(self.s_of_z(z), z, extra)
            qps += k
            if zn is None:
                return _Result("infeasible", reason2, z, "sqp-daqp", qps, math.inf, None)
            z = zn
            status, reason, score, info = self.evaluate_result(z)
            if not info["violations"]:
                break
        return _Result(status, reason, z, "sqp-daqp", qps, score, info)

    # ------------------------------------------------------------------ IPOPT reference
    def solve_ipopt(self, seed_z: FloatArray | None, seed_s: FloatArray | None) -> _Result | None:
        pl, n = self.pl, self.n
        g = self.get_grid()
        solver, sl = pl._ipopt_solver(g.n1)
        # Scaled discrete matrices: Zs = S^-1 Z, j = jmax z.
        S = pl._row_scale  # (8, 5)
        h1, h2 = g.h[0], g.h[-1]
        A, B = chain_transition(pl.dynamics, np.array([h1, h2]))
        As = A * (S[None, :, None, :] / S[None, :, :, None])  # S^-1 A S
        Bs = B * (pl._jmax[None, :, None] / S[None])
        Z0s = g.T[:, 0, :, 0] / S
        tg = self.target
        m = pl.options.margin
        par = np.concatenate([
            As.reshape(-1), Bs.reshape(-1), Z0s.reshape(-1), S.reshape(-1),
            tg.position, tg.normal, tg.velocity,
            [m * self.tol[0], math.cos(m * self.tol[1]), 1.0 - math.cos(m * self.tol[1]), m * self.tol[2]],
            [g.w[0], g.w[-1]], self.cost_slack,
        ])
        # Bounds of x = [Zs (8, n, 5), z (8, n), eps (3)].
        lbZ = np.broadcast_to((pl._row_lo / S)[:, None, :], (8, n, 5)).copy()
        ubZ = np.broadcast_to((pl._row_hi / S)[:, None, :], (8, n, 5)).copy()
        lbZ[:, n - 1, 0] = ubZ[:, n - 1, 0] = self.u_rest / S[:, 0]
        lbZ[:, n - 1, 1:3] = ubZ[:, n - 1, 1:3] = 0.0
        lbx = np.concatenate([lbZ.reshape(-1), -np.ones(8 * n), np.zeros(3)])
        ubx = np.concatenate([ubZ.reshape(-1), np.ones(8 * n), np.full(3, np.inf)])
        # Initial guess.
        if seed_z is None:
            if not hasattr(self, "_reduced"):
                _, N, r0, s_hat = self.reduced_matrices()
                self._reduced = (N, r0)
            N, r0 = self._reduced
            s_init = seed_s if seed_s is not None else self.reduced_matrices()[3]
            seed_z = np.clip(self.z_of_s(s_init, N, r0), -1.0, 1.0)
        Zb = self.boundary_states(seed_z)[1:]  # (n, 8, 5)
        x0 = np.concatenate([(np.transpose(Zb, (1, 0, 2)) / S[:, None, :]).reshape(-1), seed_z.reshape(-1), np.zeros(3)])
        x0 = np.clip(x0, lbx, ubx)
        try:
            sol = solver(x0=x0, p=par, lbx=lbx, ubx=ubx, lbg=sl["lbg"], ubg=sl["ubg"])
        except RuntimeError as exc:  # casadi raises on evaluation errors
            self.fail_reason = f"IPOPT failed: {exc}"
            return None
        stats = solver.stats()
        iters = int(stats.get("iter_count", 0))
        x = np.asarray(sol["x"]).reshape(-1)
        z = x[8 * n * 5: 8 * n * 5 + 8 * n].reshape(8, n)
        rs = stats.get("return_status", "")
        if not stats.get("success", False) and rs not in ("Solved_To_Acceptable_Level",):
            if rs in ("Infeasible_Problem_Detected", "Restoration_Failed"):
                return _Result("infeasible", f"IPOPT: {rs}: the limits cannot be met", z, "ipopt", iters, math.inf)
            self.fail_reason = f"IPOPT: {rs}"
            status, reason, score, info = self.evaluate_result(z)
            if status == "ok":
                status, reason = "failed", f"IPOPT did not converge ({rs})"
            return _Result(status, reason, z, "ipopt", iters, score + 1.0, info)
        status, reason, score, info = self.evaluate_result(z)
        return _Result(status, reason, z, "ipopt", iters, score, info)

    # ------------------------------------------------------------------ output
    def make_plan(self, res: _Result, t0: float) -> Plan:
        g = self.get_grid()
        status, reason, info = res.status, res.reason, res.info
        if info is None:
            return self.empty_plan(status, reason, t0)
        Z, Cm = info["Z"], info["C"]
        assert isinstance(Z, np.ndarray) and isinstance(Cm, np.ndarray)
        jc = 0.5 * float(np.sum(g.w[None, :] * res.z**2))

        def ro(a: FloatArray) -> FloatArray:
            a = np.ascontiguousarray(a)
            a.setflags(write=False)
            return a

        return Plan(
            status=status, reason=reason, target=self.target, start=self.start,
            t=ro(info["t"]), u=ro(Cm[..., 0]), ud=ro(Cm[..., 1]), udd=ro(Cm[..., 2]), q=ro(Z[..., 3]), qd=ro(Z[..., 4]),
            segment_times=ro(g.tb.copy()), n_tau=g.n1, jerk=ro((res.z * self.pl._jmax[:, None]).T),
            q_tau=ro(info["q_tau"]), qd_tau=ro(info["qd_tau"]), position_error=float(info["ep"]),
            angle_error=float(info["ang"]), velocity_error=float(info["ev"]), slacks=ro(info["slacks"]),
            jerk_cost=jc, solver=res.solver, iterations=res.iterations,
            solve_time_ms=1e3 * (time.perf_counter() - t0),
        )


# ======================================================================================
# Whole serve: preparation + toss + strike (+ return to rest)
# ======================================================================================


@dataclass(frozen=True, eq=False)
class ServePlan:
    """One command trajectory at 1 kHz for a whole serve (see :func:`plan_serve`).

    Times on the serve clock: t = 0 at the start of the preparation. Commands follow
    the planner's convention (``u[k]`` held over [t_k, t_k + dt), the underlying
    cubic at the interval midpoint); ``q``, ``qd`` are the predicted joint states at t_k.
    A planned strike ends with the rest command held until the predicted joints are at
    rest (:func:`settle_hold`, ``settle_samples`` samples).
    """

    t: FloatArray
    """Sample times (N,) [s]."""
    u: FloatArray
    """Joint commands (N, 8)."""
    ud: FloatArray
    """Command velocities (N, 8)."""
    udd: FloatArray
    """Command accelerations (N, 8)."""
    q: FloatArray
    """Predicted joint positions (N, 8)."""
    qd: FloatArray
    """Predicted joint velocities (N, 8)."""
    t_toss: float
    """Serve-clock time of the first toss command [s]."""
    t_switch: float
    """Serve-clock time at which the strike takes over [s]."""
    t_contact: float
    """Serve-clock contact time (strike tau) [s]."""
    strike: Plan
    """The strike plan (status, reason, errors at tau, ...)."""
    max_preparation_tilt: float
    """Largest angle [rad] of the racket normal from +Z during the preparation."""
    cup: CupHoldCheck | None = None
    """Ball-in-cup check of preparation + toss up to the release (serve clock)."""
    settle_samples: int = 0
    """Samples of the final hold of the rest command (part of the arrays)."""

    @property
    def ok(self) -> bool:
        """True when the strike plan is valid."""
        return self.strike.ok


def _quintic(q0: FloatArray, q1: FloatArray, T: float, dt: float) -> tuple[FloatArray, ...]:
    """Quintic minimum-jerk rest-to-rest motion q0 -> q1 (8,) of duration T [s] (a multiple
    of dt), sampled at the interval midpoints: (u, ud, udd), each (T / dt, 8)."""
    n = int(round(T / dt))
    s = (np.arange(n) + 0.5) * dt / T
    p = 10 * s**3 - 15 * s**4 + 6 * s**5
    pd = (30 * s**2 - 60 * s**3 + 30 * s**4) / T
    pdd = (60 * s - 180 * s**2 + 120 * s**3) / T**2
    d = (q1 - q0)[None]
    return q0[None] + p[:, None] * d, pd[:, None] * d, pdd[:, None] * d


def _rest_to_rest(q0: FloatArray, q1: FloatArray, limits: JointLimits, dt: float) -> tuple[float, FloatArray, FloatArray, FloatArray]:
    """Quintic minimum-jerk rest-to-rest joint motion, duration chosen from the limits
    (peak |u'| = 1.875 D/T, |u''| = 5.774 D/T^2, |u'''| = 60 D/T^3 for a distance D),
    rounded up to dt. Returns (T, u, ud, udd) sampled at the interval midpoints."""
    D = np.abs(q1 - q0)
    T = float(np.max(np.concatenate([
        1.875 * D / limits.velocity, np.sqrt(5.774 * D / limits.acceleration), np.cbrt(60.0 * D / limits.jerk), [dt],
    ])))
    T = math.ceil(T / dt - 1e-9) * dt
    u, ud, udd = _quintic(q0, q1, T, dt)
    return T, u, ud, udd


MAX_PREPARATION_TIME: Final[float] = 10.0
"""Longest preparation motion tried [s] before giving up on keeping the ball in the cup."""


@dataclass(frozen=True, eq=False)
class PreparationPhase:
    """Feeder pose to the toss's first command, then a hold: the first part of a serve
    (1 kHz, commands at the interval midpoints as :class:`Plan`; states at the samples)."""

    u: FloatArray
    """Commands (P, 8)."""
    ud: FloatArray
    """Command velocities (P, 8)."""
    udd: FloatArray
    """Command accelerations (P, 8)."""
    q: FloatArray
    """Predicted joint positions (P, 8) from rest at the start pose."""
    qd: FloatArray
    """Predicted joint velocities (P, 8)."""
    max_tilt: float
    """Largest racket-normal tilt from vertical over the phase [rad] (the ball rides in the cup)."""
    motion_time: float = 0.0
    """Duration of the quintic [s] (the hold follows)."""
    cup: CupHoldCheck | None = None
    """The ball-in-cup check of the whole phase (motion and hold), on its clock (t = 0 at its start)."""

    @property
    def duration(self) -> float:
        """Length of the phase [s] (the toss starts then)."""
        return self.u.shape[0] * COMMAND_DT


def _held_quintic(robot: Robot, q0: FloatArray, u1: FloatArray, T: float, n_hold: int, dt: float) -> tuple[FloatArray, ...]:
    """Quintic q0 -> u1 of duration T [s], then ``n_hold`` samples holding u1, with the
    predicted states from rest at q0: (u, ud, udd, X (P, 8, 2))."""
    pu, pud, pudd = _quintic(q0, u1, T, dt)
    pu = np.vstack([pu, np.repeat(u1[None], n_hold, axis=0)])
    pud = np.vstack([pud, np.zeros((n_hold, 8))])
    pudd = np.vstack([pudd, np.zeros((n_hold, 8))])
    return pu, pud, pudd, robot.dynamics.simulate(pu, dt, np.stack([q0, np.zeros(8)], axis=1))


def _cup_check(robot: Robot, parts: tuple[FloatArray, ...], dt: float, grip: CupGrip) -> CupHoldCheck:
    """Ball-in-cup check of :func:`_held_quintic`'s output."""
    pu, _, _, X = parts
    return check_cup_hold(robot, np.arange(pu.shape[0]) * dt, pu, X[:, :, 0], X[:, :, 1], grip=grip)


def _cup_safe_duration(
    robot: Robot, q0: FloatArray, u1: FloatArray, T0: float, n_hold: int, dt: float, grip: CupGrip
) -> tuple[float, tuple[FloatArray, ...], CupHoldCheck]:
    """Shortest quintic duration T >= T0 [s] (on the dt grid) whose motion and hold keep
    the ball in the cup: doubling from T0 until the check passes, then bisection down to
    dt. The returned duration is always a checked one (the ratio need not be monotone in
    T, so it is the shortest found, not proven shortest).

    Raises:
        InvalidInputError: not even :data:`MAX_PREPARATION_TIME` keeps the ball in the cup
            (e.g. a start or end pose tilted beyond the cone).
    """
    parts = _held_quintic(robot, q0, u1, T0, n_hold, dt)
    check = _cup_check(robot, parts, dt, grip)
    lo = hi = T0
    while not check.passed:
        if hi >= MAX_PREPARATION_TIME:
            raise InvalidInputError(f"preparation: the ball does not stay in the cup even with a {hi:.2f} s motion ({check.detail})")
        lo, hi = hi, min(math.ceil(2.0 * hi / dt) * dt, MAX_PREPARATION_TIME)
        parts = _held_quintic(robot, q0, u1, hi, n_hold, dt)
        check = _cup_check(robot, parts, dt, grip)
    best = (hi, parts, check)
    while best[0] - lo > 1.5 * dt:
        mid = math.ceil(0.5 * (lo + best[0]) / dt - 1e-9) * dt
        parts = _held_quintic(robot, q0, u1, mid, n_hold, dt)
        check = _cup_check(robot, parts, dt, grip)
        if check.passed:
            best = (mid, parts, check)
        else:
            lo = mid
    return best


def preparation_phase(
    robot: Robot,
    u_toss0: npt.ArrayLike,
    *,
    limits: JointLimits | None = None,
    q_start: npt.ArrayLike | None = None,
    settle: float = 0.3,
    dt: float = COMMAND_DT,
    grip: CupGrip | None = None,
) -> PreparationPhase:
    """The preparation of the paper: from ``q_start`` (default ``robot.q_flat``, the pose
    at the ball feeder) a rest-to-rest quintic to the toss's first command ``u_toss0``
    (8,), then ``settle`` seconds of hold so the joints are at rest when the toss starts
    (its predicted states assume so).

    The ball rides in the cup all along: the quintic is the shortest (on the 1 kHz grid)
    that is within the joint limits *and* keeps the cup's specific force inside the
    holding cone ``grip`` (default: the robot's cup, :class:`studio.robot.cup_hold.CupGrip`) at
    every sample of the motion and the hold; the check is :attr:`PreparationPhase.cup`.

    Raises:
        InvalidInputError: bad inputs, or no duration up to :data:`MAX_PREPARATION_TIME`
            keeps the ball in the cup.
    """
    if not (math.isfinite(settle) and settle >= 0.0):
        raise InvalidInputError(f"preparation: settle must be >= 0 s, got {settle}")
    q0 = _vec(robot.q_flat if q_start is None else q_start, (8,), "preparation q_start")
    u1 = _vec(u_toss0, (8,), "preparation u_toss0")
    T0, *_ = _rest_to_rest(q0, u1, limits if limits is not None else robot.limits, dt)
    grip = grip if grip is not None else CupGrip.of(robot)
    T, (pu, pud, pudd, X), check = _cup_safe_duration(robot, q0, u1, T0, int(round(settle / dt)), dt, grip)
    tilt = [math.acos(float(np.clip(robot.fk(qq).normal[2], -1.0, 1.0))) for qq in X[::10, :, 0]]
    return PreparationPhase(pu, pud, pudd, X[:, :, 0], X[:, :, 1], max(tilt) if tilt else 0.0, T, check)


@dataclass(frozen=True, slots=True)
class SettleTolerance:
    """When the predicted joints count as at rest on the last command (per joint, in the
    joint's unit: gantry [m, m/s], arm [rad, rad/s])."""

    position: float = 1e-4
    """Largest |q - u_end| [m | rad] (0.1 mm, 0.1 mrad)."""
    velocity: float = 1e-3
    """Largest |q'| [m/s | rad/s] (1 mm/s, 1 mrad/s)."""
    horizon: float = 0.2
    """The state must stay within the tolerances this long after the end [s] (the joint
    model is under-damped: zeta 0.85-0.9)."""
    max_hold: float = 3.0
    """Longest hold tried [s]."""

    def __post_init__(self) -> None:
        for name in ("position", "velocity", "horizon", "max_hold"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInputError(f"SettleTolerance.{name} must be finite and > 0, got {v!r}")


SETTLE: Final[SettleTolerance] = SettleTolerance()
"""Default rest tolerances of exported serves."""


def settle_hold(u_end: npt.ArrayLike, X_end: npt.ArrayLike, dynamics: JointDynamics, *, dt: float = COMMAND_DT, tol: SettleTolerance = SETTLE) -> FloatArray:
    """Predicted states (n, 8, 2) at t_end + dt, ..., t_end + n dt of the joints holding the
    command ``u_end`` (8,) that is sent at t_end, from their state ``X_end`` (8, 2) at t_end.

    n is the smallest count such that the last two samples (their velocities, exact and as
    finite differences from the sample before) and every sample over ``tol.horizon`` after
    them are within ``tol``
    (0 if the motion already ends that way).

    Raises:
        InvalidInputError: not settled within ``tol.max_hold``.
    """
    u1 = _vec(u_end, (8,), "settle_hold u_end")
    X0 = _vec(X_end, (8, 2), "settle_hold X_end")
    n_max, n_look = int(math.ceil(tol.max_hold / dt)), int(math.ceil(tol.horizon / dt))
    # exact free response of e = q - u1 under the held command, all samples at once
    times: FloatArray = np.arange(n_max + n_look + 1, dtype=np.float64)[:, None] * dt
    phi = _free_response(dynamics.wn, dynamics.zeta, times)
    S = np.einsum("jnab,nb->jna", phi, np.stack([X0[:, 0] - u1, X0[:, 1]], axis=1))
    S[:, :, 0] += u1
    ok = np.all((np.abs(S[:, :, 0] - u1) <= tol.position) & (np.abs(S[:, :, 1]) <= tol.velocity), axis=1)
    ok[1:] &= np.all(np.abs(np.diff(S[:, :, 0], axis=0)) <= tol.velocity * dt, axis=1)  # as a controller sees it
    bad = np.flatnonzero(~ok[: n_max + n_look])
    if bad.size == 0:
        return S[1:1]
    n = int(bad[-1]) + 2  # after the last bad sample: one good sample, then the end sample
    if n > n_max:
        raise InvalidInputError(f"settle_hold: the joints are not within {tol} after {tol.max_hold} s of hold")
    return S[1 : n + 1]


@dataclass(frozen=True, eq=False)
class ServeArrays:
    """A whole serve on one 1 kHz clock as exported (:mod:`studio.library.store`): preparation
    (if any), toss, strike, return to rest and a final hold of the rest command until the
    predicted joints are at rest (:func:`settle_hold`)."""

    t: FloatArray
    """Sample times (N,) [s], from 0 when a preparation leads (else the motion's clock)."""
    u: FloatArray
    """Commands (N, 8) [m | rad], u[k] sent at t_k and held until t_k+1."""
    q: FloatArray
    """Predicted joint positions at t_k (N, 8) [m | rad]."""
    qd: FloatArray
    """Predicted joint velocities at t_k (N, 8) [m/s | rad/s]."""
    t_toss: float
    """Time of the first toss command [s]."""
    settle_samples: int
    """Samples of the final hold appended after the motion's last command."""


def serve_arrays(
    t: npt.ArrayLike, u: npt.ArrayLike, q: npt.ArrayLike, qd: npt.ArrayLike | None, dynamics: JointDynamics, *,
    preparation: PreparationPhase | None = None, tol: SettleTolerance = SETTLE,
) -> ServeArrays:
    """Assemble the exported arrays of a motion (toss clock: times t (M,) [s] at 1 kHz,
    commands u, predicted q and qd (M, 8); qd None: central differences of q): the
    preparation before it (times shifted so that it starts at 0), then the motion, then
    the hold of its last command until the joints settle (``tol``)."""
    T, U, Q = (np.asarray(a, dtype=float) for a in (t, u, q))
    if T.ndim != 1 or T.size < 2 or U.shape != (T.size, 8) or Q.shape != U.shape:
        raise InvalidInputError(f"serve_arrays: t (M >= 2,), u and q (M, 8) expected, got {T.shape}, {U.shape}, {Q.shape}")
    dt = float(T[1] - T[0])
    QD = np.gradient(Q, T, axis=0) if qd is None else np.asarray(qd, dtype=float)
    tail = settle_hold(U[-1], np.stack([Q[-1], QD[-1]], axis=1), dynamics, dt=dt, tol=tol)
    n = tail.shape[0]
    T = np.concatenate([T, T[-1] + dt * np.arange(1, n + 1)])
    U, Q, QD = np.vstack([U, np.repeat(U[-1:], n, axis=0)]), np.vstack([Q, tail[:, :, 0]]), np.vstack([QD, tail[:, :, 1]])
    if preparation is None:
        return ServeArrays(T, U, Q, QD, float(T[0]), n)
    P = preparation.u.shape[0]
    t_toss = P * dt
    return ServeArrays(
        np.concatenate([np.arange(P) * dt, T - T[0] + t_toss]), np.vstack([preparation.u, U]),
        np.vstack([preparation.q, Q]), np.vstack([preparation.qd, QD]), t_toss, n,
    )  # fmt: skip


def serve_cup_check(robot: Robot, preparation: PreparationPhase, toss: object, *, grip: CupGrip | None = None) -> CupHoldCheck:
    """The ball-in-cup check of preparation + toss on the serve clock (t = 0 at the start of
    the preparation), at every 1 kHz sample before the toss's predicted release from the
    cup (``toss.release.time``, where the normal load vanishes; the ball flies from then on).

    ``toss``: a :class:`studio.toss.model.TossPrimitive` (u, X, release, dt)."""
    dt = float(getattr(toss, "dt"))
    tu, tX = np.asarray(getattr(toss, "u")), np.asarray(getattr(toss, "X"))
    P = preparation.u.shape[0]
    t = np.arange(P + tu.shape[0]) * dt
    u = np.vstack([preparation.u, tu])
    q, qd = np.vstack([preparation.q, tX[:, :, 0]]), np.vstack([preparation.qd, tX[:, :, 1]])
    t_end = P * dt + float(getattr(toss, "release").time)
    return check_cup_hold(robot, t, u, q, qd, t_end=t_end, grip=grip)


def start_from_toss(toss: object, t_switch: float) -> tuple[StrikeStart, int]:
    """Strike start state at the toss sample k at or before ``t_switch`` (toss clock):
    the predicted joint state ``toss.X[k]`` (at t_k) and the command state moved from
    the sample's interval midpoint (the commands' convention, see :class:`Plan`) back
    to t_k with the toss's jerk. Returns (start, k); the strike's first command then
    continues ``toss.u[:k]`` seamlessly."""
    k = int(toss.index_at(t_switch))  # type: ignore[attr-defined]
    tu, tud, tudd, tuddd, tX = (np.asarray(getattr(toss, f)) for f in ("u", "ud", "udd", "uddd", "X"))
    h = 0.5 * float(getattr(toss, "dt", COMMAND_DT))
    u0 = tu[k] - tud[k] * h + tudd[k] * h**2 / 2 - tuddd[k] * h**3 / 6
    ud0 = tud[k] - tudd[k] * h + tuddd[k] * h**2 / 2
    udd0 = tudd[k] - tuddd[k] * h
    return StrikeStart(u=u0, ud=ud0, udd=udd0, X=tX[k]), k


def plan_serve(
    planner: StrikePlanner,
    toss: object,
    target: StrikeTarget,
    *,
    t_switch: float,
    q_start: npt.ArrayLike | None = None,
    settle: float = 0.3,
    warm_start: Plan | None = None,
) -> ServePlan:
    """Plan a whole serve as one 1 kHz command trajectory, continuous up to acceleration:

    1. preparation: rest-to-rest quintic in joint space from ``q_start`` (default: the
       robot's ``q_flat``, e.g. the pose at the ball feeder) to the toss's first command,
       then ``settle`` seconds of hold so the joints are at rest when the toss starts
       (its predicted states assume so), slow enough to keep the ball in the cup
       (:func:`preparation_phase`; ``cup`` checks preparation + toss up to the release);
    2. the toss commands ``toss.u`` up to the switch sample (``toss.index_at(t_switch)``);
    3. the strike from the toss's command and predicted joint state at the switch
       (the command state is moved from the sample's midpoint back to the sample time
       with the toss's jerk), ending at rest at ``target.u_rest`` (return to rest),
       then holding it until the predicted joints are at rest (:func:`settle_hold`).

    Args:
        planner: the strike planner.
        toss: a :class:`studio.toss.model.TossPrimitive` (t, u, ud, udd, uddd, X, dt, index_at).
        target: strike target with tau, tau_f on the *strike* clock (from the switch).
        t_switch: switch time on the toss clock [s].
        q_start: preparation start (8,) (default ``robot.q_flat``).
        settle: hold before the toss [s].
        warm_start: previous strike plan to seed the planner.

    Returns:
        The :class:`ServePlan` (check ``.ok`` / ``.strike.reason``).

    Raises:
        InvalidInputError: bad inputs (non-finite, wrong shapes, switch outside the toss).
    """
    robot = planner.robot
    dt = planner.options.dt
    if abs(getattr(toss, "dt", dt) - dt) > 1e-12:
        raise InvalidInputError(f"plan_serve: toss dt {getattr(toss, 'dt', None)} differs from the planner's {dt}")
    if not (math.isfinite(t_switch) and 0.0 <= t_switch < float(toss.t[-1])):  # type: ignore[attr-defined]
        raise InvalidInputError(f"plan_serve: t_switch = {t_switch} s outside the toss [0, {float(toss.t[-1])}]")  # type: ignore[attr-defined]
    tu, tud, tudd, tX = (np.asarray(getattr(toss, f)) for f in ("u", "ud", "udd", "X"))
    start, k = start_from_toss(toss, t_switch)
    # 1. Preparation and hold.
    prep = preparation_phase(robot, tu[0], limits=planner.limits, q_start=q_start, settle=settle, dt=dt)
    pu, pud, pudd = prep.u, prep.ud, prep.udd
    n_p = pu.shape[0]
    # 3. Strike from the toss state at sample k (command state moved to t_k).
    strike = planner.plan(start, target, warm_start=warm_start)
    t_toss = n_p * dt
    t_sw = t_toss + k * dt
    if strike.u.shape[0] == 0:
        su = sud = sudd = sq = sqd = np.zeros((0, 8))
    else:
        tail = settle_hold(strike.u[-1], np.stack([strike.q[-1], strike.qd[-1]], axis=1), robot.dynamics, dt=dt)
        n_tail = tail.shape[0]
        su = np.vstack([strike.u, np.repeat(strike.u[-1:], n_tail, axis=0)])
        sud, sudd = (np.vstack([a, np.zeros((n_tail, 8))]) for a in (strike.ud, strike.udd))
        sq, sqd = np.vstack([strike.q, tail[:, :, 0]]), np.vstack([strike.qd, tail[:, :, 1]])
    u = np.vstack([pu, tu[:k], su])
    n = u.shape[0]
    return ServePlan(
        t=np.arange(n) * dt,
        u=u,
        ud=np.vstack([pud, tud[:k], sud]),
        udd=np.vstack([pudd, tudd[:k], sudd]),
        q=np.vstack([prep.q, tX[:k, :, 0], sq]),
        qd=np.vstack([prep.qd, tX[:k, :, 1], sqd]),
        t_toss=t_toss,
        t_switch=t_sw,
        t_contact=t_sw + target.tau,
        strike=strike,
        max_preparation_tilt=prep.max_tilt,
        cup=serve_cup_check(robot, prep, toss),
        settle_samples=su.shape[0] - strike.u.shape[0],
    )
