"""An exclusive lock on a folder, for processes that read, modify and rewrite its files.

Writers of a serve library (``index.json``, ``matches.jsonl``: export, match points, usage
sync, pruning; the CLI, the studio and training alike) hold :func:`locked` on the library
folder across the whole read-modify-write, so none of them overwrites another's change.

The lock is ``fcntl.flock`` on :data:`LOCK_NAME` inside the folder (created on first use,
never deleted: deleting a lock file others may have open breaks the exclusion). The kernel
releases it when its holder exits, however it ends (``kill -9`` included), so a stale lock
cannot exist. The holder writes its pid and command into the file, for the message a
waiter shows after ``timeout`` seconds (:class:`LockTimeoutError`). Readers take no lock:
every file is replaced atomically (rename), so a reader sees the old or the new version.

Re-entrant per thread: a thread that holds the lock of a folder may take it again (nested
writers such as record point -> sync usage -> rewrite index); other threads of the same
process wait like other processes (each acquisition opens its own file description).
Linux/POSIX only (``fcntl``).
"""

from __future__ import annotations

import fcntl
import os
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from studio.errors import StudioError

LOCK_NAME = ".lock"
"""File name of the lock inside the locked folder."""
DEFAULT_TIMEOUT = 120.0
"""Seconds a writer waits for the lock before giving up (an export holds it well under a
second; the environment variable ``SERVE_STUDIO_LOCK_TIMEOUT`` overrides)."""
_POLL = 0.02
"""Seconds between attempts while waiting."""

_held: dict[tuple[int, str], list[int]] = {}
"""(thread id, lock path) -> [file descriptor, depth] of the locks this process holds."""
_held_guard = threading.Lock()


class LockTimeoutError(StudioError):
    """Another process (or thread) held a folder's lock for longer than the timeout."""


def default_timeout() -> float:
    """:data:`DEFAULT_TIMEOUT`, or ``SERVE_STUDIO_LOCK_TIMEOUT`` [s] when set to a number >= 0."""
    raw = os.environ.get("SERVE_STUDIO_LOCK_TIMEOUT")
    try:
        value = float(raw) if raw is not None else DEFAULT_TIMEOUT
    except ValueError:
        return DEFAULT_TIMEOUT
    return value if value >= 0 else DEFAULT_TIMEOUT


def _holder(path: Path) -> str:
    """What the lock file says about its holder ("pid N (command)"), or "another process"."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        text = ""
    return text or "another process"


def _acquire(path: Path, timeout: float) -> int:
    """Open ``path`` and flock it exclusively, polling until ``timeout`` [s]; the fd."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    deadline = time.monotonic() + timeout
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            if time.monotonic() >= deadline:
                who = _holder(path)
                os.close(fd)
                raise LockTimeoutError(
                    f"{path.parent} is busy: {who} has held its lock {path.name} for more than {timeout:g} s; "
                    "try again when it is done (SERVE_STUDIO_LOCK_TIMEOUT sets the wait)"
                ) from None
            time.sleep(_POLL)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()} ({' '.join(sys.argv[:3])[:200]})\n".encode("utf-8", "replace"), 0)
    return fd


@contextmanager
def locked(folder: str | Path, *, timeout: float | None = None) -> Iterator[None]:
    """Hold the exclusive lock of ``folder`` (created if absent) for the ``with`` block.

    Args:
        folder: the folder whose files the block reads and rewrites.
        timeout: seconds to wait for another holder (default :func:`default_timeout`).

    Raises:
        LockTimeoutError: the lock was not free within ``timeout``; the message names the
            folder and the holder's pid and command.
    """
    path = Path(os.path.abspath(folder)) / LOCK_NAME
    key = (threading.get_ident(), str(path))
    with _held_guard:
        mine = _held.get(key)
        if mine is not None:
            mine[1] += 1
    if mine is None:
        fd = _acquire(path, default_timeout() if timeout is None else timeout)
        with _held_guard:
            _held[key] = mine = [fd, 1]
    try:
        yield
    finally:
        with _held_guard:
            mine[1] -= 1
            last = mine[1] == 0
            if last:
                del _held[key]
        if last:
            os.close(mine[0])  # closing the only descriptor releases the flock
