"""A bad-input corpus, generated here by class, run through the command line.

Classes covered: serve files (encodings, nesting, non-finite and huge numbers, lone
surrogates, wrong types, unknown fields, values outside physical ranges, empty files,
FIFOs, folders, missing files); library indexes (the same classes inside entries);
match logs (bad lines); command-line numbers out of range; a file system that refuses a
write. Elsewhere: toss CSVs (tests/test_toss_limits.py), run logs and kills
(tests/test_optimizer.py, tests/test_training_ray*.py), concurrent writers
(tests/test_filelock.py, tests/test_library.py), the studio's inputs and foreign origins (tests/test_ui_inputs.py,
tests/test_app_browser.py). For each case every command must exit with its error code and
a message naming the file and the problem, never a traceback, and leave every file it
could not read byte for byte as it was.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from studio.cli import main

ROOT = Path(__file__).resolve().parent.parent
GOOD_SERVE = json.loads((ROOT / "examples" / "serves" / "topspin_right.json").read_text(encoding="utf-8"))


def _serve_bytes(mutate: Callable[[dict], object]) -> bytes:  # type: ignore[type-arg]
    doc = json.loads(json.dumps(GOOD_SERVE))
    mutate(doc)
    return json.dumps(doc).encode("utf-8")


def _set(path: str, value: object) -> Callable[[dict], None]:  # type: ignore[type-arg]
    keys = path.split(".")

    def mutate(doc: dict) -> None:  # type: ignore[type-arg]
        for k in keys[:-1]:
            doc = doc[k]
        doc[keys[-1]] = value

    return mutate


SERVE_CASES: dict[str, tuple[bytes | None, str]] = {
    "utf16": (json.dumps(GOOD_SERVE).encode("utf-16"), "not UTF-8 text"),
    "latin1-name": (json.dumps({**GOOD_SERVE, "name": "é"}, ensure_ascii=False).encode("latin-1"), "not UTF-8 text"),
    "deep-nesting": (b"[" * 100_000 + b"]" * 100_000, "levels deep"),
    "nan-tau": (json.dumps(GOOD_SERVE).replace('"tau": ', '"tau": NaN, "x_": ', 1).encode(), "must be a finite number"),
    "huge-float": (_serve_bytes(_set("params.velocity", [0, 0, 0])).replace(b"[0, 0, 0]", b"[1e400, 0, 0]"), "must be a finite number"),
    "huge-int": (_serve_bytes(_set("params.tau", 0)).replace(b'"tau": 0', b'"tau": ' + b"9" * 5000), "an integer of 5000 digits"),
    "int-beyond-float": (_serve_bytes(_set("params.tau", 0)).replace(b'"tau": 0', b'"tau": ' + b"9" * 400), "integer out of range"),
    "lone-surrogate-name": (_serve_bytes(_set("name", "x")).replace(b'"name": "x"', b'"name": "\\ud800"'), "not valid Unicode"),
    "string-tau": (_serve_bytes(_set("params.tau", "soon")), "params.tau': must be a finite number"),
    "list-params": (_serve_bytes(_set("params", [1, 2])), "field 'params': must be an object"),
    "typo-field": (_serve_bytes(_set("limit_scales", {"acceleration": 1.5})), "unknown fields ['limit_scales']"),
    "typo-param": (_serve_bytes(_set("params.t_retrun", 0.7)), "unknown keys ['t_retrun']"),
    "return-1e6-s": (_serve_bytes(_set("params.t_return", 1e6)), "t_return = 1e+06 is outside the allowed range"),
    "velocity-1e300": (_serve_bytes(_set("params.velocity", [1e300, 0, 0])), "velocity = 1e+300 is outside the allowed range"),
    "negative-tau": (_serve_bytes(_set("params.tau", -1.0)), "tau = -1 is outside the allowed range"),
    "bad-side": (_serve_bytes(_set("side", "middle")), "field 'side'"),
    "empty": (b"", "not valid JSON"),
    "not-an-object": (b"[1, 2, 3]", "must hold a JSON object"),
    "fifo": (None, "not a regular file"),
}


def _make(path: Path, content: bytes | None) -> None:
    if content is None:
        os.mkfifo(path)
    else:
        path.write_bytes(content)


@pytest.mark.parametrize("case", sorted(SERVE_CASES))
def test_evaluate_refuses_a_bad_serve_file(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    content, message = SERVE_CASES[case]
    path = tmp_path / f"{case}.json"
    _make(path, content)
    before = path.read_bytes() if content is not None else None
    assert main(["evaluate", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{case}.json" in err and message in err and "Traceback" not in err, err
    if before is not None:
        assert path.read_bytes() == before


def test_missing_file_and_folder_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", str(tmp_path / "absent.json")]) == 2
    assert "absent.json: cannot read" in capsys.readouterr().err
    (tmp_path / "dir.json").mkdir()
    assert main(["evaluate", str(tmp_path / "dir.json")]) == 2
    assert "dir.json: cannot read" in capsys.readouterr().err


def _index(serves: list[dict]) -> dict:  # type: ignore[type-arg]
    return {"schema": "serve-studio/library@1", "serves": serves}


@pytest.fixture(scope="module")
def good_library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A library with one exported example serve (its index is the template below)."""
    lib = tmp_path_factory.mktemp("good") / "lib"
    assert main(["evaluate", str(ROOT / "examples" / "serves" / "topspin_right.json"), "--export", str(lib)]) == 0
    return lib


