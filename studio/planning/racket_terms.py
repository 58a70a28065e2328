"""Fast evaluation of the racket terms at tau: position, face normal and velocity of the
racket and their Jacobians in (q, qd), and the Hessian of a weighted sum of them
(:class:`RacketTerms`), from compiled casadi functions writing into fixed numpy buffers.

World frame, SI units; joint order of :mod:`studio.robot.model`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, cast

import casadi as ca
import numpy as np
import numpy.typing as npt

from studio.planning.kinematics_casadi import CasadiKinematics

FloatArray = npt.NDArray[np.float64]


class _Buffer(Protocol):
    """A ``casadi.FunctionBuffer`` as its Python binding is called: the binding reads the
    size from the buffer, so ``set_arg(i, a)`` / ``set_res(i, a)`` take no ``size`` (the
    casadi stub lists the C++ signature ``(i, a, size)``)."""

    def set_arg(self, i: int, a: memoryview, /) -> None: ...

    def set_res(self, i: int, a: memoryview, /) -> None: ...


def _buffer(fn: ca.Function) -> tuple[_Buffer, Callable[[], None]]:
    """``fn.buffer()``: the buffer to bind the numpy arrays to, and the evaluation trigger."""
    buf, trigger = fn.buffer()
    return cast(_Buffer, buf), trigger  # the stub's FunctionBuffer wants a size argument (see _Buffer)


class RacketTerms:
    """The racket's p, n, v (3 each) and Jacobians ``jp, jn, jvq, jvqd`` (3, 8) at
    (q, qd), and the Hessian (16, 16) of ``w . [p, n, v]`` in (q, qd) for the SQP's
    Lagrangian Hessian. Not thread-safe (shared buffers)."""

    def __init__(self, kin: CasadiKinematics) -> None:
        q = ca.SX.sym("q", 8)
        qd = ca.SX.sym("qd", 8)
        out = kin.strike_terms(q, qd)
        flat = ca.vertcat(*[ca.vec(ca.densify(o)) for o in out])
        self._terms_fn = ca.Function("terms_flat", [ca.vertcat(q, qd)], [flat], {"cse": True})
        self._terms_in = np.zeros(16)
        self._terms_out = np.zeros(9 + 4 * 24)
        # arr.data is memoryview(arr) (numpy's stubs give ndarray the buffer protocol on Python >= 3.12 only)
        buf, self._terms_trigger = _buffer(self._terms_fn)
        buf.set_arg(0, self._terms_in.data)
        buf.set_res(0, self._terms_out.data)
        self._terms_buf = buf  # keep alive
        w = ca.SX.sym("w", 9)
        xs = ca.vertcat(q, qd)
        lag = ca.dot(w[0:3], out[0]) + ca.dot(w[3:6], out[1]) + ca.dot(w[6:9], out[2])
        hess = ca.densify(ca.hessian(lag, xs)[0])
        self._hess_fn = ca.Function("lag_hess", [xs, w], [ca.vec(hess)], {"cse": True})
        self._hess_in = np.zeros(16)
        self._hess_w = np.zeros(9)
        self._hess_out = np.zeros(256)
        hbuf, self._hess_trigger = _buffer(self._hess_fn)
        hbuf.set_arg(0, self._hess_in.data)
        hbuf.set_arg(1, self._hess_w.data)
        hbuf.set_res(0, self._hess_out.data)
        self._hess_buf = hbuf  # keep alive

    def flat(self, s: FloatArray) -> FloatArray:
        """The raw output (105,) at s = (q, qd) (16,): p, n, v, then the Jacobians jp, jn,
        jvq, jvqd as column-major (3, 8) blocks. The buffer itself: valid until the next call."""
        self._terms_in[:] = s
        self._terms_trigger()
        return self._terms_out

    def terms(self, q: FloatArray, qd: FloatArray) -> tuple[FloatArray, ...]:
        """(p, n, v, jp, jn, jvq, jvqd) at (q, qd), copies."""
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

    def lag_hessian(self, s: FloatArray, w: FloatArray) -> FloatArray:
        """Hessian (16, 16) of w . [p, n, v](q, qd) at s = (q, qd)."""
        self._hess_in[:] = s
        self._hess_w[:] = w
        self._hess_trigger()
        return self._hess_out.reshape(16, 16).copy()
