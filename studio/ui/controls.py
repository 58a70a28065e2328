"""The Serve tab's serve controls: build them, read them into a snapshot, write a serve in.

:class:`ServeForm` owns the viser handles of the serve being edited (name, toss side,
toss, task, the serve parameters' sliders, joint-limit factors, MuJoCo checkbox) and
converts between them and a :class:`Controls` snapshot. Units are those of the labels:
times [s], racket velocity [m/s], racket normal yaw/roll [deg] (radians in the serve),
contact offset [m], joint limits as factors of the robot's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from studio.errors import InvalidInputError
from studio.serve.params import (
    LIMIT_SCALE_RANGE,
    MAX_NAME_LENGTH,
    GenomeBounds,
    HandServe,
    LimitScale,
    ServeParams,
)
from studio.serve.reward import TASKS
from studio.ui.checks import Choice, Flag, InputGuard, Number, Rule, Text, choices, refusal_message

MEAN_TOSS = "mean path"
"""The "Toss" choice that evaluates on the toss model's mean path."""


@dataclass(frozen=True, slots=True)
class Controls:
    """A snapshot of the studio's controls: what the worker evaluates (and undo restores)."""

    serve: HandServe
    """Serve being edited (side and parameters)."""
    task: str
    """Reward task preset."""
    toss_sample: int | None
    """Recorded toss index, or None for the mean toss path."""
    mujoco: bool
    """Also roll the serve out in MuJoCo."""


def fallback_serve() -> HandServe:
    """The serve shown when no serve file is found: a plain push at 4 m/s."""
    return HandServe(
        name="my serve", side="right", params=ServeParams(tau=0.8, velocity=(4.0, 0.0, 0.0), yaw=math.pi / 2, roll=0.0)
    )


def toss_label(sample: int | None) -> str:
    """The "Toss" dropdown entry of a toss sample (0-based; None: the mean path)."""
    return MEAN_TOSS if sample is None else f"recorded {sample + 1}"


def display_name(name: str) -> str:
    """A serve name as the "Name" field takes it: control characters as spaces, at most
    :data:`~studio.serve.params.MAX_NAME_LENGTH` characters."""
    return "".join(" " if ord(ch) < 32 or ord(ch) == 127 else ch for ch in name)[:MAX_NAME_LENGTH]


