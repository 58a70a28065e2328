"""Joint efforts of a serve's exported motion, checked against the robot's effort limits.

The peak force/torque of each joint over the whole exported motion (preparation, toss,
strike, return and final hold, :func:`studio.planning.serve_plan.serve_arrays`): pinocchio's inverse
dynamics (:meth:`studio.robot.model.Robot.joint_efforts`) of the predicted joint trajectory,
accelerations from the joint model q'' = wn^2 (u - q) - 2 zeta wn q'. The limits are the
``effort`` values of ``robots/serve_robot.toml``: stated estimates (no data-sheet figures
exist), derived by ``experiments/effort_limits.py``.

The paper's order: check the torques, then expand the acceleration and jerk limits where
the torques leave room. A plan that needs more than a limit is flagged (:attr:`
EffortReport.within`) and refused by the library's export (:class:`EffortLimitError`)
unless the user raises that joint's limit on purpose (``limits``: joint name -> new
limit), which the exported entry records.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError

if TYPE_CHECKING:
    from studio.planning.serve_plan import ServeArrays
    from studio.robot.model import Robot
    from studio.serve.evaluate import ServeMotion

FloatArray = npt.NDArray[np.float64]


class EffortLimitError(InvalidInputError):
    """A plan needs more force/torque than a joint's effort limit allows (export refused)."""


@dataclass(frozen=True)
class EffortReport:
    """Peak joint forces/torques of a serve's whole exported motion and the limits they
    are checked against."""

    names: tuple[str, ...]
    """Joint names (8)."""
    peak: FloatArray
    """Largest |force/torque| per joint (8,) [N | N m]."""
    at: FloatArray
    """Time of each peak (8,) [s] on the exported clock (the library NPZ's ``t``: 0 at the
    start of the preparation; the toss clock when the motion has no preparation)."""
    limit: FloatArray
    """Effort limit per joint (8,) [N | N m]: the robot's, or the user's where raised."""
    raised: tuple[str, ...] = field(default=())
    """Joints whose limit the user set (:meth:`with_limits`)."""

    @property
    def usage(self) -> FloatArray:
        """peak / limit (8,) [-]."""
        return np.asarray(self.peak / self.limit, dtype=float)

    @property
    def worst(self) -> tuple[str, float]:
        """(joint, usage) of the most used joint."""
        k = int(np.argmax(self.usage))
        return self.names[k], float(self.usage[k])

    @property
    def exceeded(self) -> tuple[str, ...]:
        """Joints whose peak is above their limit."""
        return tuple(n for n, u in zip(self.names, self.usage) if u > 1.0)

    @property
    def within(self) -> bool:
        """True when every peak is within its limit."""
        return not self.exceeded

    def with_limits(self, limits: Mapping[str, float]) -> EffortReport:
        """This report checked against ``limits`` (joint name -> limit [N | N m]) where given."""
        checked = parse_limits(limits, self.names)
        new = np.array([checked.get(n, lim) for n, lim in zip(self.names, self.limit)])
        return replace(self, limit=new, raised=tuple(n for n in self.names if n in checked or n in self.raised))

    def peak_limits(self) -> dict[str, float]:
        """The limits that would let this plan pass: each exceeded joint's peak rounded up
        to 1 % (joint name -> limit [N | N m]; empty when within)."""
        return {n: _round_up(float(p)) for n, p, lim in zip(self.names, self.peak, self.limit) if p > lim}

    def raised_to_peaks(self) -> EffortReport:
        """This report with every exceeded joint's limit raised to :meth:`peak_limits`."""
        return self.with_limits(self.peak_limits())

    def require_within(self) -> None:
        """Raise :class:`EffortLimitError` naming every exceeded joint, its peak and limit,
        and how to raise the limit."""
        needed = self.peak_limits()
        if not needed:
            return
        rows = ", ".join(
            f"{n} {p:.4g} > {lim:.4g} ({100 * p / lim:.0f} %)"
            for n, p, lim in zip(self.names, self.peak, self.limit)
            if n in needed
        )
        flags = " ".join(f"--effort-limit {n}={v:g}" for n, v in needed.items())
        raise EffortLimitError(
            f"the plan needs more than the effort limits allow: {rows} [N | N m]; export refused. "
            f"Lower the serve's limit scale, or raise the limit on purpose if the drive allows it ({flags})"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "names": list(self.names),
            "peak": _floats(self.peak),
            "at": _floats(self.at),
            "limit": _floats(self.limit),
            "usage": _floats(self.usage),
            "within": self.within,
            "exceeded": list(self.exceeded),
            "raised": list(self.raised),
        }

    def headline(self) -> str:
        """One Markdown line: within the limits (most used joint) or which joints exceed them."""
        name, use = self.worst
        if self.within:
            head = f"**Joint efforts** within the limits: most used {name} at {100 * use:.0f} %"
        else:
            over = ", ".join(f"{n} {100 * u:.0f} %" for n, u in zip(self.names, self.usage) if u > 1.0)
            head = f"**Joint efforts EXCEED the limits**: {over}; export refused unless the limit is raised"
        if self.raised:
            head += f" (limits raised by the user: {', '.join(self.raised)})"
        return head

    def markdown(self) -> str:
        """:meth:`headline` and a table of every joint's peak, limit, usage and time."""
        rows = "\n".join(
            f"| {n} | {p:.1f} | {lim:g}{' (raised)' if n in self.raised else ''} | {100 * p / lim:.0f} % | {t:.3f} |"
            for n, p, lim, t in zip(self.names, self.peak, self.limit, self.at)
        )
        return f"{self.headline()}\n\n| joint | peak [N, N m] | limit | usage | at [s, exported clock] |\n| --- | --- | --- | --- | --- |\n{rows}"


