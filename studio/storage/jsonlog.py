"""Append-only JSON-lines logs that survive being killed mid-write.

Every record is one line written by a single ``write`` and flushed with ``fsync``, so a
process killed while logging leaves at most its last line without the closing newline.
This module is the one writer of the program's JSON-lines logs (the match log, the
optimization and robustify run logs). What it does with a last line that lacks its newline:

- a *complete* record (valid JSON object that ``parse`` accepts; e.g. a hand-edited file
  whose editor dropped the final newline): the newline is added before anything is
  appended (:func:`ensure_line_end`), so records are never glued together;
- a *torn* line (anything else): :func:`append_jsonl` refuses to append (DataFileError
  naming the file and the line; nothing written, the file kept byte for byte), because
  gluing would corrupt the new record too and dropping would silently lose data; the
  match log is such a case (a point recorded by hand cannot be redone: the user decides).
  :func:`read_jsonl` (the resume of a run log, whose records are redone by the resumed
  work) moves the torn bytes to ``<log>.torn`` (appended, one line per cut; nothing is
  lost) and cuts them off the log, with a warning on the ``studio.storage.jsonlog`` logger.

Any malformed complete line is an error that names the file and the line.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, TypeVar

from studio.errors import DataFileError
from studio.storage.jsonfile import parse_json, read_file_bytes

T = TypeVar("T")
TORN_SUFFIX = ".torn"
"""Suffix of the file next to a log that receives the torn last lines cut off it."""
_LOG = logging.getLogger("studio.storage.jsonlog")
_BLOCK = 1 << 16


def write_line(fh: IO[str], doc: dict[str, Any]) -> None:
    """One record on an open text file: one write of the whole line, flushed and fsynced.
    The file must end with a newline (:func:`ensure_line_end` before opening it)."""
    fh.write(json.dumps(doc, allow_nan=False) + "\n")
    fh.flush()
    os.fsync(fh.fileno())


def _tail(path: Path) -> bytes:
    """The bytes after the last newline of ``path`` (empty: absent, empty or ends in one)."""
    try:
        fh = open(path, "rb")
    except FileNotFoundError:
        return b""
    with fh:
        end = fh.seek(0, os.SEEK_END)
        tail = b""
        while end > 0:
            start = max(0, end - _BLOCK)
            fh.seek(start)
            tail = fh.read(end - start) + tail
            cut = tail.rfind(b"\n")
            if cut >= 0:
                return tail[cut + 1 :]
            end = start
        return tail


def _complete(tail: bytes, parse: Callable[[Any], Any] | None) -> bool:
    """True when ``tail`` is one whole record: a JSON object that ``parse`` accepts."""
    try:
        doc = json.loads(tail)
        if not isinstance(doc, dict):
            return False
        if parse is not None:
            parse(doc)
    except (ValueError, KeyError, TypeError, RecursionError):
        return False
    return True


def _line_number(path: Path) -> int:
    """Number of the last line of ``path`` (1-based; only for messages)."""
    with open(path, "rb") as fh:
        return sum(block.count(b"\n") for block in iter(lambda: fh.read(_BLOCK), b"")) + 1


def ensure_line_end(path: Path, parse: Callable[[Any], Any] | None = None) -> None:
    """Make ``path`` end with a newline before records are appended to it.

    Nothing to do for an absent or empty file or one that ends with a newline. A last line
    without its newline that is a complete record (JSON object ``parse`` accepts) gets
    its newline (appended, fsynced). Otherwise (a torn line) DataFileError names the file
    and the line, and the file is left as it is.
    """
    tail = _tail(path)
    if not tail:
        return
    if tail.strip() and not _complete(tail, parse):
        shown = tail[:60].decode("utf-8", "replace")
        raise DataFileError(
            path,
            f"line {_line_number(path)}: incomplete last line without a newline ({shown!r}{'...' if len(tail) > 60 else ''}); "
            "nothing appended, the file is unchanged: complete or remove that line (a process killed while writing leaves one)",
        )
    with open(path, "ab") as fh:
        fh.write(b"\n")
        fh.flush()
        os.fsync(fh.fileno())


def append_jsonl(path: Path, doc: dict[str, Any], parse: Callable[[Any], Any] | None = None) -> None:
    """Append one record to ``path`` (see :func:`write_line`), after
    :func:`ensure_line_end` (``parse`` judges whether an unterminated last line is a
    complete record; DataFileError, nothing appended, when it is torn)."""
    line = json.dumps(doc, allow_nan=False) + "\n"  # a bad record fails before the file is touched
    ensure_line_end(path, parse)
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(line)
        fh.flush()
        os.fsync(fh.fileno())


def _set_aside(path: Path, torn: bytes) -> None:
    """Append the torn bytes of ``path`` as one line to ``<path>.torn`` (fsynced)."""
    aside = path.with_name(path.name + TORN_SUFFIX)
    with open(aside, "ab") as fh:
        fh.write(torn.replace(b"\n", b" ") + b"\n")
        fh.flush()
        os.fsync(fh.fileno())
    _LOG.warning(
        "%s: torn last line (%d bytes, left by an interrupted write) moved to %s; its work is redone",
        path,
        len(torn),
        aside,
    )


def _record(path: Path, number: int, line: bytes, parse: Callable[[Any], T]) -> T:
    """``parse`` of one strict-JSON log line; DataFileError naming the file and line."""
    doc = parse_json(line, path, line=number)
    try:
        return parse(doc)
    except (ValueError, KeyError, TypeError, OverflowError, RecursionError) as exc:
        raise DataFileError(path, f"line {number}: not a record of this log ({exc})") from None


def read_jsonl(path: Path, parse: Callable[[Any], T]) -> list[T]:
    """The records of ``path`` (``parse`` of each decoded line; an absent file is empty),
    for resuming the work the log records.

    A last line without its newline is kept (and gets its newline) when it is a complete
    record; otherwise it is torn: its bytes are moved to ``<path>.torn`` and cut off the
    log, with a warning (module doc). Raises DataFileError naming the file and line when a
    complete line is not JSON or ``parse`` rejects it (ValueError, KeyError or TypeError);
    the file is untouched then.
    """
    if not path.exists():
        return []
    raw = read_file_bytes(path)
    end = raw.rfind(b"\n") + 1
    out: list[T] = []
    lines = raw[:end].split(b"\n")[:-1]
    for k, line in enumerate(lines):
        if line.strip():
            out.append(_record(path, k + 1, line, parse))
    tail = raw[end:]
    if not tail.strip() or _complete(tail, parse):
        if tail.strip():
            out.append(_record(path, len(lines) + 1, tail, parse))
        ensure_line_end(path, parse)
    else:
        _set_aside(path, tail)
        with open(path, "r+b") as fh:
            fh.truncate(end)
            os.fsync(fh.fileno())
    return out