class ServeForm:
    """The serve controls, added to the current viser GUI container.

    Every control is registered with ``guard`` with its own range or options
    (:mod:`studio.ui.checks`): a value outside them never reaches an evaluation.

    Args:
        gui: the server's ``gui`` API.
        guard: the studio's input checks (None: the controls are not registered).
        bounds: slider ranges (the genome's physical bounds).
    """

    def __init__(self, gui: Any, guard: InputGuard | None = None, bounds: GenomeBounds | None = None) -> None:
        b = bounds or GenomeBounds()
        self._toss_options: tuple[str, ...] = (MEAN_TOSS,)
        self.name = gui.add_text("Name", initial_value="my serve")
        self.side = gui.add_dropdown("Toss side", options=["right", "left"], initial_value="right")
        self.toss = gui.add_dropdown("Toss", options=[MEAN_TOSS], initial_value=MEAN_TOSS)
        self.task = gui.add_dropdown("Task", options=list(TASKS), initial_value="topspin_velocity")
        with gui.add_folder("Contact"):
            self.tau = gui.add_slider("tau [s]", min=b.tau[0], max=b.tau[1], step=0.005, initial_value=0.8)
            self.t_return = gui.add_slider(
                "return [s]", min=b.t_return[0], max=b.t_return[1], step=0.01, initial_value=0.7
            )
        with gui.add_folder("Racket velocity [m/s]"):
            self.vx = gui.add_slider("v_x", min=-b.velocity[0], max=b.velocity[0], step=0.05, initial_value=4.0)
            self.vy = gui.add_slider("v_y", min=-b.velocity[1], max=b.velocity[1], step=0.05, initial_value=0.0)
            self.vz = gui.add_slider("v_z", min=-b.velocity[2], max=b.velocity[2], step=0.05, initial_value=0.0)
        with gui.add_folder("Racket normal [deg]"):
            self.yaw = gui.add_slider(
                "yaw", min=math.degrees(b.yaw[0]), max=math.degrees(b.yaw[1]), step=0.5, initial_value=90.0
            )
            self.roll = gui.add_slider("roll", min=-180.0, max=180.0, step=0.5, initial_value=0.0)
        with gui.add_folder("Contact offset [m]", expand_by_default=False):
            self.dpx = gui.add_slider("dp_x", min=-b.offset, max=b.offset, step=0.002, initial_value=0.0)
            self.dpy = gui.add_slider("dp_y", min=-b.offset, max=b.offset, step=0.002, initial_value=0.0)
            self.dpz = gui.add_slider("dp_z", min=-b.offset, max=b.offset, step=0.002, initial_value=0.0)
        with gui.add_folder("Joint limits [x robot's]", expand_by_default=False):
            lo, hi = LIMIT_SCALE_RANGE
            self.limit_speed = gui.add_slider("speed", min=lo, max=hi, step=0.05, initial_value=1.0)
            self.limit_accel = gui.add_slider("acceleration", min=lo, max=hi, step=0.05, initial_value=1.0)
            self.limit_jerk = gui.add_slider("jerk", min=lo, max=hi, step=0.05, initial_value=1.0)
        self.mujoco = gui.add_checkbox("MuJoCo rollout", initial_value=False)

        def slider(handle: Any, label: str, unit: str) -> Number:
            return Number(label, float(handle.min), float(handle.max), unit)

        self.rules: dict[str, tuple[Any, Rule]] = {
            "name": (self.name, Text("Name", MAX_NAME_LENGTH)),
            "side": (self.side, Choice("Toss side", choices("right", "left"))),
            "toss": (self.toss, Choice("Toss", lambda: self._toss_options)),
            "task": (self.task, Choice("Task", choices(*TASKS))),
            "tau": (self.tau, slider(self.tau, "tau", "s")),
            "return": (self.t_return, slider(self.t_return, "return", "s")),
            "v_x": (self.vx, slider(self.vx, "v_x", "m/s")),
            "v_y": (self.vy, slider(self.vy, "v_y", "m/s")),
            "v_z": (self.vz, slider(self.vz, "v_z", "m/s")),
            "yaw": (self.yaw, slider(self.yaw, "yaw", "deg")),
            "roll": (self.roll, slider(self.roll, "roll", "deg")),
            "dp_x": (self.dpx, slider(self.dpx, "dp_x", "m")),
            "dp_y": (self.dpy, slider(self.dpy, "dp_y", "m")),
            "dp_z": (self.dpz, slider(self.dpz, "dp_z", "m")),
            "speed limit": (self.limit_speed, slider(self.limit_speed, "speed limit", "x the robot's")),
            "acceleration limit": (self.limit_accel, slider(self.limit_accel, "acceleration limit", "x the robot's")),
            "jerk limit": (self.limit_jerk, slider(self.limit_jerk, "jerk limit", "x the robot's")),
            "mujoco": (self.mujoco, Flag("MuJoCo rollout")),
        }
        """Each control's rule by key (the numeric keys are those of :meth:`read`'s errors)."""
        if guard is not None:
            for handle, rule in self.rules.values():
                guard.add(handle, rule)

    @property
    def inputs(self) -> tuple[Any, ...]:
        """Every handle whose change re-evaluates the serve."""
        return (
            self.side,
            self.toss,
            self.task,
            self.tau,
            self.t_return,
            self.vx,
            self.vy,
            self.vz,
            self.yaw,
            self.roll,
            self.dpx,
            self.dpy,
            self.dpz,
            self.limit_speed,
            self.limit_accel,
            self.limit_jerk,
            self.mujoco,
        )

    def _checked(self, key: str) -> Any:
        """The value of control ``key`` if its rule accepts it, else InvalidInputError
        naming the control and its range or options."""
        handle, rule = self.rules[key]
        value = handle.value
        why = rule.refusal(value)
        if why is not None:
            raise InvalidInputError(
                refusal_message(rule.label, value, why, has_kept=False).removeprefix("**Refused:** ")
            )
        return value

    def _numbers(self) -> dict[str, float]:
        """The numeric controls by name; InvalidInputError names one that is not a finite
        number within its slider's range."""
        keys = (
            "tau",
            "return",
            "v_x",
            "v_y",
            "v_z",
            "yaw",
            "roll",
            "dp_x",
            "dp_y",
            "dp_z",
            "speed limit",
            "acceleration limit",
            "jerk limit",
        )
        return {k: float(self._checked(k)) for k in keys}

    def read(self) -> Controls:
        """Read the controls into a validated snapshot (InvalidInputError names the control)."""
        v = self._numbers()
        params = ServeParams(
            tau=v["tau"],
            velocity=(v["v_x"], v["v_y"], v["v_z"]),
            yaw=math.radians(v["yaw"]),
            roll=math.radians(v["roll"]),
            t_return=v["return"],
            offset=(v["dp_x"], v["dp_y"], v["dp_z"]),
        )
        try:
            scale = LimitScale(velocity=v["speed limit"], acceleration=v["acceleration limit"], jerk=v["jerk limit"])
        except InvalidInputError as err:
            raise InvalidInputError(f"joint limits control: {err}") from None
        name, side, task, toss_choice = (self._checked(k) for k in ("name", "side", "task", "toss"))
        mujoco = self._checked("mujoco")
        serve = HandServe(name=name.strip() or "my serve", side=side, params=params, task=task, limit_scale=scale)
        toss = None if toss_choice == MEAN_TOSS else int(toss_choice.split()[-1]) - 1
        return Controls(serve=serve, task=task, toss_sample=toss, mujoco=bool(mujoco))

    def write(self, serve: HandServe) -> None:
        """Put ``serve`` into the controls, each value clipped to its slider's range (the
        caller keeps the change callbacks quiet meanwhile)."""
        p = serve.params
        self.name.value = display_name(serve.name)
        self.side.value = serve.side
        if serve.task in TASKS:
            self.task.value = serve.task
        pairs = (
            (self.tau, p.tau), (self.t_return, p.t_return),
            (self.vx, p.velocity[0]), (self.vy, p.velocity[1]), (self.vz, p.velocity[2]),
            (self.dpx, p.offset[0]), (self.dpy, p.offset[1]), (self.dpz, p.offset[2]),
            (self.yaw, math.degrees(p.yaw)), (self.roll, math.degrees(p.roll)),
        )  # fmt: skip
        for handle, value in pairs:
            handle.value = float(np.clip(value, handle.min, handle.max))
        scale = serve.limit_scale  # the sliders span LIMIT_SCALE_RANGE: every valid scale fits
        self.limit_speed.value, self.limit_accel.value, self.limit_jerk.value = (
            scale.velocity,
            scale.acceleration,
            scale.jerk,
        )

    def write_all(self, controls: Controls, n_tosses: int) -> None:
        """Put a whole snapshot back (undo, redo, restore): serve, task, toss, MuJoCo."""
        self.write(controls.serve)
        self.task.value = controls.task
        self.set_toss_options(n_tosses, toss_label(controls.toss_sample))
        self.mujoco.value = controls.mujoco

    def set_toss_options(self, n_tosses: int, choice: str | None = None) -> None:
        """List the mean path and ``n_tosses`` recorded tosses; keep (or set) the choice if listed."""
        options = [MEAN_TOSS, *(toss_label(i) for i in range(n_tosses))]
        wanted = self.toss.value if choice is None else choice
        self._toss_options = (*self._toss_options, *options)  # both lists valid while they change
        self.toss.options = options
        self._toss_options = tuple(options)
        self.toss.value = wanted if wanted in options else MEAN_TOSS
