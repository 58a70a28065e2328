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
    GenomeBounds,
    HandServe,
    LimitScale,
    ServeParams,
)
from studio.serve.reward import TASKS

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
    return HandServe(name="my serve", side="right", params=ServeParams(tau=0.8, velocity=(4.0, 0.0, 0.0), yaw=math.pi / 2, roll=0.0))


def toss_label(sample: int | None) -> str:
    """The "Toss" dropdown entry of a toss sample (0-based; None: the mean path)."""
    return MEAN_TOSS if sample is None else f"recorded {sample + 1}"


class ServeForm:
    """The serve controls, added to the current viser GUI container.

    Args:
        gui: the server's ``gui`` API.
        bounds: slider ranges (the genome's physical bounds).
    """

    def __init__(self, gui: Any, bounds: GenomeBounds | None = None) -> None:
        b = bounds or GenomeBounds()
        self.name = gui.add_text("Name", initial_value="my serve")
        self.side = gui.add_dropdown("Toss side", options=["right", "left"], initial_value="right")
        self.toss = gui.add_dropdown("Toss", options=[MEAN_TOSS], initial_value=MEAN_TOSS)
        self.task = gui.add_dropdown("Task", options=list(TASKS), initial_value="topspin_velocity")
        with gui.add_folder("Contact"):
            self.tau = gui.add_slider("tau [s]", min=b.tau[0], max=b.tau[1], step=0.005, initial_value=0.8)
            self.t_return = gui.add_slider("return [s]", min=b.t_return[0], max=b.t_return[1], step=0.01, initial_value=0.7)
        with gui.add_folder("Racket velocity [m/s]"):
            self.vx = gui.add_slider("v_x", min=-b.velocity[0], max=b.velocity[0], step=0.05, initial_value=4.0)
            self.vy = gui.add_slider("v_y", min=-b.velocity[1], max=b.velocity[1], step=0.05, initial_value=0.0)
            self.vz = gui.add_slider("v_z", min=-b.velocity[2], max=b.velocity[2], step=0.05, initial_value=0.0)
        with gui.add_folder("Racket normal [deg]"):
            self.yaw = gui.add_slider("yaw", min=math.degrees(b.yaw[0]), max=math.degrees(b.yaw[1]), step=0.5, initial_value=90.0)
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

    @property
    def inputs(self) -> tuple[Any, ...]:
        """Every handle whose change re-evaluates the serve."""
        return (self.side, self.toss, self.task, self.tau, self.t_return, self.vx, self.vy, self.vz, self.yaw, self.roll, self.dpx, self.dpy, self.dpz, self.limit_speed, self.limit_accel, self.limit_jerk, self.mujoco)

    def _numbers(self) -> dict[str, float]:
        """The numeric controls by name; InvalidInputError names a non-finite one."""
        values = {
            "tau": self.tau.value, "return": self.t_return.value,
            "v_x": self.vx.value, "v_y": self.vy.value, "v_z": self.vz.value,
            "yaw": self.yaw.value, "roll": self.roll.value,
            "dp_x": self.dpx.value, "dp_y": self.dpy.value, "dp_z": self.dpz.value,
            "speed limit": self.limit_speed.value, "acceleration limit": self.limit_accel.value, "jerk limit": self.limit_jerk.value,
        }  # fmt: skip
        for key, value in values.items():
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InvalidInputError(f"control {key!r} must be a finite number, got {value!r}")
        return {k: float(v) for k, v in values.items()}

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
        serve = HandServe(name=self.name.value.strip() or "my serve", side=self.side.value, params=params, task=self.task.value, limit_scale=scale)
        toss = None if self.toss.value == MEAN_TOSS else int(self.toss.value.split()[-1]) - 1
        return Controls(serve=serve, task=self.task.value, toss_sample=toss, mujoco=bool(self.mujoco.value))

    def write(self, serve: HandServe) -> None:
        """Put ``serve`` into the controls, each value clipped to its slider's range (the
        caller keeps the change callbacks quiet meanwhile)."""
        p = serve.params
        self.name.value = serve.name
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
        self.limit_speed.value, self.limit_accel.value, self.limit_jerk.value = scale.velocity, scale.acceleration, scale.jerk

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
        self.toss.options = options
        self.toss.value = wanted if wanted in options else MEAN_TOSS