def arrays_effort_report(robot: Robot, arrays: ServeArrays) -> EffortReport:
    """The peak joint efforts of exported ``arrays`` against ``robot``'s effort limits."""
    from studio.robot.cup_hold import joint_accelerations

    tau = np.abs(robot.joint_efforts(arrays.q, arrays.qd, joint_accelerations(robot, arrays.u, arrays.q, arrays.qd)))
    k = np.argmax(tau, axis=0)
    cols = np.arange(tau.shape[1])
    return EffortReport(
        robot.joint_names, tau[k, cols], np.asarray(arrays.t)[k], np.asarray(robot.effort_limits, dtype=float)
    )


def effort_report(motion: ServeMotion, robot: Robot) -> EffortReport | None:
    """The peak joint efforts of ``motion`` as exported: its preparation, toss, strike,
    return and final hold, times on the exported clock (None without a motion)."""
    if motion.t is None or motion.u is None or motion.q is None or len(motion.t) < 3:
        return None
    from studio.planning.serve_plan import serve_arrays

    arrays = serve_arrays(motion.t, motion.u, motion.q, motion.qd, robot.dynamics, preparation=motion.preparation)
    return arrays_effort_report(robot, arrays)


def parse_limits(limits: Mapping[str, Any] | Sequence[str], names: Sequence[str]) -> dict[str, float]:
    """User effort limits as {joint: limit [N | N m]}, from a mapping or ``NAME=VALUE``
    strings (the CLI's ``--effort-limit``); InvalidInputError for an unknown joint or a
    limit that is not a finite positive number."""
    pairs: list[tuple[str, Any]] = []
    if isinstance(limits, Mapping):
        pairs = list(limits.items())
    else:
        for item in limits:
            name, sep, value = str(item).partition("=")
            if not sep:
                raise InvalidInputError(f"effort limit {item!r}: expected JOINT=VALUE, e.g. gantry_x=4700")
            pairs.append((name.strip(), value.strip()))
    out: dict[str, float] = {}
    for name, value in pairs:
        if name not in names:
            raise InvalidInputError(f"effort limit for unknown joint {name!r}: the joints are {', '.join(names)}")
        try:
            number = float(value)
        except (TypeError, ValueError, OverflowError):
            number = math.nan
        if isinstance(value, bool) or not math.isfinite(number) or number <= 0.0:
            raise InvalidInputError(f"effort limit of {name}: must be a finite number > 0 [N | N m], got {value!r}")
        out[name] = number
    return out


def _round_up(x: float) -> float:
    """``x`` rounded up to 3 significant digits (within 1 %)."""
    if x <= 0.0:
        return x
    step = 10.0 ** (math.floor(math.log10(x)) - 2)
    return math.ceil(x / step - 1e-9) * step


def _floats(a: npt.ArrayLike) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=float)]
