"""The one hardened way to read a user's JSON: files, single documents and log lines.

Whatever a file holds, reading it ends in a decoded document or in a
:class:`~studio.errors.DataFileError` naming the file (and the line or field), never in
a traceback, a hang or an exhausted memory:

- only regular files are read (a named pipe or a device would block or never end), and
  at most ``max_bytes`` of them;
- the bytes must be UTF-8 (a UTF-8 byte-order mark is skipped); UTF-16 or Latin-1
  files are refused with the offset of the first bad byte;
- strict JSON numbers: ``NaN``, ``Infinity`` and ``1e400`` (read as infinity) are
  refused, naming the field, unless a caller allows ``Infinity`` at named fields;
  integers must be exact in every JSON reader (|n| <= 2**53 - 1);
- nesting deeper than ``max_depth`` is refused (no RecursionError);
- strings and keys must be valid Unicode (a ``\\ud800`` escape decodes to a lone
  surrogate that cannot be printed or written as UTF-8).
"""

from __future__ import annotations

import codecs
import json
import math
import os
import stat
from pathlib import Path
from typing import Any

from studio.errors import DataFileError

MAX_INT = 2**53 - 1
"""Largest integer magnitude accepted (exact in every JSON reader) [-]."""
MAX_DEPTH = 64
"""Deepest nesting of arrays and objects accepted [-]."""
MAX_BYTES = 64 * 2**20
"""Default size limit of a JSON file [bytes] (a library index of ~100,000 serves)."""


class _Refused(ValueError):
    """A JSON value outside the strict subset (raised inside the decoder's hooks)."""


