"""The rollout's contact search: the first instant the flying ball touches a geom of the
scene within one flight step (:class:`ContactSearch`).

Broadphase per RK4 step: the ball's box against the court geoms' boxes, and against
bounding spheres of the robot's collision geoms posed with ``mj_kinematics`` at every
command sample. Near a candidate, the narrowphase ``mujoco.mj_geomDistance`` (signed
distance) is evaluated on a grid of ``substep`` spacing, skipping grid points by
conservative advancement (no contact can happen before distance / closing-speed bound);
the first touch is then located by Brent's method on the distance to ``time_tolerance``.

A geom just touched is *disarmed*: it counts again only after the ball has been
``rearm_distance`` away from it, or if the ball sinks ``sink_depth`` into it (pushed
again: a double hit), so one contact is counted once. World frame, SI units.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Final

import mujoco
import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq

from studio.physics.ball import hermite
from studio.sim.options import RolloutOptions
from studio.sim.robot_track import RobotTrack, hermite_rows
from studio.sim.scene import Scene

FloatArray = npt.NDArray[np.float64]

BROAD_MARGIN: Final[float] = 0.005
"""Extra broadphase margin [m]: curvature of ball and robot paths between samples."""

SPEED_SLACK: Final[float] = 0.1
"""Added to speed bounds of the conservative advancement [m/s] (curvature of the paths
within a sample interval)."""

DISTANCE_CUTOFF: Final[float] = 0.05
"""Cut-off of the narrowphase distance queries [m] (farther geoms report this)."""

Step = tuple[float, float, Sequence[float], Sequence[float], Sequence[float], Sequence[float]]
"""A flight step ``(ta, h, y(ta), y'(ta), y(ta + h), y'(ta + h))`` of the 9-state [p, v, w]
(cubic Hermite dense output)."""


def static_boxes(scene: Scene, d: mujoco.MjData) -> tuple[list[int], FloatArray, FloatArray]:
    """World AABBs (S, 3) lo/hi of the court's contact geoms (planes: the half-space below)."""
    m = scene.model
    ids = [int(g) for g in scene.contact_geoms if m.geom_bodyid[g] == 0]
    lo = np.empty((len(ids), 3))
    hi = np.empty((len(ids), 3))
    for i, g in enumerate(ids):
        R = d.geom_xmat[g].reshape(3, 3)
        c = d.geom_xpos[g]
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            lo[i] = -np.inf
            hi[i] = np.inf
            if R[2, 2] > 1.0 - 1e-12:  # horizontal plane, normal +Z: solid below
                hi[i, 2] = c[2]
        else:
            aabb = m.geom_aabb[g]
            cw = c + R @ aabb[:3]
            hw = np.abs(R) @ aabb[3:]
            lo[i] = cw - hw
            hi[i] = cw + hw
    return ids, lo, hi


