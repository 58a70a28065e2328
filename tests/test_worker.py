"""The latest-input-wins worker: coalescing, ordering, errors."""

from __future__ import annotations

import threading
import time

import pytest

from studio.ui.worker import LatestWorker, WorkResult


def test_newest_input_wins_and_intermediate_dropped() -> None:
    gate = threading.Event()
    computed: list[int] = []
    published: list[WorkResult[int, int]] = []

    def compute(x: int) -> int:
        if x == 0:
            gate.wait(5)  # hold the first computation while more input arrives
        computed.append(x)
        return x * x

    worker = LatestWorker(compute, published.append)
    worker.submit(0)
    time.sleep(0.05)
    for x in range(1, 20):
        worker.submit(x)
    gate.set()
    assert worker.wait_idle(5)
    worker.close()
    assert computed == [0, 19]  # 1..18 were coalesced away
    assert [r.value for r in published] == [0, 361]
    assert published[0].superseded and not published[1].superseded
    tickets = [r.ticket for r in published]
    assert tickets == sorted(tickets) and tickets[-1] == 20


def test_errors_are_published_not_raised() -> None:
    published: list[WorkResult[float, float]] = []

    def compute(x: float) -> float:
        if x != x:
            raise ValueError("slider 'tau' is NaN")
        return 2 * x

    worker = LatestWorker(compute, published.append)
    worker.submit(float("nan"))
    assert worker.wait_idle(5)
    worker.submit(1.5)
    assert worker.wait_idle(5)
    worker.close()
    assert published[0].value is None and isinstance(published[0].error, ValueError)
    assert "slider 'tau' is NaN" in published[0].error_text
    assert published[1].value == 3.0 and published[1].error is None


def test_closed_worker_rejects_input() -> None:
    worker: LatestWorker[int, int] = LatestWorker(lambda x: x, lambda r: None)
    worker.close()
    with pytest.raises(RuntimeError):
        worker.submit(1)
