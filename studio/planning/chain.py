"""Exact discretization of the command/joint chain of one joint, Z = [u, u', u'', q, q'],
driven by a piecewise-constant command jerk (robot model q'' = wn^2 (u - q) - 2 zeta wn q').

Closed-form transition matrices (:func:`chain_transition`), the polynomial particular
solution of the joint model and its free response (per damping regime), and a cached
table of the free response on the 1 kHz output grid (:class:`FreeResponseTable`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from studio.robot.model import JointDynamics

FloatArray = npt.NDArray[np.float64]


def chain_transition(dynamics: JointDynamics, delta: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Closed-form exact transition of the chain Z = [u, u', u'', q, q'] under a jerk
    held constant for ``delta`` seconds (same result as ``dynamics.jerk_chain(delta)``,
    vectorised and much faster: ``docs/planner.md#planner-benchmark``).

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
    phi = free_response(wn, zeta, d)
    c1, c3, c4 = particular_coefficients(wn, zeta)
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


def particular_coefficients(wn: FloatArray, zeta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    c1 = 2.0 * zeta / wn
    c2 = 1.0 / wn**2
    return c1, c1**2 - c2, 2.0 * c1 * c2 - c1**3


def free_response(wn: FloatArray, zeta: FloatArray, d: FloatArray) -> FloatArray:
    """Transition (..., n, 2, 2) of e'' + 2 zeta wn e' + wn^2 e = 0 over d (..., 1) [s]
    (closed form per damping regime: under-, over- or critically damped)."""
    a = zeta * wn
    es, ec = free_response_terms(wn, zeta, d)
    phi = np.empty(es.shape + (2, 2))
    phi[..., 0, 0] = ec + a * es
    phi[..., 0, 1] = es
    phi[..., 1, 0] = -(wn**2) * es
    phi[..., 1, 1] = ec - a * es
    return phi


def free_response_terms(wn: FloatArray, zeta: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
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


class FreeResponseTable:
    """``exp(lam j dt)``, ``j = 0, 1, ...``, ``lam = -zeta wn + i wd`` per joint: the free
    response of under-damped joints on the output grid, grown on demand (real and
    imaginary parts as real arrays: numpy's complex product is several times slower,
    ``docs/planner.md#planner-benchmark``)."""

    def __init__(self, dynamics: JointDynamics, dt: float) -> None:
        self.dt = dt
        """Grid step [s]."""
        self.under = bool(np.all(dynamics.zeta < 1.0 - 1e-6))
        """Every joint under-damped (the table applies)."""
        self.lam = -dynamics.zeta * dynamics.wn + 1j * dynamics.wn * np.sqrt(np.abs(1.0 - dynamics.zeta**2))
        """Complex exponents (8,) [1/s]."""
        self._re, self._im = np.ones((1, 8)), np.zeros((1, 8))

    def steps(self, count: int) -> tuple[FloatArray, FloatArray]:
        """Real and imaginary parts of exp(lam j dt) (>= count, 8), j = 0..count-1 (cached,
        grown on demand)."""
        if len(self._re) < count:
            j = np.arange(max(count, 2 * len(self._re)))[:, None]
            e = np.exp(self.lam[None, :] * (j * self.dt))
            self._re, self._im = np.ascontiguousarray(e.real), np.ascontiguousarray(e.imag)
        return self._re, self._im