class ContactSearch:
    """First contact of the ball with a geom of the scene during a flight step.

    State: the court's boxes (computed once from ``data`` as posed at construction), the
    robot track, and the set of disarmed geoms (:meth:`disarm_touching`,
    :meth:`disarm`), which the search re-arms as the ball gets away from them. Uses (and
    overwrites) the robot pose and the ball geom's position in ``data``.
    """

    def __init__(
        self,
        scene: Scene,
        data: mujoco.MjData,
        track: RobotTrack,
        grid: FloatArray,
        t0: float,
        dt: float,
        options: RolloutOptions,
    ) -> None:
        self.scene = scene
        self.m = scene.model
        self.d = data
        self.track = track
        self.grid = grid
        """Command grid (n,) [s]: ``t0 + dt k``."""
        self.t0 = t0
        self.dt = dt
        self.options = options
        self.bg = scene.ball_geom
        self.r = float(self.m.geom_size[self.bg, 0])
        """Ball radius [m]."""
        self.static_ids, self.static_lo, self.static_hi = static_boxes(scene, data)
        self.disarmed: set[int] = set()
        """Geoms that count again only once the ball has left them (or sinks into them)."""

    def disarm_touching(self, t_start: float, p: Sequence[float]) -> None:
        """Disarm the geoms touching the ball at ``p`` (3,) [m] at ``t_start`` [s] (e.g. the
        cup at the release): they count only once the ball has left them."""
        self.track.pose(t_start)
        self.d.geom_xpos[self.bg] = p
        rearm = self.options.rearm_distance
        self.disarmed = {
            int(g)
            for g in self.scene.contact_geoms
            if mujoco.mj_geomDistance(self.m, self.d, self.bg, int(g), DISTANCE_CUTOFF, None) <= rearm
        }

    def disarm(self, g: int) -> None:
        """Disarm geom ``g`` (just touched)."""
        self.disarmed.add(g)

    def first_contact(self, step: Step) -> tuple[float, int] | None:
        """First contact ``(time [s], geom)`` with a geom in ``[ta, ta + h]`` of the flight
        ``step``, or None: broadphase candidates, then the narrowphase on their window."""
        cands, speeds, window, any_robot = self._broadphase(step)
        if self.disarmed:
            for g in [g for g in self.disarmed if g not in cands]:
                self.disarmed.discard(g)  # far from the ball: armed again
        if not cands:
            return None
        w_lo, w_hi = window
        span = w_hi - w_lo
        if span <= 0.0:
            return None
        return self._narrowphase(step, cands, speeds, w_lo, span, any_robot)

    def _broadphase(self, step: Step) -> tuple[list[int], list[float], tuple[float, float], bool]:
        """Candidate geoms, the speed bound of each one's surface [m/s], the time window
        of the fine search [s] and whether a robot geom is among the candidates. Court
        boxes against the ball's box over the step; the robot's geoms by their bounding
        spheres at the grid samples (then the window is the robot's, if no court box)."""
        ta, h, ya, _, yb, _ = step
        tb = ta + h
        pad = self.r + BROAD_MARGIN
        plo = np.minimum(ya[0:3], yb[0:3]) - pad
        phi = np.maximum(ya[0:3], yb[0:3]) + pad
        s_hit = np.all(self.static_lo <= phi, axis=1) & np.all(self.static_hi >= plo, axis=1)
        cands = [self.static_ids[i] for i in np.flatnonzero(s_hit)]
        speeds = [0.0] * len(cands)  # speed bound of each candidate's surface [m/s]
        w_lo, w_hi = ta, tb
        robot = self._robot_broadphase(step, plo, phi)
        if robot is None:
            return cands, speeds, (w_lo, w_hi), False
        geoms, vg, (r_lo, r_hi) = robot
        cands.extend(geoms)
        speeds.extend(vg)
        if not s_hit.any():  # restrict the fine search to the robot's window
            w_lo, w_hi = r_lo, r_hi
        return cands, speeds, (w_lo, w_hi), True

    def _robot_broadphase(
        self, step: Step, plo: FloatArray, phi: FloatArray
    ) -> tuple[list[int], list[float], tuple[float, float]] | None:
        """Robot geoms whose bounding spheres come near the ball over the step (ball box
        ``plo``..``phi``), their surface speed bounds [m/s] and the window [s] of the
        samples where they do; None if none does."""
        ta, h, ya, fa, yb, fb = step
        tb = ta + h
        track, dt, n_total = self.track, self.dt, self.grid.size
        ka = min(max(int(math.floor((ta - self.t0) / dt)), 0), n_total - 1)
        kb = min(int(math.ceil((tb - self.t0) / dt)), n_total - 1)
        track.ensure(kb)
        if not (
            np.all(np.min(track.lo[ka : kb + 1], axis=0) <= phi)
            and np.all(np.max(track.hi[ka : kb + 1], axis=0) >= plo)
        ):
            return None
        ks = np.arange(ka, kb + 1)
        ts = self.grid[ks]
        K = ks.size
        th = np.clip((ts - ta) / h, 0.0, 1.0) if h > 0.0 else np.zeros(K)
        ones = np.ones((K, 1))
        P = hermite_rows(th, np.full(K, h), ones * ya[0:3], ones * fa[0:3], ones * yb[0:3], ones * fb[0:3])
        Cg = track.centers[ka : kb + 1]
        gap = np.linalg.norm(P[:, None, :] - Cg, axis=2) - track.rb[None, :] - self.r
        if K > 1:
            dP = float(np.max(np.linalg.norm(np.diff(P, axis=0), axis=1)))
            dC = np.max(np.linalg.norm(np.diff(Cg, axis=0), axis=2), axis=0)
        else:
            dP, dC = 0.0, np.zeros(Cg.shape[1])
        near = gap <= (dP + dC + BROAD_MARGIN)[None, :]
        gsel = np.flatnonzero(np.any(near, axis=0))
        if not gsel.size:
            return None
        # surface speed bound: centre chord speed (+ slack for its curvature)
        # + angular speed bound (sum of the chain's hinge speeds) x bounding radius
        omega = np.max(np.abs(track.QD[ka : kb + 1]) @ track.hinge_chain[gsel].T, axis=0)
        vg = dC[gsel] / dt + SPEED_SLACK + omega * track.rb[gsel]
        rows = np.flatnonzero(np.any(near, axis=1))
        window = (max(ta, float(ts[rows[0]]) - dt), min(tb, float(ts[rows[-1]]) + dt))
        return [int(g) for g in track.geoms[gsel]], [float(x) for x in vg], window

    def _narrowphase(
        self, step: Step, cands: list[int], speeds: list[float], w_lo: float, span: float, any_robot: bool
    ) -> tuple[float, int] | None:
        """Signed distances to the candidates on a grid of ``substep`` spacing over
        ``[w_lo, w_lo + span]``, skipping points by conservative advancement; the first
        crossing is refined by :meth:`_refine`."""
        ta, h, ya, fa, yb, fb = step
        n_sub = max(1, math.ceil(span / self.options.substep - 1e-9))
        h_sub = span / n_sub
        taus = w_lo + h_sub * np.arange(n_sub + 1, dtype=np.float64)
        th = (taus - ta) / h if h > 0.0 else np.zeros(n_sub + 1)
        ones = np.ones((n_sub + 1, 1))
        Pb = hermite_rows(th, np.full(n_sub + 1, h), ones * ya[0:3], ones * fa[0:3], ones * yb[0:3], ones * fb[0:3])
        Qs = self.track.q_batch(taus) if any_robot else None
        v_ball = math.sqrt(max(ya[3] ** 2 + ya[4] ** 2 + ya[5] ** 2, yb[3] ** 2 + yb[4] ** 2 + yb[5] ** 2))
        a_ball = math.sqrt(max(fa[3] ** 2 + fa[4] ** 2 + fa[5] ** 2, fb[3] ** 2 + fb[4] ** 2 + fb[5] ** 2))
        v_ball += a_ball * h + SPEED_SLACK
        closing = [v_ball + vg for vg in speeds]
        prev = None
        i = 0
        while i <= n_sub:
            tau = float(taus[i])
            if Qs is not None:
                self.track.set_pose(Qs[i])
            self.d.geom_xpos[self.bg] = Pb[i]
            crossing, safe = self._crossings(cands, closing)
            if crossing:
                if prev is None:
                    return tau, crossing[0][0]
                return self._refine(step, crossing, prev, tau)
            prev = tau
            i += max(1, int(safe / h_sub)) if safe < math.inf else n_sub + 1
        return None

    def _crossings(self, cands: list[int], closing: list[float]) -> tuple[list[tuple[int, float]], float]:
        """At the current pose: the candidates touched ``(geom, level)`` (level 0, or
        ``-sink_depth`` for a disarmed geom still touching: only a new push counts; geoms
        the ball has left are re-armed) and the time [s] no other one can be touched
        before (distance over closing speed)."""
        rearm, sink = self.options.rearm_distance, self.options.sink_depth
        crossing: list[tuple[int, float]] = []
        safe = math.inf
        for j, g in enumerate(cands):
            dist = mujoco.mj_geomDistance(self.m, self.d, self.bg, g, DISTANCE_CUTOFF, None)
            level = 0.0
            if g in self.disarmed:
                if dist > rearm:
                    self.disarmed.discard(g)
                else:
                    level = -sink  # touching since the last contact: only a new push counts
            if dist <= level:
                crossing.append((g, level))
            else:
                safe = min(safe, (dist - level) / closing[j])
        return crossing, safe

    def _refine(
        self, step: Step, crossing: list[tuple[int, float]], prev: float, tau: float
    ) -> tuple[float, int] | None:
        """The earliest touch among the ``crossing`` geoms in ``[prev, tau]`` [s], by
        Brent's method on the distance (robot posed and ball placed at each trial time)."""
        ta, h, ya, fa, yb, fb = step
        m, d, bg, geom_body = self.m, self.d, self.bg, self.m.geom_bodyid
        best: tuple[float, int] | None = None
        for g, level in crossing:
            robot_g = bool(geom_body[g] != 0)

            def gap_at(s: float, g: int = g, robot_g: bool = robot_g, level: float = level) -> float:
                if robot_g:
                    self.track.pose(s)
                d.geom_xpos[bg] = hermite((s - ta) / h if h > 0.0 else 0.0, h, ya, fa, yb, fb, 3)
                return mujoco.mj_geomDistance(m, d, bg, g, DISTANCE_CUTOFF, None) - level  # type: ignore[no-any-return]

            if gap_at(prev) <= 0.0:
                tc = prev
            else:
                tc = float(brentq(gap_at, prev, tau, xtol=self.options.time_tolerance, rtol=1e-15))
            if best is None or tc < best[0]:
                best = (tc, g)
        return best
