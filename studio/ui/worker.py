"""A single background worker where the newest input wins.

GUI callbacks (a slider being dragged fires dozens of events a second) only record the
latest input with :meth:`LatestWorker.submit`; one thread computes, and publishes each
finished result through ``on_result``. Inputs submitted while a computation runs are
coalesced: only the newest is computed next, intermediate ones are dropped. Results are
published in submission order, so a consumer never sees an older result after a newer
one. An exception inside ``compute`` is published as the result's ``error``; it never
kills the worker.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

Inp = TypeVar("Inp")
R = TypeVar("R")


@dataclass(frozen=True, slots=True)
class WorkResult(Generic[Inp, R]):
    """What the worker publishes for one computed input."""

    ticket: int
    """Increasing number of the submission this result belongs to."""
    inputs: Inp
    """The input that was computed."""
    value: R | None
    """The computed value, or None if ``compute`` raised."""
    error: BaseException | None
    """The exception raised by ``compute``, if any."""
    error_text: str
    """Formatted traceback of ``error`` (empty when there is none)."""
    seconds: float
    """Wall time of the computation [s]."""
    superseded: bool
    """True if newer input was already waiting when this result was published."""


class LatestWorker(Generic[Inp, R]):
    """Runs ``compute`` on the newest submitted input in one daemon thread."""

    def __init__(
        self,
        compute: Callable[[Inp], R],
        on_result: Callable[[WorkResult[Inp, R]], None],
        *,
        name: str = "latest-worker",
    ) -> None:
        self._compute = compute
        self._on_result = on_result
        self._cond = threading.Condition()
        self._pending: tuple[int, Inp] | None = None
        self._ticket = 0
        self._done_ticket = 0
        self._busy = False
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, inputs: Inp) -> int:
        """Record ``inputs`` as the newest; returns its ticket. Never blocks on computation."""
        with self._cond:
            if self._closed:
                raise RuntimeError("worker is closed")
            self._ticket += 1
            self._pending = (self._ticket, inputs)
            self._cond.notify_all()
            return self._ticket

    @property
    def latest_ticket(self) -> int:
        """Ticket of the newest submission."""
        return self._ticket

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every submitted input has been handled; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._pending is not None or self._busy:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def close(self, timeout: float | None = 5.0) -> None:
        """Stop the thread after the computation in progress (pending input is dropped)."""
        with self._cond:
            self._closed = True
            self._pending = None
            self._cond.notify_all()
        self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                assert self._pending is not None
                ticket, inputs = self._pending
                self._pending = None
                self._busy = True
            start = time.perf_counter()
            value: R | None = None
            error: BaseException | None = None
            text = ""
            try:
                value = self._compute(inputs)
            except Exception as exc:  # noqa: BLE001 - published to the GUI, never lost
                error, text = exc, traceback.format_exc()
            seconds = time.perf_counter() - start
            with self._cond:
                superseded = self._pending is not None
            result = WorkResult(ticket, inputs, value, error, text, seconds, superseded)
            try:
                self._on_result(result)
            except Exception:  # noqa: BLE001 - a broken consumer must not kill the worker
                traceback.print_exc()
            with self._cond:
                self._busy = False
                self._done_ticket = ticket
                self._cond.notify_all()
