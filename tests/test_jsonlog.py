"""JSON-lines logs: append, read back, a torn last line cut off, a bad line named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from studio.errors import DataFileError
from studio.jsonlog import append_jsonl, read_jsonl


def _parse(d: object) -> int:
    assert isinstance(d, dict)
    return int(d["i"])


def test_round_trip_and_torn_last_line(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    assert read_jsonl(path, _parse) == []  # absent: empty
    for i in range(3):
        append_jsonl(path, {"i": i})
    intact = path.read_bytes()
    path.write_bytes(intact + b'{"i": 3, "x"')  # killed mid-write
    assert read_jsonl(path, _parse) == [0, 1, 2]
    assert path.read_bytes() == intact  # the torn bytes are cut off, the rest untouched
    with pytest.raises(ValueError):
        append_jsonl(path, {"i": float("nan")})  # never a non-JSON number in a log


def test_a_bad_complete_line_is_an_error_naming_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    path.write_text(json.dumps({"i": 0}) + "\n" + "{nope}\n" + json.dumps({"i": 2}) + "\n")
    with pytest.raises(DataFileError, match=r"log.jsonl: line 2: not a record"):
        read_jsonl(path, _parse)
    path.write_text(json.dumps({"i": 0}) + "\n" + json.dumps({"j": 1}) + "\n")  # parse rejects it (KeyError)
    with pytest.raises(DataFileError, match="line 2"):
        read_jsonl(path, _parse)
    assert path.read_text().count("\n") == 2  # nothing cut from a file with a bad complete line
