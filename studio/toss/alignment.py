"""Time alignment of toss recordings: each recording's clock offset (and height bias)
against the primitive's predicted cup height, which puts every toss on the command clock.
SI units."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError
from studio.toss.primitive import TossPrimitive
from studio.toss.recordings import TossRecording

FloatArray = npt.NDArray[np.float64]

MAX_CUP_OFFSET = 0.05
"""Largest horizontal distance [m] between a recorded ball riding in the cup and the
primitive's cup path (mean over the in-cup samples). The shipped synthetic tosses: 0.5 mm
at most; the other side's recordings: 0.60 m (issue 18: a left-side file was accepted for
the right toss, the per-recording offsets of the t_lift fit absorbing the 0.6 m)."""


def align_recordings(
    primitive: TossPrimitive, recordings: tuple[TossRecording, ...]
) -> tuple[tuple[TossRecording, ...], FloatArray, FloatArray]:
    """The recordings of ``primitive`` moved to its command clock, with their estimated
    clock offsets (recording minus command clock) [s] and height biases [m], each (K,).

    Each offset comes from a coarse match of the crossing of the half-way height of the
    lift (between the start and the predicted release), refined by least squares of the
    recording's heights while the ball rides up in the cup against the predicted cup
    height (:attr:`~studio.toss.primitive.TossPrimitive.cup_p`).

    Raises:
        InvalidInputError: a recording that does not show the ball rising in the cup, or
            whose ball rides farther than :data:`MAX_CUP_OFFSET` from the cup's path
            (a recording of another toss, e.g. the other side's).
    """
    from scipy.interpolate import CubicSpline

    rel = primitive.release
    z_cup = CubicSpline(primitive.t, primitive.cup_p[:, 2])
    z0 = float(primitive.cup_p[0, 2])
    z_thr = z0 + 0.5 * (float(rel.position[2]) - z0)
    i_thr = int(np.argmax(primitive.cup_p[:, 2] >= z_thr))
    zc = primitive.cup_p[:, 2]
    w = (z_thr - zc[i_thr - 1]) / (zc[i_thr] - zc[i_thr - 1])
    t_cross = float(primitive.t[i_thr - 1] + w * primitive.dt)

    offsets, biases, aligned = [], [], []
    for rec in recordings:
        off, bias = _align_recording(rec, z_cup, t_cross, z_thr, rel.time)
        offsets.append(off)
        biases.append(bias)
        aligned.append(TossRecording(toss_id=rec.toss_id, t=rec.t - off, p=rec.p))
        _check_in_cup(primitive, aligned[-1])
    return tuple(aligned), np.array(offsets), np.array(biases)


def _check_in_cup(primitive: TossPrimitive, rec: TossRecording) -> None:
    """InvalidInputError when the aligned recording's ball, while it rides in the cup, is
    on average farther than :data:`MAX_CUP_OFFSET` from the cup's path horizontally."""
    sel = (rec.t >= primitive.t[0]) & (rec.t <= primitive.release.time - 0.01)
    if not np.any(sel):
        return
    cup = np.stack([np.interp(rec.t[sel], primitive.t, primitive.cup_p[:, j]) for j in range(2)], axis=1)
    dx, dy = np.mean(rec.p[sel, :2] - cup, axis=0)
    if float(np.hypot(dx, dy)) > MAX_CUP_OFFSET:
        raise InvalidInputError(
            f"toss {rec.toss_id!r}: while in the cup the ball is {float(np.hypot(dx, dy)):.3f} m from the cup path of "
            f"{primitive.name} (x {dx:+.3f} m, y {dy:+.3f} m; at most {MAX_CUP_OFFSET} m): a recording of another toss "
            "(the other side's?)"
        )


def _align_recording(
    rec: TossRecording, z_nom: object, t_cross_nom: float, z_thr: float, t_rel_nom: float
) -> tuple[float, float]:
    """Clock offset (recording minus command clock) [s] and height bias [m] of one
    recording, by least squares of its in-cup heights against the predicted cup height.

    ``z_nom`` is a callable z(t) of the predicted cup height on the command clock;
    ``t_cross_nom`` is when it crosses ``z_thr`` (half-way up the lift).
    """
    from scipy.optimize import minimize_scalar

    z = rec.p[:, 2]
    above = np.flatnonzero(z >= z_thr)
    if above.size == 0 or above[0] == 0:
        raise InvalidInputError(
            f"toss {rec.toss_id!r}: the recording does not show the ball rising in the cup through "
            f"z = {z_thr:.3f} m (it must start before the lift to be aligned)"
        )
    i = int(above[0])
    w = (z_thr - z[i - 1]) / (z[i] - z[i - 1])
    off0 = float(rec.t[i - 1] + w * (rec.t[i] - rec.t[i - 1]) - t_cross_nom)
    tc = rec.t - off0
    sel = tc <= t_rel_nom - 0.01
    if np.count_nonzero(sel) < 8:
        raise InvalidInputError(f"toss {rec.toss_id!r}: too few in-cup samples to align it ({np.count_nonzero(sel)})")
    ts, zs = rec.t[sel], z[sel]

    def cost(off: float) -> float:
        r = zs - z_nom(ts - off)  # type: ignore[operator]
        r = r - r.mean()
        return float(r @ r)

    res = minimize_scalar(cost, bounds=(off0 - 0.01, off0 + 0.01), method="bounded", options={"xatol": 1e-7})
    off = float(res.x)
    bias = float(np.mean(zs - z_nom(ts - off)))  # type: ignore[operator]
    return off, bias