INDEX_CASES: dict[str, tuple[Callable[[bytes], bytes], str]] = {
    "nan-net": (lambda raw: raw.replace(b'"net": {', b'"net": {"nan": NaN, ', 1), "must be a finite number"),
    "string-net": (lambda raw: _edit(raw, lambda d: d["serves"][0].__setitem__("net", "fast")), "serves[0].net"),
    "huge-counter": (lambda raw: _edit(raw, lambda d: d["serves"][0]["usage"].__setitem__("used", 10**400)), "serves[0].usage.used"),
    "surrogate-name": (lambda raw: raw.replace(b'"name": "', b'"name": "\\ud800', 1), "not valid Unicode"),
    "utf16": (lambda raw: raw.decode("utf-8").encode("utf-16"), "not UTF-8 text"),
    "deep": (lambda raw: b"[" * 5000 + b"]" * 5000, "levels deep"),
    "truncated": (lambda raw: raw[: len(raw) // 2], "not valid JSON"),
}


def _edit(raw: bytes, change: Callable[[dict], object]) -> bytes:  # type: ignore[type-arg]
    doc = json.loads(raw)
    change(doc)
    return json.dumps(doc).encode("utf-8")


def _digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.mark.parametrize("case", sorted(INDEX_CASES))
def test_no_command_rewrites_a_corrupt_index(case: str, good_library: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    lib = tmp_path / "lib"
    shutil.copytree(good_library, lib)
    corrupt, message = INDEX_CASES[case]
    index = lib / "index.json"
    index.write_bytes(corrupt(index.read_bytes()))
    sid = json.loads(good_library.joinpath("index.json").read_text())["serves"][0]["id"]
    before = _digest(lib)
    commands = [
        (["library", "validate", str(lib)], 1),
        (["library", "list", str(lib)], 2),
        (["library", "record", str(lib), "--serve", sid, "--winner", "robot"], 2),
        (["library", "prune", str(lib)], 2),
        (["evaluate", str(ROOT / "examples" / "serves" / "topspin_left.json"), "--export", str(lib)], 2),
    ]
    for argv, code in commands:
        assert main(argv) == code, argv
        err = capsys.readouterr().err
        assert "index.json" in err and message in err and "Traceback" not in err, (argv, err)
    assert _digest(lib) == before  # nothing rewritten, nothing added


MATCH_CASES: dict[str, tuple[bytes, str]] = {
    "not-utf8": (b'{"time": "\xff"}\n', "line 1: not UTF-8 text"),
    "nan": (b'{"time": NaN}\n', "line 1: field 'time': must be a finite number"),
    "wrong-type": (b'{"time": "2026-01-01T00:00:00+00:00", "server": "robot", "serve": 5, "winner": "robot", "ace": false}\n', "line 1"),
    "deep": (b"[" * 1000 + b"]" * 1000 + b"\n", "line 1: nested 1000 levels deep"),
}


@pytest.mark.parametrize("case", sorted(MATCH_CASES))
def test_a_bad_match_log_is_named_and_kept(case: str, good_library: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    lib = tmp_path / "lib"
    shutil.copytree(good_library, lib)
    content, message = MATCH_CASES[case]
    log = lib / "matches.jsonl"
    log.write_bytes(content)
    sid = json.loads((lib / "index.json").read_text())["serves"][0]["id"]
    before = _digest(lib)
    for argv in (["library", "stats", str(lib)], ["library", "record", str(lib), "--serve", sid, "--winner", "robot"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "matches.jsonl" in err and message in err and "Traceback" not in err, (argv, err)
    assert _digest(lib) == before


def test_the_real_command_prints_no_traceback(tmp_path: Path) -> None:
    """One case through a separate process: exit code 2, the message, no traceback."""
    path = tmp_path / "bad.json"
    path.write_bytes(SERVE_CASES["utf16"][0] or b"")
    out = subprocess.run([sys.executable, "-m", "studio.cli", "evaluate", str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "bad.json: not UTF-8 text" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["optimize", "--workers", "24000"], "argument --workers: '24000' is outside the allowed range [1, 64]"),
        (["optimize", "--iterations", "nan"], "argument --iterations: 'nan' is not an integer"),
        (["optimize", "--iterations", "-3"], "argument --iterations: '-3' is outside the allowed range [0, 10000]"),
        (["evaluate", "x.json", "--legal-fraction", "nan"], "argument --legal-fraction: 'nan' is outside the allowed range [0, 1]"),
        (["evaluate", "x.json", "--tosses", "1e12"], "argument --tosses: '1e12' is not an integer"),
        (["train", "--count", "0"], "argument --count: '0' is outside the allowed range [1, 10000]"),
        (["app", "--port", "70000"], "argument --port: '70000' is outside the allowed range [1, 65535]"),
    ],
)
def test_command_line_numbers_are_bounded(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_a_file_system_refusal_is_a_message_naming_the_path(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Class: the file system refuses a write (here a file where a folder goes; disk full and
    permissions take the same path): exit 2 with the path, no traceback."""
    blocker = tmp_path / "file"
    blocker.write_text("x", encoding="utf-8")
    code = main(["toss", "--generate", "--out", str(blocker / "sub"), "--n", "3"])
    err = capsys.readouterr().err
    assert code == 2 and f"{blocker / 'sub'}: Not a directory" in err and "Traceback" not in err
    assert blocker.read_text(encoding="utf-8") == "x"


def test_not_utf8_offsets_count_a_byte_order_mark() -> None:
    """``utf-8-sig`` counts after the byte-order mark; the message gives the file's offset."""
    from studio.errors import DataFileError
    from studio.storage.jsonfile import decode_text

    for data, offset in ((b'{"a": "caf\xe9"}', 10), (b'\xef\xbb\xbf{"a": "caf\xe9"}', 13)):
        with pytest.raises(DataFileError, match=rf"f\.json: not UTF-8 text \(byte 0xe9 at offset {offset}\)"):
            decode_text(data, "f.json")
        assert data[offset] == 0xE9
