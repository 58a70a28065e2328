"""Collision check of robot motions against the robot itself and the court (coal).

The paper verifies collision safety of every motion plan "by running the motion plan
through a custom collision detector based on Coal". This module does the same:

* robot geometry: the URDF's collision elements, loaded by pinocchio
  (``buildGeomFromUrdf(..., COLLISION)``, coal shapes: boxes and cylinders);
* environment: the table top, net and net posts (:meth:`studio.court.Court.boxes`), the
  table legs (:meth:`~studio.court.Court.legs`) as coal boxes and the floor as a coal
  half-space, all fixed in the world frame (``DESIGN.md``: origin at the centre of
  the playing surface, +Z up, floor at z = -0.76 m);
* pairs: every robot geometry against every environment geometry, and robot
  geometries against each other except (a) geometries of the same link or of two
  links joined by one joint (adjacent links touch by construction), (b) static parts
  (the gantry rails) against the environment, (c) pairs that are in contact in both
  named poses ``q_rest`` and ``q_flat`` (permanent contacts of the model, listed in
  :attr:`CollisionChecker.ignored_pairs`).

Sampling: a trajectory is checked at every sample (1 kHz for plans). Broad phase,
vectorised over all samples with numpy (batched forward kinematics of the joint
frames): one bounding sphere per link, then per geometry its bounding sphere (or
oriented box for boxes such as the gantry beam); (sample, pair) candidates are the
overlapping robot/robot volumes and the robot volumes reaching a court box or the
floor. Narrow phase: coal checks only the candidates (pinocchio ``computeCollision``
per pair). At 1 kHz and racket speeds up to 10 m/s a point moves at most 1 cm between
samples, less than the thinnest obstacle plus the racket (4 mm net + 14 mm blade), so
a contact cannot be stepped over (it may be reported up to 1 ms late). ``stride`` > 1
checks every stride-th sample only (faster, weaker guarantee). pinocchio's own
broad-phase managers were tried and rejected: they skipped the forearm/flange pair
(link_4/link_6) in 112 of 1500 random poses where it collides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import coal
import numpy as np
import numpy.typing as npt
import pinocchio as pin

from studio.court import DEFAULT_COURT, Box, Court
from studio.errors import InvalidInputError, RobotModelError
from studio.robot import Robot

FloatArray = npt.NDArray[np.float64]

_DISTANCE_MARGIN = 1e-4
"""Distance [m] below which conservative advancement stops skipping a pair and asks coal's
collision test at every sample: covers the tolerance of coal's GJK distance (~1e-6 m) and
rounding with a wide margin (engineering choice)."""


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
    geometries are named ``<link>_<k>``, court ones as in :mod:`studio.court`."""
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
    ) -> None:
        """Build the geometry model.

        Args:
            robot: the robot (its URDF provides the collision geometry).
            court: court geometry (table, net, posts, legs, extras).
            floor: add the floor half-space (z = court.floor_z).
            stride: check every stride-th sample (>= 1; the last sample is always checked).

        Raises:
            RobotModelError: the URDF's collision geometry cannot be loaded.
            InvalidInputError: bad stride.
        """
        if int(stride) < 1:
            raise InvalidInputError(f"CollisionChecker: stride must be >= 1, got {stride}")
        self.robot = robot
        self.stride = int(stride)
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
        self.geom_data = pin.GeometryData(gm)
        # Permanent contacts of the model: robot pairs touching in both named poses.
        touching = [set(self._colliding_pairs(q)) for q in (robot.q_rest, robot.q_flat)]
        permanent = {p for p in touching[0] & touching[1] if p[0] < n_robot and p[1] < n_robot}
        if permanent:
            for i, j in sorted(permanent):
                gm.removeCollisionPair(pin.CollisionPair(i, j))
            self.geom_data = pin.GeometryData(gm)
        self.ignored_pairs: tuple[tuple[str, str], ...] = tuple(
            (self.names[i], self.names[j]) for i, j in sorted(permanent)
        )
        self._pairs = [(int(cp.first), int(cp.second)) for cp in gm.collisionPairs]
        self._build_broad_phase(court if floor else None, n_robot, env)

    def _build_broad_phase(self, court: Court | None, n_robot: int, env: list[tuple[str, object, pin.SE3]]) -> None:
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
        # Conservative advancement: frames carrying geometry (world first) and pair members.
        self._frames = sorted({0, *self._g_joint.tolist()})
        fpos = {j: i for i, j in enumerate(self._frames)}
        self._g_frame = np.array([fpos[j] for j in self._g_joint.tolist()], dtype=int)
        self._pair_a = np.array([i for i, _ in self._pairs], dtype=int)
        self._pair_b = np.array([j if j < n_robot else -1 for _, j in self._pairs], dtype=int)
        groups: dict[tuple[int, int], list[int]] = {}
        for row, (a, b) in enumerate(self._rr.tolist()):
            ja, jb = self._g_jpos[a], self._g_jpos[b]
            groups.setdefault((min(ja, jb), max(ja, jb)), []).append(row)
        self._rr_groups = [(ja, jb, np.array(rows, dtype=int)) for (ja, jb), rows in sorted(groups.items())]

    def _candidates(self, qq: FloatArray) -> dict[int, npt.NDArray[np.int64]]:
        """{sample index: pair indices} whose bounding volumes overlap, samples (N, 8).

        Two levels: one sphere per link, then per geometry: spheres against spheres,
        spheres against oriented robot boxes, world AABBs (sphere, or the box's own
        when tighter) against the axis-aligned court boxes and the floor."""
        N = qq.shape[0]
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
            gap = np.maximum(env_lo[None, None] - Cj[:, :, None], 0.0) + np.maximum(Cj[:, :, None] - env_hi[None, None], 0.0)
            sj = np.flatnonzero(np.any(np.linalg.norm(gap, axis=-1) < self._j_r[None, :, None], axis=(1, 2)))
            if sj.size:
                G = self._n_robot
                ks = np.arange(G)
                C, R = geom_frames(sj, ks)
                ext = np.broadcast_to(r[None, :, None], C.shape).copy()
                is_box = ~np.isnan(self._halves[:, 0])
                if np.any(is_box):
                    ext[:, is_box] = np.minimum(ext[:, is_box], np.einsum("sgij,gj->sgi", np.abs(R[:, is_box]), self._halves[is_box]))
                over = ~np.any((env_lo[None, None] > (C + ext)[:, :, None]) | ((C - ext)[:, :, None] > env_hi[None, None]), axis=-1)
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
        """Conservative advancement over the checked samples (see :meth:`_motion_bounds`).

        Each pair is measured with coal's distance d at some sample s; the samples s' after
        it whose accumulated motion bound B(s, s') stays below d - margin cannot be in
        contact for that pair and are skipped; the pair is measured again at the first
        sample where the bound reaches d - margin. Pairs closer than the margin are
        checked with coal's collision test (the exhaustive path's test) at that sample.
        The first sample where some pair collides is reported with every pair coal finds
        colliding there, so the result equals the exhaustive check's."""
        model, data, gm, gd = self.robot.model, self.data, self.geom_model, self.geom_data
        S = idx.size
        qs = qq[idx]
        cum = self._motion_bounds(qs)  # (P, S)
        n_pairs = len(self._pairs)
        buckets: list[list[int]] = [[] for _ in range(S + 1)]
        buckets[0] = list(range(n_pairs))
        margin = _DISTANCE_MARGIN
        for s in range(S):
            due = buckets[s]
            if not due:
                continue
            buckets[s] = []
            i = int(idx[s])
            pin.updateGeometryPlacements(model, data, gm, gd, qs[s])
            collided = False
            for k in due:
                d = float(pin.computeDistance(gm, gd, k).min_distance)
                if d <= margin:
                    if pin.computeCollision(gm, gd, k):
                        collided = True
                        break
                    nxt = s + 1
                else:
                    row = cum[k]
                    nxt = int(np.searchsorted(row, row[s] + (d - margin), side="left"))
                    if nxt <= s:
                        nxt = s + 1
                buckets[min(nxt, S)].append(k)
            if collided:
                hits = [k for k in range(n_pairs) if pin.computeCollision(gm, gd, k)]
                return self._report(tt, i, hits, int(S))
        return CollisionReport(False, None, None, (), int(S))

    def _motion_bounds(self, qs: FloatArray) -> FloatArray:
        """Accumulated bounds B (P, S) on how much each pair's distance can shrink, samples (S, 8).

        For a pair (a, b) and samples s < s', the distance at s' is at least
        d(s) - (B[s'] - B[s]). Per step s -> s+1 the bound is the largest displacement of
        a point of one geometry seen from the other geometry's joint frame (distances are
        frame-invariant): a geometry with bounding sphere (centre c, radius rho) moving from
        (c, R) to (c', R') in that frame moves its points by at most
        |c' - c| + rho * ||R' - R||_2, with ||R' - R||_2 = ||R' - R||_F / sqrt(2) for
        rotations (exact: two singular values 2 sin(theta/2), one zero). The smaller
        of the two frames' bounds is used per step; court geometries are static in the world
        frame (joint 0). This bounds the distance change between the samples themselves
        (the exhaustive check also looks only at samples), whatever the path in between."""
        P, R = self._fk(qs)  # (S, nj, 3), (S, nj, 3, 3)
        S = qs.shape[0]
        if S < 2:
            return np.zeros((len(self._pairs), max(S, 1)))
        J = np.array(self._frames, dtype=int)  # joint frames that carry geometry (incl. 0)
        PJ, RJ = P[:, J], R[:, J]  # (S, F, 3), (S, F, 3, 3)
        C = P[:, self._g_joint] + np.einsum("sgab,gb->sga", R[:, self._g_joint], self._g_p)  # (S, G, 3)
        # Centres of every robot geometry in every frame: X[s, f, g] = R_f^T (C_g - P_f).
        F, G = len(J), C.shape[1]
        RJt = RJ.transpose(0, 1, 3, 2).reshape(S, 3 * F, 3)  # rows (f, a): R_f^T
        X = (RJt @ C.transpose(0, 2, 1)).reshape(S, F, 3, G)  # R_f^T C_g
        X -= np.sum(RJ * PJ[:, :, :, None], axis=2)[..., None]  # ... - R_f^T P_f
        dX = np.sqrt(np.sum(np.square(X[1:] - X[:-1]), axis=2))  # (S-1, F, G)
        Rrel = (RJt @ RJ.transpose(0, 2, 1, 3).reshape(S, 3, 3 * F)).reshape(S, F, 3, F, 3)  # R_f^T R_h
        dR = np.sqrt(np.sum(np.square(Rrel[1:] - Rrel[:-1]), axis=(2, 4)) * 0.5)  # (S-1, F, F)
        gf = self._g_frame  # frame index of each robot geometry
        step = dX + dR[:, :, gf] * self._radii[None, None, :]  # (S-1, F, G): geometry g seen from frame f
        a, b = self._pair_a, self._pair_b  # robot geometry of each pair; b = -1 for court geometries
        env = b < 0
        fa = gf[a]
        fb = np.where(env, 0, gf[np.maximum(b, 0)])
        pair_step = step[:, fb, a]  # a seen from b's frame (world for the court)
        rr = ~env
        pair_step[:, rr] = np.minimum(pair_step[:, rr], step[:, fa[rr], b[rr]])
        out = np.zeros((len(self._pairs), S))
        np.cumsum(pair_step.T, axis=1, out=out[:, 1:])
        return out

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
                Rot = np.eye(3)[None] + np.sin(th)[:, None, None] * K[None] + (1.0 - np.cos(th))[:, None, None] * (K @ K)[None]
                Rj = Rj @ Rot
            P[:, j] = Pj
            R[:, j] = Rj
        return P, R


def _box_placement(box: Box) -> pin.SE3:
    return pin.SE3(np.eye(3), np.asarray(box.center, dtype=float))