def read_file_bytes(path: str | Path, *, max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (DataFileError if it is not one, cannot be
    read or is larger than ``max_bytes``)."""
    path = Path(path)
    try:
        with open(path, "rb", opener=_nonblocking) as fh:
            info = os.fstat(fh.fileno())
            if not stat.S_ISREG(info.st_mode):
                raise DataFileError(path, "not a regular file (a pipe, device or folder cannot be read as data)")
            if info.st_size > max_bytes:
                raise DataFileError(path, f"{info.st_size} bytes, more than the {max_bytes} bytes allowed")
            data = fh.read(max_bytes + 1)
    except DataFileError:
        raise
    except OSError as err:
        raise DataFileError(path, f"cannot read: {err.strerror or err}") from None
    if len(data) > max_bytes:
        raise DataFileError(path, f"more than the {max_bytes} bytes allowed")
    return data


def _nonblocking(path: str, flags: int) -> int:
    """Open without blocking on a FIFO (its type is refused right after)."""
    return os.open(path, flags | getattr(os, "O_NONBLOCK", 0))


def decode_text(data: bytes, path: str | Path, *, line: int | None = None) -> str:
    """``data`` as UTF-8 text (a leading byte-order mark dropped), else DataFileError with
    the offset of the first byte that is not UTF-8."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise not_utf8(path, err, line=line, skipped=_bom(data)) from None


def _bom(data: bytes) -> int:
    """Bytes of a leading UTF-8 byte-order mark (``utf-8-sig`` drops them before counting)."""
    return len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0


def not_utf8_message(err: UnicodeDecodeError, *, skipped: int = 0) -> str:
    """The project's one wording for text that is not UTF-8: the first bad byte and its
    offset (``err``'s offset plus ``skipped`` bytes the decoder did not see)."""
    bad = err.object[err.start] if err.start < len(err.object) else 0
    return f"not UTF-8 text (byte 0x{bad:02x} at offset {err.start + skipped}); save the file as UTF-8"


def not_utf8(path: str | Path, err: UnicodeDecodeError, *, line: int | None = None, skipped: int = 0) -> DataFileError:
    """DataFileError naming ``path`` (and ``line``) with :func:`not_utf8_message`."""
    where = f"line {line}: " if line is not None else ""
    return DataFileError(path, where + not_utf8_message(err, skipped=skipped))


def not_utf8_file(path: str | Path) -> DataFileError:
    """DataFileError for a text file that failed to decode while read as a stream (whose
    error counts from the stream's buffer, not the file): the file's first bad byte, its
    offset and line, found by decoding the file's bytes again (the error path only)."""
    data = read_file_bytes(path)
    try:
        data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        skipped = _bom(data)
        return not_utf8(path, err, line=data.count(b"\n", 0, err.start + skipped) + 1, skipped=skipped)
    return DataFileError(path, "not UTF-8 text; save the file as UTF-8")


def parse_json(
    text: str | bytes,
    path: str | Path,
    *,
    line: int | None = None,
    infinity_at: tuple[str, ...] = (),
    max_depth: int = MAX_DEPTH,
) -> Any:
    """Decode one strict JSON document (module doc) from ``text``; errors name ``path``,
    the field and, for a log, its ``line``. ``infinity_at``: field paths ending so that may
    hold ``Infinity`` (legacy files)."""
    where = f"line {line}: " if line is not None else ""
    if isinstance(text, bytes):
        text = decode_text(text, path, line=line)
    try:
        doc = json.loads(text, parse_constant=float, parse_int=_int)
    except (ValueError, RecursionError) as err:  # the rare path: a too deep text is named as such first
        _check_depth(_max_depth(text), path, where, max_depth)
        if isinstance(err, json.JSONDecodeError):
            raise DataFileError(
                path, f"{where}not valid JSON (line {err.lineno}, column {err.colno}): {err.msg}"
            ) from None
        if isinstance(err, _Refused):
            raise DataFileError(path, f"{where}{err}") from None
        raise DataFileError(path, f"{where}not valid JSON ({err or 'nested too deeply'})") from None
    _check_depth(_doc_depth(doc), path, where, max_depth)
    check_values(doc, path, prefix=where, infinity_at=infinity_at)
    return doc


def _check_depth(depth: int, path: str | Path, where: str, max_depth: int) -> None:
    if depth > max_depth:
        raise DataFileError(path, f"{where}nested {depth} levels deep, more than the {max_depth} allowed")


def check_values(
    doc: Any, path: str | Path, *, root: str = "", prefix: str = "", infinity_at: tuple[str, ...] = ()
) -> None:
    """DataFileError naming the field (``root`` + its path) unless every value of ``doc``
    is strict JSON: finite numbers (``Infinity`` only at fields ending in one of
    ``infinity_at``), integers within +-:data:`MAX_INT`, valid Unicode strings and keys."""
    stack: list[tuple[Any, str]] = [(doc, root)]
    while stack:  # iterative: deep nesting cannot exhaust the Python stack
        value, field = stack.pop()
        if isinstance(value, dict):
            for key, item in value.items():
                _text(key, f"{field} (a key)", path, prefix)
                stack.append((item, f"{field}.{key}" if field else key))
        elif isinstance(value, list):
            stack.extend((item, f"{field}[{i}]") for i, item in enumerate(value))
        elif isinstance(value, str):
            _text(value, field, path, prefix)
        elif isinstance(value, bool) or value is None:
            continue
        elif isinstance(value, int) and abs(value) > MAX_INT:
            raise DataFileError(
                path, f"{prefix}field '{field}': integer out of range (|n| > 2**53 - 1, {len(str(abs(value)))} digits)"
            )
        elif (
            isinstance(value, float)
            and not math.isfinite(value)
            and not (value > 0 and field.endswith(infinity_at) and infinity_at)
        ):
            raise DataFileError(path, f"{prefix}field '{field}': must be a finite number, got {value!r}")


def read_json_file(path: str | Path, *, max_bytes: int = MAX_BYTES, infinity_at: tuple[str, ...] = ()) -> Any:
    """Read and decode the strict JSON file ``path`` (module doc)."""
    return parse_json(read_file_bytes(path, max_bytes=max_bytes), path, infinity_at=infinity_at)


def lone_surrogate(text: str) -> int | None:
    """Position of the first lone surrogate in ``text`` (not valid Unicode: cannot be
    written as UTF-8), or None when the text is valid."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as err:
        return int(err.start)
    return None


def _text(text: str, where: str, path: str | Path, prefix: str = "") -> None:
    """DataFileError unless ``text`` is valid Unicode (no lone surrogate)."""
    pos = lone_surrogate(text)
    if pos is not None:
        raise DataFileError(
            path, f"{prefix}field '{where}' is not valid Unicode (lone surrogate {text[pos]!r} at position {pos})"
        )


def _int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > 4000:  # Python refuses > 4300 digits: a clear message instead
        raise _Refused(f"an integer of {digits} digits (|n| > 2**53 - 1)")
    return int(text)


def _doc_depth(doc: Any) -> int:
    """Deepest nesting of arrays and objects in a decoded document (iterative)."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(doc, 0)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict | list):
            deepest = max(deepest, depth + 1)
            stack.extend((item, depth + 1) for item in (value.values() if isinstance(value, dict) else value))
    return deepest


def _max_depth(text: str) -> int:
    """Deepest bracket nesting of ``text`` outside strings (for texts the decoder refused)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest
