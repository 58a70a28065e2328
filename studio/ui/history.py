"""Undo/redo of the studio's control changes, and the pinned serve for A/B comparison.

:class:`History` is a plain list of states with a cursor: a control change records a new
state (dropping anything undone); a burst of changes of the same control (a slider being
dragged fires dozens of events a second) is one step; undo and redo move the cursor and
return the state to put back into the controls. It knows nothing of viser or serves.

:class:`Pin` holds the serve pinned as "A": its controls, its evaluation and its scene
(drawn faded as a ghost), to compare the current serve "B" with while tuning and to
restore in one click.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Generic, TypeVar

if TYPE_CHECKING:
    from studio.serve.efforts import EffortReport
    from studio.serve.evaluate import Evaluation
    from studio.ui.controls import Controls
    from studio.ui.scene import SceneFrame

S = TypeVar("S")

MERGE_WINDOW = 1.0
"""Changes of the same control closer together than this [s] are one undo step."""

CAPACITY = 200
"""Most states kept (the oldest are dropped)."""


@dataclass(frozen=True, slots=True)
class _Step(Generic[S]):
    state: S
    key: str | None
    """The control whose change made this state (None: a load, not mergeable)."""
    time: float
    """When it was recorded [s, monotonic clock]."""


class History(Generic[S]):
    """Undo/redo over states of type ``S``.

    Args:
        window: changes of one control within ``window`` [s] of the last are merged.
        capacity: most states kept.
    """

    def __init__(self, *, window: float = MERGE_WINDOW, capacity: int = CAPACITY) -> None:
        if capacity < 2:
            raise ValueError(f"History capacity must be >= 2, got {capacity}")
        self.window = window
        self.capacity = capacity
        self._steps: list[_Step[S]] = []
        self._pos = -1
        self._lock = threading.RLock()  # GUI callbacks and background jobs record concurrently

    def record(self, state: S, *, key: str | None = None, now: float | None = None) -> None:
        """Record ``state`` as the current one, after dropping the undone states.

        With ``key`` (the changed control) equal to the current state's and within the
        merge window, the current state is replaced instead (one step per drag). A state
        equal to the current one is not recorded twice."""
        now = time.monotonic() if now is None else now
        with self._lock:
            del self._steps[self._pos + 1 :]
            top = self._steps[-1] if self._steps else None
            if top is not None and top.state == state:
                self._steps[-1] = _Step(state, top.key, top.time if key is None else now)
                return
            if top is not None and key is not None and key == top.key and now - top.time < self.window:
                self._steps[-1] = _Step(state, key, now)
                return
            self._steps.append(_Step(state, key, now))
            if len(self._steps) > self.capacity:
                del self._steps[0]
            self._pos = len(self._steps) - 1

    @property
    def current(self) -> S | None:
        """The state at the cursor (None before the first record)."""
        return self._steps[self._pos].state if self._pos >= 0 else None

    @property
    def can_undo(self) -> bool:
        """Whether there is an earlier state."""
        return self._pos > 0

    @property
    def can_redo(self) -> bool:
        """Whether an undone state can be redone."""
        return self._pos < len(self._steps) - 1

    def undo(self) -> S | None:
        """Step back: the previous state, or None (nothing changes) at the oldest."""
        with self._lock:
            if not self.can_undo:
                return None
            self._pos -= 1
            self._seal()
            return self._steps[self._pos].state

    def redo(self) -> S | None:
        """Step forward again: the next state, or None at the newest."""
        with self._lock:
            if not self.can_redo:
                return None
            self._pos += 1
            self._seal()
            return self._steps[self._pos].state

    def _seal(self) -> None:
        """After an undo/redo the next change starts a new step (never merges into it)."""
        step = self._steps[self._pos]
        self._steps[self._pos] = _Step(step.state, None, step.time)

    def counts(self) -> tuple[int, int]:
        """(undo steps available, redo steps available)."""
        with self._lock:
            return max(self._pos, 0), len(self._steps) - 1 - self._pos


@dataclass(frozen=True)
class Pin:
    """The serve pinned as "A" for comparison."""

    controls: Controls
    """Its control values (what "Restore" puts back)."""
    evaluation: Evaluation
    """Its evaluation (its numbers beside the current ones)."""
    efforts: EffortReport | None
    """Its joint-effort report."""
    frame: SceneFrame
    """Its scene, drawn faded as the ghost."""
