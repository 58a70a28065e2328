"""The rebound of the ball at a rollout contact (:class:`Impacts`): contact geometry from
MuJoCo, velocity and spin after the impact from the impulse maps of
:mod:`studio.physics.ball`.

Table top (edges with their own normal) and floor: :class:`~studio.physics.ball.TableBounceModel`;
the blade faces: :class:`~studio.physics.ball.RacketModel` relative to the racket's velocity
at the contact point (MuJoCo point Jacobian), face A or B from the side touched; net and
posts: :class:`~studio.physics.ball.NetModel`; any other robot geom (links, handle, cup,
blade rim): a simple restitution relative to the geom's velocity
(:attr:`~studio.sim.options.RolloutOptions.robot_restitution`). World frame, SI units.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, cast

import mujoco
import numpy as np
import numpy.typing as npt

from studio.physics.ball import NetModel, RacketModel, TableBounceModel
from studio.sim.contact import Contact, ContactKind
from studio.sim.contact_search import DISTANCE_CUTOFF
from studio.sim.options import RolloutOptions
from studio.sim.robot_track import RobotTrack
from studio.sim.scene import Scene

FloatArray = npt.NDArray[np.float64]


def surface_frame(n: FloatArray) -> FloatArray:
    """Rotation (3, 3) whose third column is the unit vector ``n``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, n)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], axis=1)


def restitution(v: FloatArray, v_surface: FloatArray, n: FloatArray, e: float) -> FloatArray:
    """Velocity after a frictionless impact with restitution ``e`` on a surface moving at
    ``v_surface`` with unit normal ``n`` (towards the ball)."""
    vn = float((v - v_surface) @ n)
    if vn >= 0.0:
        return v.copy()
    return v - (1.0 + e) * vn * n


class Impacts:
    """Contacts of a rollout: geometry and rebound of the ball at a touched geom.

    ``racket_model`` None: :meth:`RacketModel.default` (the calibrated racket), loaded at
    each blade contact. Uses (and overwrites) the robot pose and the ball geom's position
    in ``data``.
    """

    def __init__(
        self,
        scene: Scene,
        data: mujoco.MjData,
        track: RobotTrack,
        *,
        table: TableBounceModel,
        net: NetModel,
        racket_model: RacketModel | None,
        options: RolloutOptions,
    ) -> None:
        self.scene = scene
        self.d = data
        self.track = track
        self.table = table
        self.net = net
        self.racket_model = racket_model
        self.options = options
        self._fromto = np.zeros(6)

    def contact(self, g: int, tc: float, ye: Sequence[float]) -> Contact:
        """The contact with geom ``g`` at ``tc`` [s] of the ball in state ``ye`` (9,) =
        [p, v, w] just before it: contact point and normal from MuJoCo, rebound from the
        impulse maps."""
        scene = self.scene
        body = int(scene.model.geom_bodyid[g])
        if body != 0:
            self.track.pose(tc)
        p = np.array(ye[0:3])
        v_b = np.array(ye[3:6])
        w_b = np.array(ye[6:9])
        point, normal = self._geometry(g, p)
        kind = cast(ContactKind, scene.geom_kind[g])
        name = scene.geom_name(g)
        v_s = np.zeros(3)
        side: Literal["server", "receiver"] | None = None
        if kind in ("floor", "table"):
            part, v_a, w_a = self._table_rebound(kind, normal, v_b, w_b)
            side = scene.court.side(float(p[0]))
        elif kind in ("net", "post"):
            part = name
            v_a, w_a = self.net.bounce(v_b, w_b, normal, "net" if kind == "net" else "post")
        else:
            part, v_a, w_a, v_s = self._robot_rebound(kind, name, body, tc, p, point, normal, v_b, w_b)
        for a in (p, point, normal, v_b, v_a, w_b, w_a, v_s):
            a.setflags(write=False)
        return Contact(
            t=float(tc),
            kind=kind,
            geom=name,
            body=scene.body_name(body),
            part=part,
            p=p,
            point=point,
            normal=normal,
            v_before=v_b,
            v_after=v_a,
            w_before=w_b,
            w_after=w_a,
            surface_velocity=v_s,
            side=side,
        )

    def _geometry(self, g: int, p: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Contact point (3,) on geom ``g`` and unit normal (3,) from it to the ball centre
        ``p`` (ball placed at ``p``; robot already posed)."""
        m, d, bg, fromto = self.scene.model, self.d, self.scene.ball_geom, self._fromto
        d.geom_xpos[bg] = p
        mujoco.mj_geomDistance(m, d, bg, g, DISTANCE_CUTOFF, fromto)
        point = fromto[3:6].copy()
        nv = p - point
        nn = float(np.linalg.norm(nv))
        if nn > 1e-9:
            normal = nv / nn
        else:  # degenerate (cannot happen at a first touch): use the ball's surface point
            nv = p - fromto[0:3]
            normal = nv / max(float(np.linalg.norm(nv)), 1e-12)
        return point, normal

    def _table_rebound(
        self, kind: str, normal: FloatArray, v_b: FloatArray, w_b: FloatArray
    ) -> tuple[str, FloatArray, FloatArray]:
        """Part touched, velocity and spin after a floor or table contact (table edges:
        the bounce model in the frame of their own normal)."""
        table = self.table
        if kind == "floor":
            v_a, w_a = table.bounce(v_b, w_b)
            return "floor", v_a, w_a
        part = "top" if normal[2] > 1.0 - 1e-9 else "edge"
        if part == "top":
            v_a, w_a = table.bounce(v_b, w_b)
        else:
            F = surface_frame(normal)
            v2, w2 = table.bounce(F.T @ v_b, F.T @ w_b)
            v_a, w_a = F @ v2, F @ w2
        return part, v_a, w_a

    def _robot_rebound(
        self,
        kind: str,
        name: str,
        body: int,
        tc: float,
        p: FloatArray,
        point: FloatArray,
        normal: FloatArray,
        v_b: FloatArray,
        w_b: FloatArray,
    ) -> tuple[str, FloatArray, FloatArray, FloatArray]:
        """Part touched, velocity and spin after, and the surface velocity at the contact
        point, of a robot contact: the rubber model on a blade face, else restitution."""
        track, options = self.track, self.options
        v_s, w_s = track.point_velocity(tc, body, point)
        part = name
        v_a, w_a = restitution(v_b, v_s, normal, options.robot_restitution), w_b.copy()
        if kind == "racket":
            R = self.d.xmat[self.scene.racket_body].reshape(3, 3).copy()
            c = float(normal @ R[:, 2])
            if abs(c) >= options.rim_cosine:
                s = 1.0 if c > 0.0 else -1.0
                part = "face_a" if s > 0.0 else "face_b"
                racket_model = self.racket_model if self.racket_model is not None else RacketModel.default()
                v_c, _ = track.point_velocity(tc, body, p)  # racket point at the ball centre
                v_a, w_a = racket_model.bounce_moving(v_b, w_b, R, v_c, s, omega=w_s)
            else:
                part = "rim"
        return part, v_a, w_a, v_s
