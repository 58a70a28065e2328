"""JSON-lines logs: append, read back, a torn last line set aside, a missing newline repaired, a bad line named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from studio.errors import DataFileError
from studio.storage.jsonlog import TORN_SUFFIX, append_jsonl, read_jsonl


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
    assert (tmp_path / "log.jsonl.torn").read_bytes() == b'{"i": 3, "x"\n'  # and kept aside
    with pytest.raises(ValueError):
        append_jsonl(path, {"i": float("nan")})  # never a non-JSON number in a log


def test_a_bad_complete_line_is_an_error_naming_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    path.write_text(json.dumps({"i": 0}) + "\n" + "{nope}\n" + json.dumps({"i": 2}) + "\n")
    with pytest.raises(DataFileError, match=r"log.jsonl: line 2: not valid JSON"):
        read_jsonl(path, _parse)
    path.write_text(json.dumps({"i": 0}) + "\n" + json.dumps({"j": 1}) + "\n")  # parse rejects it (KeyError)
    with pytest.raises(DataFileError, match="line 2"):
        read_jsonl(path, _parse)
    assert path.read_text().count("\n") == 2  # nothing cut from a file with a bad complete line


def test_append_repairs_a_complete_last_line_without_newline(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    path.write_text(json.dumps({"i": 0}) + "\n" + json.dumps({"i": 1}))  # an editor dropped the final newline
    append_jsonl(path, {"i": 2}, parse=_parse)
    assert path.read_text() == '{"i": 0}\n{"i": 1}\n{"i": 2}\n'  # never glued
    assert read_jsonl(path, _parse) == [0, 1, 2]


def test_append_refuses_a_torn_last_line_and_keeps_the_file(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    for torn in (b'{"i": 0}\n{"i": 1, "x', b'{"i": 0}\n{"j": 1}'):  # cut JSON; JSON that parse rejects
        path.write_bytes(torn)
        with pytest.raises(DataFileError, match=r"log.jsonl: line 2: incomplete last line"):
            append_jsonl(path, {"i": 2}, parse=_parse)
        assert path.read_bytes() == torn


def test_read_keeps_a_complete_unterminated_record_and_sets_a_torn_one_aside(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "log.jsonl"
    path.write_text('{"i": 0}\n{"i": 1}')
    assert read_jsonl(path, _parse) == [0, 1]  # kept, and the newline repaired for the next append
    assert path.read_text() == '{"i": 0}\n{"i": 1}\n'
    path.write_text('{"i": 0}\n{"i": 1, "x')
    with caplog.at_level("WARNING", logger="studio.storage.jsonlog"):
        assert read_jsonl(path, _parse) == [0]
    assert path.read_text() == '{"i": 0}\n'
    assert (tmp_path / ("log.jsonl" + TORN_SUFFIX)).read_text() == '{"i": 1, "x\n'  # not lost: set aside
    assert "torn last line" in caplog.text and "log.jsonl.torn" in caplog.text
