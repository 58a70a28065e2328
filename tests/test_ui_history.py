"""Undo/redo history of the studio's controls (studio.ui.history.History)."""

from __future__ import annotations

import pytest

from studio.ui.history import History


def test_undo_redo_walk_the_recorded_states() -> None:
    h: History[int] = History()
    assert h.current is None and h.undo() is None and h.counts() == (0, 0)
    h.record(1, now=0.0)  # a load
    h.record(2, key="v_x", now=10.0)
    h.record(3, key="roll", now=20.0)
    assert h.current == 3 and h.counts() == (2, 0)
    assert h.undo() == 2 and h.undo() == 1 and h.undo() is None  # the oldest stays
    assert h.counts() == (0, 2)
    assert h.redo() == 2 and h.current == 2 and h.counts() == (1, 1)
    h.record(7, key="v_z", now=30.0)  # a change after an undo drops the undone state (3)
    assert h.redo() is None and h.undo() == 2 and h.redo() == 7


def test_a_drag_of_one_control_is_one_step() -> None:
    """Events of the same control within the merge window replace the step; another
    control, a pause or a load start a new one."""
    h: History[float] = History(window=1.0)
    h.record(0.0, now=0.0)
    for i, value in enumerate((4.0, 4.1, 4.2, 4.3)):  # a slider dragged: 4 events 0.1 s apart
        h.record(value, key="v_x", now=5.0 + 0.1 * i)
    assert h.counts() == (1, 0) and h.current == 4.3
    h.record(4.5, key="v_x", now=5.3 + 1.5)  # after a pause: a new step
    h.record(4.6, key="roll", now=6.9)  # another control: a new step
    h.record(4.7, now=7.0)  # a load never merges
    h.record(4.8, key="roll", now=7.1)  # nor merges into a load
    assert h.counts() == (5, 0)
    assert [h.undo() for _ in range(5)] == [4.7, 4.6, 4.5, 4.3, 0.0]


def test_undo_seals_the_step_and_equal_states_are_not_doubled() -> None:
    h: History[int] = History()
    h.record(1, now=0.0)
    h.record(2, key="v_x", now=1.0)
    h.undo()
    h.record(3, key="v_x", now=1.1)  # within the window, but after an undo: a new step
    assert h.counts() == (1, 0) and h.undo() == 1
    h.redo()
    h.record(3, key="tau", now=50.0)  # the same state again: nothing new
    assert h.counts() == (1, 0)


def test_capacity_drops_the_oldest() -> None:
    h: History[int] = History(capacity=3)
    for i in range(5):
        h.record(i, now=float(i))
    assert h.counts() == (2, 0) and h.undo() == 3 and h.undo() == 2 and h.undo() is None
    with pytest.raises(ValueError):
        History(capacity=1)
