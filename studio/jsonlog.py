"""Append-only JSON-lines logs that survive being killed mid-write.

Every record is one line written by a single ``write`` and flushed with ``fsync``, so a
process killed while logging leaves at most its last line without the closing newline
(torn). :func:`read_jsonl` cuts such a torn line off the file (the record is lost and
is redone by the resumed work); any other malformed line is an error that names the file
and the line. Used by the optimization and robustify run logs.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, TypeVar

from studio.errors import DataFileError

T = TypeVar("T")


def write_line(fh: IO[str], doc: dict[str, Any]) -> None:
    """One record on an open text file: one write of the whole line, flushed and fsynced."""
    fh.write(json.dumps(doc, allow_nan=False) + "\n")
    fh.flush()
    os.fsync(fh.fileno())


def append_jsonl(path: Path, doc: dict[str, Any]) -> None:
    """Append one record to ``path`` (see :func:`write_line`)."""
    with open(path, "a", encoding="utf-8") as fh:
        write_line(fh, doc)


def read_jsonl(path: Path, parse: Callable[[Any], T]) -> list[T]:
    """The records of ``path`` (``parse`` of each decoded line; an absent file is empty).

    A last line without its newline (torn by a kill) is cut off the file. Raises
    DataFileError naming the file and line when a complete line is not JSON or ``parse``
    rejects it (ValueError, KeyError or TypeError).
    """
    if not path.exists():
        return []
    raw = path.read_bytes()
    end = raw.rfind(b"\n") + 1  # bytes after the last newline belong to a torn write
    out: list[T] = []
    for k, line in enumerate(raw[:end].split(b"\n")[:-1]):
        if not line.strip():
            continue
        try:
            out.append(parse(json.loads(line)))
        except (ValueError, KeyError, TypeError) as exc:
            raise DataFileError(path, f"line {k + 1}: not a record of this log ({exc})") from None
    if end < len(raw):
        with open(path, "r+b") as fh:
            fh.truncate(end)
    return out
