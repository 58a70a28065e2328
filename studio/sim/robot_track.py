"""The predicted robot motion of a rollout on the command grid, posed in MuJoCo batch by
batch (:class:`RobotTrack`), and the vectorised cubic Hermite interpolation
(:func:`hermite_rows`) of robot and ball paths. World frame, SI units."""

from __future__ import annotations

import math
from typing import Final

import mujoco
import numpy as np
import numpy.typing as npt

from studio.sim.scene import Scene

FloatArray = npt.NDArray[np.float64]

CHUNK: Final[int] = 128
"""Robot samples posed per batch (the robot is posed lazily, as far as the ball flies)."""


def hermite_rows(
    theta: FloatArray, h: FloatArray, ya: FloatArray, fa: FloatArray, yb: FloatArray, fb: FloatArray
) -> FloatArray:
    """Vectorized cubic Hermite: theta, h (K,), the rest (K, n) -> (K, n)."""
    th = theta[:, None]
    t2 = th * th
    t3 = t2 * th
    hh = h[:, None]
    return (2 * t3 - 3 * t2 + 1) * ya + (t3 - 2 * t2 + th) * hh * fa + (-2 * t3 + 3 * t2) * yb + (t3 - t2) * hh * fb


class RobotTrack:
    """The predicted robot motion on the command grid, posed in MuJoCo batch by batch.

    Per sample: centres of the robot's contact geoms, the union box of their bounding
    spheres, the cup site and the racket orientation. Between samples the joints are
    cubic-Hermite interpolated from the predicted positions and velocities.
    """

    def __init__(self, scene: Scene, data: mujoco.MjData, t0: float, dt: float, Q: FloatArray, QD: FloatArray) -> None:
        m = scene.model
        self.scene = scene
        self.m = m
        self.d = data
        self.t0 = t0
        self.dt = dt
        self.Q = Q
        self.QD = QD
        self.n = Q.shape[0]
        self.geoms = np.array([g for g in scene.contact_geoms if m.geom_bodyid[g] != 0], dtype=np.intp)
        self.rb = np.array(m.geom_rbound[self.geoms], dtype=float)
        # hinge_chain[i, j]: robot joint j is a hinge that moves geom i (its angular speed
        # bound is the sum of these joints' speeds)
        self.hinge_chain = np.zeros((self.geoms.size, scene.robot_dof.size))
        dof_index = {int(a): j for j, a in enumerate(scene.robot_dof)}
        for i, g in enumerate(self.geoms):
            b = int(m.geom_bodyid[g])
            while b > 0:
                for jnt in range(int(m.body_jntadr[b]), int(m.body_jntadr[b] + m.body_jntnum[b])):
                    if int(m.jnt_type[jnt]) == int(mujoco.mjtJoint.mjJNT_HINGE):
                        j = dof_index.get(int(m.jnt_dofadr[jnt]))
                        if j is not None:
                            self.hinge_chain[i, j] = 1.0
                b = int(m.body_parentid[b])
        G = self.geoms.size
        self.centers = np.empty((self.n, G, 3))
        self.lo = np.empty((self.n, 3))
        self.hi = np.empty((self.n, 3))
        self.cup = np.empty((self.n, 3))
        self.R = np.empty((self.n, 3, 3))
        self._gx = np.empty((self.n, m.ngeom, 3))
        self._sx = np.empty((self.n, m.nsite, 3))
        self._xm = np.empty((self.n, 9))
        self.done = 0
        adr = scene.robot_qpos
        self.qslice = slice(int(adr[0]), int(adr[0]) + adr.size) if np.all(np.diff(adr) == 1) else None
        self.qadr = adr
        self.dof = scene.robot_dof

    def _set_q(self, q: FloatArray) -> None:
        if self.qslice is not None:
            self.d.qpos[self.qslice] = q
        else:
            self.d.qpos[self.qadr] = q

    def ensure(self, k: int) -> None:
        """Pose samples up to index ``k`` (inclusive)."""
        k = min(k, self.n - 1)
        if k < self.done:
            return
        m, d = self.m, self.d
        start = self.done
        stop = min(self.n, max(k + 1, start + CHUNK))
        gx, sx, xm = d.geom_xpos, d.site_xpos, d.xmat
        GX, SX, XM = self._gx, self._sx, self._xm
        qv = d.qpos[self.qslice] if self.qslice is not None else None
        racket = self.scene.racket_body
        for i in range(start, stop):
            if qv is not None:
                qv[:] = self.Q[i]
            else:
                d.qpos[self.qadr] = self.Q[i]
            mujoco.mj_kinematics(m, d)
            GX[i] = gx
            SX[i] = sx
            XM[i] = xm[racket]
        c = GX[start:stop][:, self.geoms]
        self.centers[start:stop] = c
        self.cup[start:stop] = SX[start:stop, self.scene.cup_site]
        self.R[start:stop] = XM[start:stop].reshape(-1, 3, 3)
        self.lo[start:stop] = np.min(c - self.rb[None, :, None], axis=1)
        self.hi[start:stop] = np.max(c + self.rb[None, :, None], axis=1)
        self.done = stop

    def _interp(self, tau: float) -> tuple[int, float]:
        x = (tau - self.t0) / self.dt
        k = min(max(int(math.floor(x)), 0), self.n - 2)
        return k, min(max(x - k, 0.0), 1.0)

    def q_at(self, tau: float) -> tuple[FloatArray, FloatArray]:
        """Joint positions and velocities (8,) at time ``tau`` (Hermite interpolation)."""
        k, th = self._interp(tau)
        h = self.dt
        qa, qb, va, vb = self.Q[k], self.Q[k + 1], self.QD[k], self.QD[k + 1]
        t2 = th * th
        t3 = t2 * th
        q = (2 * t3 - 3 * t2 + 1) * qa + (t3 - 2 * t2 + th) * h * va + (-2 * t3 + 3 * t2) * qb + (t3 - t2) * h * vb
        qd = (
            ((6 * t2 - 6 * th) * qa + (-6 * t2 + 6 * th) * qb) / h + (3 * t2 - 4 * th + 1) * va + (3 * t2 - 2 * th) * vb
        )
        return q, qd

    def q_batch(self, taus: FloatArray) -> FloatArray:
        """Joint positions (K, 8) at times ``taus`` (K,) (Hermite interpolation)."""
        x = (taus - self.t0) / self.dt
        k = np.clip(np.floor(x).astype(np.intp), 0, self.n - 2)
        th = np.clip(x - k, 0.0, 1.0)
        return hermite_rows(th, np.full(k.size, self.dt), self.Q[k], self.QD[k], self.Q[k + 1], self.QD[k + 1])

    def set_pose(self, q: FloatArray) -> None:
        """Pose the robot in ``data`` at joint positions ``q`` (8,) (mj_kinematics)."""
        self._set_q(q)
        mujoco.mj_kinematics(self.m, self.d)

    def pose(self, tau: float) -> None:
        """Pose the robot in ``data`` at time ``tau`` (mj_kinematics)."""
        q, _ = self.q_at(tau)
        self._set_q(q)
        mujoco.mj_kinematics(self.m, self.d)

    def point_velocity(self, tau: float, body: int, point: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Velocity [m/s] of the body-fixed ``point`` (3,) and the body's angular velocity
        [rad/s] at time ``tau`` (robot posed at ``tau``; point Jacobian of MuJoCo)."""
        _, qd = self.q_at(tau)
        self.pose(tau)
        mujoco.mj_comPos(self.m, self.d)
        jacp = np.zeros((3, self.m.nv))
        jacr = np.zeros((3, self.m.nv))
        mujoco.mj_jac(self.m, self.d, jacp, jacr, point, body)
        return jacp[:, self.dof] @ qd, jacr[:, self.dof] @ qd
