"""Collision check of robot motions against the robot itself and the court (coal).

The paper verifies collision safety of every motion plan "by running the motion plan
through a custom collision detector based on Coal". This module does the same:

* robot geometry: the URDF's collision elements, loaded by pinocchio
  (``buildGeomFromUrdf(..., COLLISION)``, coal shapes: boxes and cylinders);
* environment: the table top, net and net posts (:meth:`studio.physics.court.Court.boxes`), the
  table legs (:meth:`~studio.physics.court.Court.legs`) as coal boxes and the floor as a coal
  half-space, all fixed in the world frame (``DESIGN.md``: origin at the centre of
  the playing surface, +Z up, floor at z = -0.76 m);
* pairs: every robot geometry against every environment geometry, and robot
  geometries against each other except (a) geometries of the same link or of two
  links joined by one joint (adjacent links touch by construction), (b) static parts
  (the gantry rails) against the environment, (c) pairs that are in contact in both
  named poses ``q_rest`` and ``q_flat`` (permanent contacts of the model, listed in
  :attr:`CollisionChecker.ignored_pairs`).

Sampling: a trajectory is checked at its samples (1 kHz for plans). At 1 kHz and racket
speeds up to 10 m/s a point moves at most 1 cm between samples, less than the thinnest
obstacle plus the racket (4 mm net + 14 mm blade), so a contact cannot be stepped over
(it may be reported up to 1 ms late). ``stride`` > 1 checks every stride-th sample only
(faster, weaker guarantee).

Two ways to find the first colliding sample, with the same result:

* default, conservative advancement: each pair's coal distance d at a sample certifies
  the following samples for which a bound on how much the pair can have approached
  (joint steps |dq| times lever arms of the geometry about the joints between the two
  bodies, :meth:`CollisionChecker._motion_bounds`) stays below d - 0.1 mm; the pair is
  measured again at the first sample not certified, and checked with coal's collision
  test when closer than 0.1 mm. A vectorised pre-filter first bounds every pair's
  distance from its bounding volumes (below) once per window of 32 checked samples, minus the
  motion bound over the window; a pair is measured only inside windows where that lower
  bound reaches the margin. A strike then needs a small fraction of the coal distance
  queries conservative advancement alone would make, instead of collision tests at every
  sample (figures: ``docs/planner.md#the-strike-planner``, ``docs/measured.md``).
* ``exhaustive=True``: broad phase vectorised over all samples with numpy (batched
  forward kinematics of the joint frames): one bounding sphere per link, then per
  geometry its bounding sphere (or oriented box for boxes such as the gantry beam);
  (sample, pair) candidates are the overlapping robot/robot volumes and the robot
  volumes reaching a court box or the floor; coal checks the candidates of every sample.

Collision requests compute contacts: with pinocchio's default requests coal 3.0.3
missed shallow cylinder overlaps (6 of 2130 penetrating pairs in 2000 random poses).
pinocchio's own broad-phase managers were tried and rejected: they skipped the
forearm/flange pair (link_4/link_6) in 112 of 1500 random poses where it collides.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Any

import coal
import numpy as np
import numpy.typing as npt
import pinocchio as pin

from studio.errors import InvalidInputError, RobotModelError
from studio.physics.court import DEFAULT_COURT, Box, Court
from studio.robot.model import Robot

FloatArray = npt.NDArray[np.float64]

_DISTANCE_MARGIN = 1e-4
"""Distance [m] below which conservative advancement stops skipping a pair and asks coal's
collision test at every sample: covers the tolerance of coal's GJK distance (~1e-6 m) and
rounding with a wide margin (engineering choice)."""

_HOT_WINDOW = 32
"""Samples per window of the bounding-volume pre-filter of conservative advancement.
Shorter windows leave fewer coal queries but cost more numpy work in the pre-filter (its
cost grows with the number of windows); 32 was the fastest in total on the example strikes
of ``benchmarks/collision.py`` (figures: ``docs/planner.md#the-strike-planner``)."""


@dataclass(frozen=True, slots=True)
class CollisionReport:
    """Result of :meth:`CollisionChecker.check`."""

    collides: bool
    """True if some sample of the motion is in collision."""
    time: float | None
    """Time [s] of the first colliding sample (None if collision-free)."""
    index: int | None
    """Index of the first colliding sample (None if collision-free)."""
    pairs: tuple[tuple[str, str], ...]
    """Colliding (geometry, geometry) names at the first colliding sample; robot
    geometries are named ``<link>_<k>``, court ones as in :mod:`studio.physics.court`."""
    samples_checked: int
    """How many samples were checked."""

    def describe(self) -> str:
        """One-line human-readable summary."""
        if not self.collides:
            return f"collision-free ({self.samples_checked} samples checked)"
        pairs = ", ".join(f"{a} / {b}" for a, b in self.pairs)
        return f"collision at t = {self.time:.3f} s (sample {self.index}): {pairs}"


class CollisionChecker:
    """Coal collision checker of the serve robot in the court.

    Not thread-safe (one pinocchio/coal data set): use one checker per thread.
    """

    def __init__(
        self,
        robot: Robot,
        *,
        court: Court = DEFAULT_COURT,
        floor: bool = True,
        stride: int = 1,
        window: int = _HOT_WINDOW,
    ) -> None:
        """Build the geometry model.

        Args:
            robot: the robot (its URDF provides the collision geometry).
            court: court geometry (table, net, posts, legs, extras).
            floor: add the floor half-space (z = court.floor_z).
            stride: check every stride-th sample (>= 1; the last sample is always checked).
            window: checked samples per window of the conservative advancement's
                bounding-volume pre-filter (>= 1; a tuning knob: the result does not
                depend on it, see :data:`_HOT_WINDOW`).

        Raises:
            RobotModelError: the URDF's collision geometry cannot be loaded.
            InvalidInputError: bad stride or window.
        """
        for name, val in (("stride", stride), ("window", window)):
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 1:
                raise InvalidInputError(f"CollisionChecker: {name} must be an integer >= 1, got {val!r}")
        self.robot = robot
        self.stride = int(stride)
        self.window = int(window)
        """Checked samples per window of the conservative advancement's pre-filter (:meth:`_check_advancing`)."""
        model = robot.model
        try:
            gm = pin.buildGeomFromUrdf(model, str(robot.urdf_path), pin.GeometryType.COLLISION)
        except Exception as exc:  # pinocchio raises ValueError/RuntimeError
            raise RobotModelError(f"{robot.urdf_path}: cannot load the collision geometry: {exc}") from exc
        n_robot = gm.ngeoms
        env: list[tuple[str, coal.CollisionGeometry, pin.SE3]] = []
        for box in (*court.boxes(), *court.legs()):
            env.append((box.name, coal.Box(*(2.0 * np.asarray(box.half_size))), _box_placement(box)))
        if floor:
            env.append(("floor", coal.Halfspace(np.array([0.0, 0.0, 1.0]), court.floor_z), pin.SE3.Identity()))
        for name, geom, placement in env:
            gm.addGeometryObject(pin.GeometryObject(name, 0, placement, geom))
        self.geom_model = gm
        self.names = tuple(g.name for g in gm.geometryObjects)
        self._env = set(range(n_robot, gm.ngeoms))
        joints = [int(g.parentJoint) for g in gm.geometryObjects]
        parents = [int(p) for p in model.parents]

        def adjacent(a: int, b: int) -> bool:
            return a == b or parents[a] == b or parents[b] == a

        candidates: list[tuple[int, int]] = []
        for i in range(gm.ngeoms):
            for j in range(i + 1, gm.ngeoms):
                ja, jb = joints[i], joints[j]
                if ja == 0 and jb == 0:
                    continue  # static against static (rails, court, floor)
                if i < n_robot and j < n_robot and adjacent(ja, jb):
                    continue
                candidates.append((i, j))
        for i, j in candidates:
            gm.addCollisionPair(pin.CollisionPair(i, j))
        self.data = model.createData()
        self.geom_data = _geometry_data(gm)
        # Permanent contacts of the model: robot pairs touching in both named poses.
        touching = [set(self._colliding_pairs(q)) for q in (robot.q_rest, robot.q_flat)]
        permanent = {p for p in touching[0] & touching[1] if p[0] < n_robot and p[1] < n_robot}
        if permanent:
            for i, j in sorted(permanent):
                gm.removeCollisionPair(pin.CollisionPair(i, j))
            self.geom_data = _geometry_data(gm)
        self.ignored_pairs: tuple[tuple[str, str], ...] = tuple(
            (self.names[i], self.names[j]) for i, j in sorted(permanent)
        )
        self._pairs = [(int(cp.first), int(cp.second)) for cp in gm.collisionPairs]
        self._build_broad_phase(court if floor else None, n_robot, env)

    def _build_broad_phase(self, court: Court | None, n_robot: int, env: list[tuple[str, Any, pin.SE3]]) -> None:
        """Bounding volumes of the robot geometries (spheres, oriented boxes, one sphere
        per link) and the court's axis-aligned boxes, for :meth:`_candidates`."""
        gm, model = self.geom_model, self.robot.model
        self._fk = _BatchJointFK(model)
        radii, halves, joints, local_p, local_R = [], [], [], [], []
        for k in range(n_robot):
            g = gm.geometryObjects[k]
            geom = g.geometry
            geom.computeLocalAABB()
            local_p.append(g.placement.act(np.asarray(geom.aabb_center, dtype=float)))
            local_R.append(np.asarray(g.placement.rotation))
            joints.append(int(g.parentJoint))
            radii.append(float(geom.aabb_radius))
            halves.append(np.asarray(geom.halfSide, dtype=float) if isinstance(geom, coal.Box) else np.full(3, np.nan))
        self._g_joint = np.array(joints, dtype=int)
        self._g_p = np.array(local_p)
        self._g_R = np.array(local_R)
        self._n_robot = n_robot
        self._radii = np.array(radii)
        self._halves = np.array(halves)
        robot_pairs = [(k, (i, j)) for k, (i, j) in enumerate(self._pairs) if j < n_robot]
        self._rr_index = np.array([k for k, _ in robot_pairs], dtype=int)
        rr = np.array([p for _, p in robot_pairs], dtype=int).reshape(-1, 2)
        # Put the box with the larger bounding sphere second: it is tested as an oriented
        # box against the first geometry's sphere (long gantry beams have huge spheres).
        is_box = ~np.isnan(self._halves[:, 0])
        swap = is_box[rr[:, 0]] & (~is_box[rr[:, 1]] | (self._radii[rr[:, 0]] > self._radii[rr[:, 1]]))
        rr[swap] = rr[swap][:, ::-1]
        self._rr = rr
        self._rr_box = is_box[rr[:, 1]]
        # Environment boxes (axis-aligned) and the floor, with the pair index per robot geometry.
        pair_id = {p: k for k, p in enumerate(self._pairs)}
        boxes_lo, boxes_hi, box_pairs = [], [], []
        self._floor_pairs: FloatArray | None = None
        for e_idx, (name, geom, placement) in enumerate(env):
            gi = n_robot + e_idx
            ids = np.array([pair_id.get((k, gi), -1) for k in range(n_robot)], dtype=int)
            if name == "floor":
                self._floor_pairs = ids
                self._floor_z = court.floor_z if court is not None else -math.inf
                continue
            half = np.asarray(geom.halfSide, dtype=float)
            ctr = np.asarray(placement.translation, dtype=float)
            boxes_lo.append(ctr - half)
            boxes_hi.append(ctr + half)
            box_pairs.append(ids)
        self._box_lo = np.array(boxes_lo).reshape(-1, 3)
        self._box_hi = np.array(boxes_hi).reshape(-1, 3)
        self._box_pairs = np.array(box_pairs, dtype=int).reshape(-1, n_robot)
        # First level: one sphere per joint (moving link) enclosing its geometries.
        self._joints = sorted(set(self._g_joint.tolist()))
        jc, jr = [], []
        for j in self._joints:
            ks = np.flatnonzero(self._g_joint == j)
            c = self._g_p[ks].mean(axis=0)
            jc.append(c)
            jr.append(float(np.max(np.linalg.norm(self._g_p[ks] - c, axis=1) + self._radii[ks])))
        self._j_c = np.array(jc)
        self._j_r = np.array(jr)
        jpos = {j: i for i, j in enumerate(self._joints)}
        self._g_jpos = np.array([jpos[j] for j in self._g_joint.tolist()], dtype=int)
        self._build_motion_tables(model, {n_robot + e for e, (name, _, _) in enumerate(env) if name == "floor"})
        groups: dict[tuple[int, int], list[int]] = {}
        for row, (a, b) in enumerate(self._rr.tolist()):
            ja, jb = self._g_jpos[a], self._g_jpos[b]
            groups.setdefault((min(ja, jb), max(ja, jb)), []).append(row)
        self._rr_groups = [(ja, jb, np.array(rows, dtype=int)) for (ja, jb), rows in sorted(groups.items())]
        eb = np.argwhere(self._box_pairs >= 0)  # (box, geometry) with a pair
        self._eb_box, self._eb_geom = eb[:, 0], eb[:, 1]
        self._eb_index = self._box_pairs[eb[:, 0], eb[:, 1]]
        fl = self._floor_pairs if self._floor_pairs is not None else np.full(n_robot, -1)
        self._fl_geom = np.flatnonzero(fl >= 0)
        self._fl_index = fl[self._fl_geom]
        self._box_geoms = np.flatnonzero(is_box)
        self._rr_box_rows = np.flatnonzero(self._rr_box)
        box_pos = np.full(n_robot, -1)
        box_pos[self._box_geoms] = np.arange(self._box_geoms.size)
        self._rr_box_pos = box_pos[rr[self._rr_box_rows, 1]]

    def _candidates(self, qq: FloatArray) -> dict[int, npt.NDArray[np.int64]]:
        """{sample index: pair indices} whose bounding volumes overlap, samples (N, 8).

        Two levels: one sphere per link, then per geometry: spheres against spheres,
        spheres against oriented robot boxes, world AABBs (sphere, or the box's own
        when tighter) against the axis-aligned court boxes and the floor."""
        Pj, Rj = self._fk(qq)  # (N, njoints, 3), (N, njoints, 3, 3)
        J = np.array(self._joints)
        Cj = Pj[:, J] + np.einsum("njab,jb->nja", Rj[:, J], self._j_c)  # (N, nJ, 3)
        r = self._radii
        sis: list[npt.NDArray[np.int64]] = []
        pks: list[npt.NDArray[np.int64]] = []

        def geom_frames(samples: npt.NDArray[np.int64], ks: npt.NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
            Rg = Rj[np.ix_(samples, self._g_joint[ks])]  # (S, K, 3, 3)
            C = Pj[np.ix_(samples, self._g_joint[ks])] + np.einsum("skab,kb->ska", Rg, self._g_p[ks])
            return C, Rg @ self._g_R[ks][None]

        for ja, jb, rows in self._rr_groups:
            near = np.flatnonzero(np.linalg.norm(Cj[:, ja] - Cj[:, jb], axis=-1) < self._j_r[ja] + self._j_r[jb])
            if near.size == 0:
                continue
            a, b = self._rr[rows, 0], self._rr[rows, 1]
            ks = np.unique(np.concatenate([a, b]))
            pos = {k: i for i, k in enumerate(ks.tolist())}
            C, R = geom_frames(near, ks)
            ia = np.array([pos[k] for k in a.tolist()])
            ib = np.array([pos[k] for k in b.tolist()])
            d = C[:, ia] - C[:, ib]
            dist = np.linalg.norm(d, axis=-1) - r[b][None]
            bx = np.flatnonzero(self._rr_box[rows])
            if bx.size:
                local = np.einsum("spji,spj->spi", R[:, ib[bx]], d[:, bx])  # R^T d
                ex = np.maximum(np.abs(local) - self._halves[b[bx]][None], 0.0)
                dist[:, bx] = np.linalg.norm(ex, axis=-1)
            si, pi = np.nonzero(dist < r[a][None])
            sis.append(near[si])
            pks.append(self._rr_index[rows[pi]])
        # Environment: link spheres against the court boxes and the floor first.
        env_lo = self._box_lo
        env_hi = self._box_hi
        if self._floor_pairs is not None:
            env_lo = np.vstack([env_lo, [-np.inf, -np.inf, -np.inf]])
            env_hi = np.vstack([env_hi, [np.inf, np.inf, self._floor_z]])
        if env_lo.size:
            gap = np.maximum(env_lo[None, None] - Cj[:, :, None], 0.0) + np.maximum(
                Cj[:, :, None] - env_hi[None, None], 0.0
            )
            sj = np.flatnonzero(np.any(np.linalg.norm(gap, axis=-1) < self._j_r[None, :, None], axis=(1, 2)))
            if sj.size:
                G = self._n_robot
                ks = np.arange(G)
                C, R = geom_frames(sj, ks)
                ext = np.broadcast_to(r[None, :, None], C.shape).copy()
                is_box = ~np.isnan(self._halves[:, 0])
                if np.any(is_box):
                    ext[:, is_box] = np.minimum(
                        ext[:, is_box], np.einsum("sgij,gj->sgi", np.abs(R[:, is_box]), self._halves[is_box])
                    )
                over = ~np.any(
                    (env_lo[None, None] > (C + ext)[:, :, None]) | ((C - ext)[:, :, None] > env_hi[None, None]), axis=-1
                )
                si, gi, bi = np.nonzero(over)
                pairs = self._box_pairs
                if self._floor_pairs is not None:
                    pairs = np.vstack([pairs, self._floor_pairs[None]])
                pk = pairs[bi, gi]
                sis.append(sj[si[pk >= 0]])
                pks.append(pk[pk >= 0])
        if not sis:
            return {}
        si = np.concatenate(sis)
        pk = np.concatenate(pks)
        if si.size == 0:
            return {}
        order = np.argsort(si, kind="stable")
        si, pk = si[order], pk[order]
        cuts = np.flatnonzero(np.diff(si)) + 1
        return {int(g[0]): p for g, p in zip(np.split(si, cuts), np.split(pk, cuts), strict=True)}

    def _sphere_bounds(self, qs: FloatArray) -> FloatArray:
        """Lower bounds (P, S) of every pair's distance [m] at samples qs (S, 8), from the
        bounding volumes of :meth:`_candidates` (robot geometry: sphere, or oriented box
        for boxes; court boxes and floor: exact), vectorised over samples and pairs
        (coordinates first: numpy is slow at reductions over a last axis of 3)."""
        S = qs.shape[0]
        Pj, Rj = self._fk(qs)
        Rg = Rj[:, self._g_joint]  # (S, G, 3, 3)
        C = np.ascontiguousarray((Pj[:, self._g_joint] + np.einsum("sgab,gb->sga", Rg, self._g_p)).transpose(2, 0, 1))
        r = self._radii
        out = np.full((len(self._pairs), S), -np.inf)  # a pair no volume covers stays "may touch"
        a, b = self._rr[:, 0], self._rr[:, 1]
        d = C[:, :, a] - C[:, :, b]  # (3, S, R)
        rr = np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2) - (r[a] + r[b])
        boxes = self._box_geoms
        # Box geometries' world rotations, (3, 3, S, B): Rw[i, j] = world axis i of box axis j.
        Rw = np.einsum("sgab,gbc->acsg", Rg[:, boxes], self._g_R[boxes])
        bx = self._rr_box_rows
        if bx.size:
            k = self._rr_box_pos  # position of the pair's box in ``boxes``
            db = d[:, :, bx]
            sq = np.zeros(db.shape[1:])
            for j in range(3):
                lj = Rw[0, j][:, k] * db[0] + Rw[1, j][:, k] * db[1] + Rw[2, j][:, k] * db[2]
                sq += np.maximum(np.abs(lj) - self._halves[b[bx], j], 0.0) ** 2
            rr[:, bx] = np.sqrt(sq) - r[a[bx]]
        out[self._rr_index] = rr.T
        # Court: the robot geometry's world AABB (its sphere, or the box's own when tighter).
        ext = np.broadcast_to(r[None, None, :], C.shape).copy()  # (3, S, G)
        if boxes.size:
            ext[:, :, boxes] = np.minimum(ext[:, :, boxes], np.einsum("ijsb,bj->isb", np.abs(Rw), self._halves[boxes]))
        if self._eb_index.size:
            g, e = self._eb_geom, self._eb_box
            sq = np.zeros((S, g.size))
            for i in range(3):
                lo, hi = self._box_lo[e, i], self._box_hi[e, i]
                ci, xi = C[i][:, g], ext[i][:, g]
                sq += (np.maximum(lo - (ci + xi), 0.0) + np.maximum((ci - xi) - hi, 0.0)) ** 2
            out[self._eb_index] = np.sqrt(sq).T
        if self._fl_index.size:
            g = self._fl_geom
            out[self._fl_index] = (C[2][:, g] - ext[2][:, g] - self._floor_z).T
        return out

    # ------------------------------------------------------------------ queries
    @property
    def n_pairs(self) -> int:
        """Number of checked geometry pairs."""
        return len(self._pairs)

    def _colliding_pairs(self, q: FloatArray) -> list[tuple[int, int]]:
        pin.computeCollisions(self.robot.model, self.data, self.geom_model, self.geom_data, q, False)
        out = []
        for k, res in enumerate(self.geom_data.collisionResults):
            if res.isCollision():
                cp = self.geom_model.collisionPairs[k]
                out.append((int(cp.first), int(cp.second)))
        return out

    def _min_distance(self, q: FloatArray) -> float:
        pin.computeDistances(self.robot.model, self.data, self.geom_model, self.geom_data, q)
        return float(min(r.min_distance for r in self.geom_data.distanceResults))

    def colliding_pairs(self, q: npt.ArrayLike) -> tuple[tuple[str, str], ...]:
        """Names of the colliding geometry pairs at configuration q (8,)."""
        qa = self._as_q(q, "q")
        return tuple((self.names[i], self.names[j]) for i, j in self._colliding_pairs(qa))

    def min_distance(self, q: npt.ArrayLike) -> float:
        """Smallest signed distance [m] over the checked pairs at configuration q (8,)."""
        return self._min_distance(self._as_q(q, "q"))

    def _as_q(self, q: npt.ArrayLike, what: str) -> FloatArray:
        arr = np.asarray(q, dtype=float)
        if arr.shape != (self.robot.nq,):
            raise InvalidInputError(f"{what}: expected shape ({self.robot.nq},), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise InvalidInputError(f"{what}: not finite")
        return arr

    def check(self, t: npt.ArrayLike, q: npt.ArrayLike, *, exhaustive: bool = False) -> CollisionReport:
        """Check a joint trajectory (predicted joint positions).

        Args:
            t: sample times (N,) [s].
            q: joint positions (N, 8) [m | rad].
            exhaustive: check every (stride-th) sample's broad-phase candidates with coal
                instead of conservative advancement (same result, slower; the reference
                the fast path is tested against).

        Returns:
            The :class:`CollisionReport` (first collision in time, if any).

        Raises:
            InvalidInputError: shapes mismatch or non-finite values (naming the field).
        """
        tt = np.asarray(t, dtype=float)
        qq = np.asarray(q, dtype=float)
        if tt.ndim != 1 or qq.shape != (tt.size, self.robot.nq):
            raise InvalidInputError(f"check: need t (N,) and q (N, {self.robot.nq}), got {tt.shape} and {qq.shape}")
        if not np.all(np.isfinite(tt)):
            raise InvalidInputError("check: t is not finite")
        if not np.all(np.isfinite(qq)):
            raise InvalidInputError(f"check: q is not finite at sample {int(np.argwhere(~np.isfinite(qq))[0, 0])}")
        N = tt.size
        idx = np.arange(0, N, self.stride)
        if N and idx[-1] != N - 1:
            idx = np.append(idx, N - 1)
        if N == 0:
            return CollisionReport(False, None, None, (), 0)
        if exhaustive:
            return self._check_exhaustive(tt, qq, idx)
        return self._check_advancing(tt, qq, idx)

    def _report(self, tt: FloatArray, i: int, hits: list[int], checked: int) -> CollisionReport:
        names = tuple((self.names[self._pairs[k][0]], self.names[self._pairs[k][1]]) for k in sorted(set(hits)))
        return CollisionReport(True, float(tt[i]), i, names, checked)

    def _check_exhaustive(self, tt: FloatArray, qq: FloatArray, idx: npt.NDArray[np.int64]) -> CollisionReport:
        """Broad phase at every checked sample, coal on the candidates (reference path)."""
        cand = self._candidates(qq[idx])
        model, data, gm, gd = self.robot.model, self.data, self.geom_model, self.geom_data
        for c in sorted(cand):
            i = int(idx[c])
            pin.updateGeometryPlacements(model, data, gm, gd, qq[i])
            hits = [int(k) for k in cand[c] if pin.computeCollision(gm, gd, int(k))]
            if hits:
                return self._report(tt, i, hits, int(idx.size))
        return CollisionReport(False, None, None, (), int(idx.size))

    def _check_advancing(self, tt: FloatArray, qq: FloatArray, idx: npt.NDArray[np.int64]) -> CollisionReport:
        """Conservative advancement over the checked samples (bounds: :meth:`_motion_bounds`).

        Each pair is measured with coal's distance d at some sample s; the samples s' after
        it whose accumulated motion bound B(s') - B(s) stays below d - margin cannot be in
        contact for that pair and are skipped; the pair is measured again at the first
        sample where the bound reaches d - margin. Pairs closer than the margin are
        checked with coal's collision test (the exhaustive path's test) at that sample.

        Before any coal query, the samples are cut into windows of :attr:`window`
        samples; a pair is only ever measured inside its "hot" windows, those where the
        lower bound of :meth:`_sphere_bounds` at the window's first sample minus the
        motion bound over the window reaches the margin (most pairs have none: ~100
        coal queries per strike instead of ~2000).

        The first sample where some pair collides is reported with every pair coal finds
        colliding there, so the result equals the exhaustive check's."""
        model, data, gm, gd = self.robot.model, self.data, self.geom_model, self.geom_data
        S = idx.size
        qs = qq[idx]
        steps, lever, view = self._motion_bounds(qs)  # (S, nq), (nq, U), (P,)
        n_pairs = len(self._pairs)
        margin = _DISTANCE_MARGIN
        W = self.window
        starts = np.arange(0, S, W)
        nW = starts.size
        ends = np.minimum(starts + W - 1, S - 1)
        growth = ((steps[ends] - steps[starts]) @ lever).T  # (U, nW)
        low = self._sphere_bounds(qs[starts]) - growth[view]  # (P, nW)
        first_hot = np.where(~(low > margin), np.arange(nW), nW)  # NaN counts as hot
        hot_next = np.minimum.accumulate(first_hot[:, ::-1], axis=1)[:, ::-1].tolist()
        heap = [(hot_next[k][0] * W, k) for k in range(n_pairs) if hot_next[k][0] < nW]
        heapq.heapify(heap)
        view_list = view.tolist()
        rows: dict[int, FloatArray] = {}
        placed = -1
        while heap:
            s, k = heapq.heappop(heap)
            if s != placed:
                pin.updateGeometryPlacements(model, data, gm, gd, qs[s])
                placed = s
            d = pin.computeDistance(gm, gd, k).min_distance
            if d <= margin:
                if pin.computeCollision(gm, gd, k):
                    hits = [kk for kk in range(n_pairs) if pin.computeCollision(gm, gd, kk)]
                    return self._report(tt, int(idx[s]), hits, int(S))
                nxt = s + 1
            else:
                u = view_list[k]
                row = rows.get(u)
                if row is None:
                    row = rows[u] = steps @ lever[:, u]
                nxt = max(int(row.searchsorted(row[s] + (d - margin))), s + 1)
            if nxt < S:
                w = hot_next[k][nxt // W]
                if w < nW:
                    heapq.heappush(heap, (max(nxt, w * W), k))
        return CollisionReport(False, None, None, (), int(S))

    def _build_motion_tables(self, model: pin.Model, floors: set[int]) -> None:
        """Joint-space levers of the "views" the pairs need, for :meth:`_motion_bounds`.

        A view (f, g) is robot geometry g seen from joint frame f (0: world, for the court
        boxes); a floor view is g's height above the floor. Moving the joints one after the
        other from sample s to s+1, a point x of g seen from f moves by at most
        sum_k |dq_k| lever[k] over the joints k on the tree path between f and g's joint:
        prismatic: 1; revolute: x's distance from the axis, at most |P_jg - P_k| + |c_g| +
        rho_g (c_g, rho_g: g's bounding sphere in its joint frame), |P_jg - P_k| at most the
        lengths of the joint placements on the path plus the travel max |q| of the
        prismatic joints on it (added per motion, over its samples). For the floor only the
        height matters: a joint whose axis a is fixed in the world (only prismatic joints
        above it) moves heights by at most |a_z| |dq| (prismatic) or
        sqrt(1 - a_z^2) lever |dq| (revolute: the motion is orthogonal to a)."""
        parents = [int(p) for p in model.parents]
        kinds = self._fk.kinds

        def chain(j: int) -> set[int]:
            out = set()
            while j != 0:
                out.add(j)
                j = parents[j]
            return out

        _, R0 = self._fk(np.zeros((1, model.nq)))
        fixed_axis: dict[int, FloatArray] = {}
        for k in range(1, model.njoints):
            if all(kinds[e][0] == "P" for e in chain(parents[k])):
                fixed_axis[k] = R0[0, parents[k]] @ self._fk.placements[k][1] @ kinds[k][1]
        edge = [0.0] + [float(np.linalg.norm(t)) for t, _ in self._fk.placements[1:]]
        n_robot = self._n_robot
        views: dict[tuple[int, int], int] = {}
        first: list[int] = []
        second: list[int] = []
        for i, j in self._pairs:
            if j >= n_robot:  # court: static in the world frame (-1: floor, height only)
                first.append(views.setdefault((-1 if j in floors else 0, i), len(views)))
                second.append(-1)
            else:  # i seen from j's joint frame, j seen from i's
                first.append(views.setdefault((int(self._g_joint[j]), i), len(views)))
                second.append(views.setdefault((int(self._g_joint[i]), j), len(views)))
        self._view_first = np.array(first, dtype=int)
        self._view_second = np.array(second, dtype=int)
        lever = np.zeros((model.nq, len(views)))
        pris = np.zeros((model.nq, len(views), model.nq))
        for (f, g), u in views.items():
            jg = int(self._g_joint[g])
            for k in chain(max(f, 0)) ^ chain(jg):
                kind, _, iq = kinds[k]
                if kind == "P":
                    lever[iq, u] = abs(fixed_axis[k][2]) if f < 0 and k in fixed_axis else 1.0
                    continue
                path = chain(k) ^ chain(jg)
                lever[iq, u] = float(np.linalg.norm(self._g_p[g])) + self._radii[g] + sum(edge[e] for e in path)
                for e in path:
                    if kinds[e][0] == "P":
                        pris[iq, u, kinds[e][2]] = 1.0
                if f < 0 and k in fixed_axis:
                    scale = math.sqrt(max(0.0, 1.0 - float(fixed_axis[k][2]) ** 2))
                    lever[iq, u] *= scale
                    pris[iq, u] *= scale
        self._lever = lever
        self._lever_pris = pris

    def _motion_bounds(self, qs: FloatArray) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int64]]:
        """Motion bounds of the pairs over samples qs (S, 8): accumulated joint steps
        A (S, nq), levers L (nq, U) and the view of each pair (P,).

        B = A @ L (S, U) bounds how much the pairs' distances can shrink: for a pair k,
        view u = view[k] and checked samples s < s', the distance at s' is at least
        d(s) - (B[s', u] - B[s, u]) (distances are frame-invariant; levers:
        :meth:`_build_motion_tables`). This bounds the distance change between the samples
        themselves (the exhaustive check also looks only at samples) whatever the path in
        between. Of a robot pair's two views the one whose bound grows less over the
        motion is used. B's columns are formed on demand (few pairs need them)."""
        S = qs.shape[0]
        lever = self._lever + self._lever_pris @ np.max(np.abs(qs), axis=0)  # (nq, U)
        steps = np.zeros_like(qs)
        if S > 1:
            np.cumsum(np.abs(np.diff(qs, axis=0)), axis=0, out=steps[1:])
        total = steps[-1] @ lever
        view = self._view_first.copy()
        rr = np.flatnonzero(self._view_second >= 0)
        better = total[self._view_second[rr]] < total[view[rr]]
        view[rr[better]] = self._view_second[rr[better]]
        return steps, lever, view


class _BatchJointFK:
    """World placements of all joint frames (pinocchio ``oMi``) for many
    configurations at once (numpy), for revolute/prismatic joints about one axis."""

    _AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}

    def __init__(self, model: pin.Model) -> None:
        self.parents = [int(p) for p in model.parents]
        self.placements = [(np.asarray(M.translation), np.asarray(M.rotation)) for M in model.jointPlacements]
        self.kinds: list[tuple[str, FloatArray, int]] = [("fixed", np.zeros(3), 0)]
        for j in range(1, model.njoints):
            jm = model.joints[j]
            name = jm.shortname()
            if name in ("JointModelRX", "JointModelRY", "JointModelRZ"):
                self.kinds.append(("R", np.array(self._AXES[name[-1]]), jm.idx_q))
            elif name in ("JointModelPX", "JointModelPY", "JointModelPZ"):
                self.kinds.append(("P", np.array(self._AXES[name[-1]]), jm.idx_q))
            elif name in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
                ax = np.asarray(jm.extract().axis, dtype=float)
                self.kinds.append(("R" if "Revolute" in name else "P", ax / np.linalg.norm(ax), jm.idx_q))
            else:
                raise RobotModelError(f"collision: joint type {name} not supported")

    def __call__(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        N = q.shape[0]
        nj = len(self.kinds)
        P = np.zeros((N, nj, 3))
        R = np.zeros((N, nj, 3, 3))
        R[:, 0] = np.eye(3)
        for j in range(1, nj):
            kind, ax, iq = self.kinds[j]
            t, Rp = self.placements[j]
            pa = self.parents[j]
            Rj = R[:, pa] @ Rp
            Pj = P[:, pa] + R[:, pa] @ t
            if kind == "P":
                Pj = Pj + (Rj @ ax) * q[:, iq, None]
            else:
                K = np.array([[0.0, -ax[2], ax[1]], [ax[2], 0.0, -ax[0]], [-ax[1], ax[0], 0.0]])
                th = q[:, iq]
                Rot = (
                    np.eye(3)[None]
                    + np.sin(th)[:, None, None] * K[None]
                    + (1.0 - np.cos(th))[:, None, None] * (K @ K)[None]
                )
                Rj = Rj @ Rot
            P[:, j] = Pj
            R[:, j] = Rj
        return P, R


def _geometry_data(gm: pin.GeometryModel) -> pin.GeometryData:
    """pinocchio geometry data whose collision requests compute contacts.

    pinocchio's default requests (``enable_contact = False``) let coal 3.0.3 miss
    penetrating cylinder pairs: link_4_0/link_6_0 overlapping by 0.8 mm (coal's signed
    distance -8.2e-4 m) was reported free, found again with contacts enabled (regression
    test in ``tests/test_collision.py``)."""
    gd = pin.GeometryData(gm)
    for req in gd.collisionRequests:
        req.enable_contact = True
    return gd


def _box_placement(box: Box) -> pin.SE3:
    return pin.SE3(np.eye(3), np.asarray(box.center, dtype=float))
