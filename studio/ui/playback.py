"""Playback of the evaluated serve: play/pause, scrub, slow motion, ball size.

:class:`PlaybackPanel` owns the "Playback" folder and a 30 Hz daemon loop that advances
its own clock (seconds of serve time per second of wall time = the chosen speed) and
poses robot and ball through :meth:`studio.ui.scene.StudioScene.show_time`; the ball's
seam turns at the simulated spin, so slow motion shows the spin.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import AbstractContextManager
from typing import Any

from studio.ui.checks import Choice, InputGuard, Number, Press, choices
from studio.ui.scene import BALL_MAGNIFICATIONS, SceneFrame, StudioScene

log = logging.getLogger("studio.ui")

SPEEDS = ("0.02x", "0.05x", "0.1x", "0.25x", "0.5x", "1x")
"""Playback speeds (serve time per wall time)."""

SLOW_MOTION = "0.02x"
"""Speed of "Slow motion from contact": 300 rad/s of spin (~48 rev/s) turns the seam about
once a second, 12 degrees a frame."""

LEAD_IN = 0.03
""""Slow motion from contact" starts this long before the racket contact [s]."""

FPS = 30.0
"""Playback frames per second of wall time."""


class PlaybackPanel:
    """The Playback folder and its loop.

    Args:
        gui: the server's ``gui`` API; the folder goes into its current container.
        scene: the scene to pose.
        lock: a re-entrant lock held while posing the scene (the worker replaces the
            frame under it; setting the time slider calls back synchronously).
        guard: the studio's input checks (the time within the serve's span, a listed
            speed and ball size); None: unchecked.
    """

    def __init__(
        self, gui: Any, scene: StudioScene, lock: AbstractContextManager[Any], guard: InputGuard | None = None
    ) -> None:
        self.scene = scene
        self.lock = lock
        self.playing = False
        self.clock = 0.0
        """Current serve time shown [s]."""
        self.span = (0.0, 2.5)
        """The time slider's range: the shown serve's playback [s]."""
        with gui.add_folder("Playback"):
            self.play_button = gui.add_button("Play")
            self.slow_button = gui.add_button(
                "Slow motion from contact",
                hint=f"play at {SLOW_MOTION} from just before the racket contact: the seam turns at the simulated spin",
            )
            self.time = gui.add_slider("time [s]", min=0.0, max=2.5, step=0.001, initial_value=0.0)
            self.speed = gui.add_dropdown("speed", options=list(SPEEDS), initial_value="0.25x")
            self.ball_size = gui.add_dropdown(
                "ball drawn",
                options=list(BALL_MAGNIFICATIONS),
                initial_value="x3",
                hint="the ball is 40 mm across; a bigger ball shows its seam turning",
            )
        if guard is None:
            self.play_button.on_click(lambda _event: self.toggle())
            self.slow_button.on_click(lambda _event: self.slow_motion_from_contact())
            self.time.on_update(lambda _event: self._scrubbed())
            self.ball_size.on_update(lambda _event: self._resize_ball())
        else:
            guard.add(self.play_button, Press("Play"))
            guard.add(self.slow_button, Press("Slow motion from contact"))
            guard.add(self.time, Number("time", unit="s", span=lambda: self.span))
            guard.add(self.speed, Choice("speed", choices(*SPEEDS)))
            guard.add(self.ball_size, Choice("ball drawn", choices(*BALL_MAGNIFICATIONS)))
            guard.on_update(self.play_button, lambda _event: self.toggle())
            guard.on_update(self.slow_button, lambda _event: self.slow_motion_from_contact())
            guard.on_update(self.time, lambda _event: self._scrubbed())
            guard.on_update(self.ball_size, lambda _event: self._resize_ball())
        self._resize_ball()

    def _scrubbed(self) -> None:
        if not self.playing:
            self.clock = float(self.time.value)
            with self.lock:
                self.scene.show_time(self.clock)

    def _resize_ball(self) -> None:
        with self.lock:
            self.scene.set_ball_scale(BALL_MAGNIFICATIONS[self.ball_size.value])

    def toggle(self) -> None:
        """Play or pause."""
        self.playing = not self.playing
        self.play_button.label = "Pause" if self.playing else "Play"

    def play_from_start(self) -> None:
        """Start playing from the beginning (nothing if already playing)."""
        if self.playing:
            return
        self.seek(float(self.time.min))
        self.toggle()

    def slow_motion_from_contact(self) -> None:
        """Play at :data:`SLOW_MOTION` from :data:`LEAD_IN` before the racket contact."""
        pb = self.scene.frame.playback
        if pb is None or pb.contact_t is None:
            return
        self.speed.value = SLOW_MOTION
        self.seek(pb.contact_t - LEAD_IN)
        if not self.playing:
            self.toggle()

    def seek(self, t: float) -> None:
        """Show serve time ``t`` [s] (clipped to the playback's span)."""
        with self.lock:
            self.clock = min(max(float(t), float(self.time.min)), float(self.time.max))
            self.scene.show_time(self.clock)
        self.time.value = self.clock

    def new_frame(self, frame: SceneFrame) -> None:
        """Fit the time slider to a new frame's playback and pose it at the current time
        (call with the lock held, after :meth:`StudioScene.show`)."""
        pb = frame.playback
        if pb is None or not len(pb.t):
            return
        t0, t1 = float(pb.t[0]), float(pb.t[-1])
        self.span = (min(t0, self.span[0]), max(t1, self.span[1]))  # both spans valid while the slider changes
        self.time.max = t1
        self.time.min = t0
        self.span = (t0, t1)
        self.clock = min(max(self.clock, float(pb.t[0])), float(pb.t[-1]))
        self.time.value = self.clock
        self.scene.show_time(self.clock)

    def advance(self, wall_dt: float) -> float:
        """Move the clock by ``wall_dt`` [s] of wall time at the chosen speed (wrapping to
        the start after the end) and pose the scene; returns the new serve time [s]."""
        speed = self.speed.value if self.speed.value in SPEEDS else "1x"
        t_new = self.clock + wall_dt * float(speed.rstrip("x"))
        if t_new > self.time.max:
            t_new = float(self.time.min)
        with self.lock:  # clock and pose change together
            self.clock = t_new
            self.scene.show_time(t_new)
        self.time.value = t_new
        return t_new

    def start_loop(self) -> None:
        """Run the playback loop in a daemon thread."""

        def loop() -> None:
            last = time.perf_counter()
            while True:
                time.sleep(1.0 / FPS)
                now = time.perf_counter()
                dt, last = now - last, now
                if self.playing:
                    try:
                        self.advance(dt)
                    except Exception as err:  # noqa: BLE001 - the loop outlives a bad frame
                        log.warning("studio: playback: %s: %s", type(err).__name__, err)

        threading.Thread(target=loop, name="studio-playback", daemon=True).start()
