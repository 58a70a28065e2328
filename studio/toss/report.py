"""Human-readable analysis of toss recordings (``serve-studio toss``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from studio import constants as C
from studio.errors import DataFileError, InvalidInputError
from studio.toss.defaults import (
    default_recordings_path,
    default_toss,
    load_default_toss_model,
)
from studio.toss.local_fit import LOCAL_FIT_HALF_WINDOW
from studio.toss.model import TossModel
from studio.toss.primitive import TOSS_SIDES, TossSide
from studio.toss.recordings import load_recordings_csv

if TYPE_CHECKING:
    from studio.robot.model import Robot


def toss_report(side: TossSide = "right", csv_path: str | Path | None = None, *, robot: Robot | None = None) -> str:
    """Human-readable analysis of toss recordings (``serve-studio toss``).

    Builds the :class:`~studio.toss.model.TossModel` of the default ``side`` primitive from ``csv_path``
    (default: the shipped recordings) and reports the predicted release, ``t_lift``,
    the rise of the mean path and the spread after the lift.

    Raises:
        InvalidInputError / DataFileError: bad side or recordings file.
    """
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"toss side must be one of {TOSS_SIDES}, got {side!r}")
    if robot is None and csv_path is None:
        model = load_default_toss_model(side)
    else:
        from studio.robot.model import load_robot

        rb = load_robot() if robot is None else robot
        path = default_recordings_path(side) if csv_path is None else Path(csv_path)
        recordings = load_recordings_csv(path)
        try:
            model = TossModel.from_recordings(default_toss(rb, side), recordings)
        except DataFileError:
            raise
        except InvalidInputError as exc:  # a toss that does not fit this side's primitive: name the file
            raise DataFileError(path, str(exc)) from None
    rel = model.primitive.release
    apex = float(np.max(model.p[:, 2]))
    lines = [
        f"{model.primitive.name}: {model.n_tosses} tosses, model grid {model.t[0]:.3f}-{model.t[-1]:.3f} s (command clock)",
        f"  predicted release {rel.time:.4f} s at {np.round(rel.position, 3)} m, "
        f"v = {np.round(rel.velocity, 3)} m/s, spin {rel.spin:.2g} rad/s",
        f"  t_lift {model.t_lift:.4f} s (fit rms {model.lift_fit_rms * 1e3:.2f} mm, "
        f"{(model.t_lift - rel.time) * 1e3:+.1f} ms from the prediction)",
        f"  mean path apex {apex:.3f} m: rise {apex - float(rel.position[2]):.3f} m above the release "
        f"(ITTF 2.6.2: >= {C.TOSS_MIN_RISE} m)",
        f"  clock offsets {np.min(model.clock_offsets):.3f}..{np.max(model.clock_offsets):.3f} s, "
        f"height bias {np.min(model.z_bias) * 1e3:+.1f}..{np.max(model.z_bias) * 1e3:+.1f} mm",
    ]
    for dt_after in (0.3, 0.5, 0.7):
        tq = model.t_lift + dt_after
        if tq <= model.t[-1]:
            sp = model.spread_at(tq) * 1e3
            lines.append(
                f"  spread {dt_after:.1f} s after the lift: x {sp[0]:.1f}, y {sp[1]:.1f}, z {sp[2]:.1f} mm "
                f"(|.| {float(np.linalg.norm(sp)):.1f} mm), ball at z = {model.mean_state(tq).p[2]:.3f} m"
            )
            if tq >= model.free_flight_start:
                rs = model.recorded_spread_at(tq) * 1e3
                lines.append(
                    f"    recorded states there (each toss's own samples +/- {LOCAL_FIT_HALF_WINDOW * 1e3:.0f} ms): |spread| {float(np.linalg.norm(rs)):.1f} mm"
                )
    return "\n".join(lines)
