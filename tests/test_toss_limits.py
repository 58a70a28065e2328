"""Work limits and physical bounds of toss recordings files (issue 18: an 11 MB toss CSV kept
``serve-studio toss`` busy for more than 4 minutes; times of 1e300 ended in a traceback).

Classes covered: a file over the size limit, a named pipe, non-UTF-8 text, too many rows,
tosses or samples per toss (refused in seconds, naming the file, the line and the limit), times
and positions outside their physical bounds, samples closer than the least step, a toss
spanning minutes; the 11 MB file of the report through ``serve-studio toss`` (exit 2 within
seconds); a 200-toss file modelled in seconds (the t_lift fit is linear in the tosses now),
with the same fit as the dense least squares it replaced.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

import studio.toss.recordings as recordings
from studio.errors import DataFileError, InvalidInputError
from studio.toss.recordings import MAX_CSV_BYTES, MAX_SAMPLES_PER_TOSS, MAX_TOSSES, load_recordings_csv

HEADER = "toss_id,t,x,y,z"


def _rows(tid: str, n: int = 25, t0: float = 0.0, step: float = 0.005) -> list[str]:
    return [f"{tid},{t0 + step * k:.6f},-1.6,0.3,{0.1 + 0.01 * k:.4f}" for k in range(n)]


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _refused(path: Path, match: str, seconds: float = 5.0) -> str:
    t0 = time.perf_counter()
    with pytest.raises(DataFileError, match=match) as info:
        load_recordings_csv(path)
    assert time.perf_counter() - t0 < seconds
    assert path.name in str(info.value)
    return str(info.value)


@pytest.mark.parametrize(
    ("rows", "match"),
    [
        ([*_rows("a")[:3], "a,1e300,-1.6,0.3,0.2"], r"line 5, column t: 1e300 s is outside \[-1e\+10, 1e\+10\] s"),
        ([*_rows("a")[:3], "a,0.02,-1e5,0.3,0.2"], r"line 5, column x: -1e5 m is outside \[-100, 100\] m"),
        ([*_rows("a")[:3], "a,0.02,-1.6,0.3,1e300"], r"line 5, column z: 1e300 m is outside"),
        ([*_rows("a")[:3], "a,0.010001,-1.6,0.3,0.2"], r"line 5, column t: time 0.010001 of toss 'a' not after 0.01 \(line 4\) by at least 1e-05 s"),
        ([*_rows("a")[:3], "a,61.0,-1.6,0.3,0.2"], r"line 5, column t: toss 'a' spans 61 s from its first sample; at most 60.0 s"),
    ],
)  # fmt: skip
def test_values_outside_physical_bounds_name_file_line_and_field(tmp_path: Path, rows: list[str], match: str) -> None:
    _refused(_write(tmp_path / "bounds.csv", [HEADER, *rows, *_rows("b")]), match)


def test_a_unix_time_clock_is_accepted(tmp_path: Path) -> None:
    recs = load_recordings_csv(_write(tmp_path / "unix.csv", [HEADER, *_rows("a", t0=1.8e9)]))
    assert recs.recordings[0].t[0] == pytest.approx(1.8e9)


def test_too_many_tosses_samples_or_rows_are_refused_in_seconds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    many = [row for k in range(MAX_TOSSES + 1) for row in _rows(f"t{k}", 20)]
    text = _refused(
        _write(tmp_path / "tosses.csv", [HEADER, *many]), "column toss_id: toss 't500' is one more than the 500 tosses"
    )
    assert f"line {MAX_TOSSES * 20 + 2}" in text
    long = _rows("a", MAX_SAMPLES_PER_TOSS + 1, step=0.001)
    _refused(
        _write(tmp_path / "long.csv", [HEADER, *long]),
        f"line {MAX_SAMPLES_PER_TOSS + 2}: toss 'a' has more than 5000 samples",
    )
    monkeypatch.setattr(recordings, "MAX_SAMPLES", 30)
    _refused(_write(tmp_path / "rows.csv", [HEADER, *_rows("a"), *_rows("b")]), "line 32: more than 30 samples")


def test_an_oversized_file_a_pipe_and_utf16_are_refused_before_parsing(tmp_path: Path) -> None:
    big = tmp_path / "big.csv"
    with open(big, "wb") as fh:
        fh.truncate(MAX_CSV_BYTES + 1)  # sparse: nothing is written
    _refused(big, f"{MAX_CSV_BYTES + 1} bytes, more than the {MAX_CSV_BYTES} bytes allowed", seconds=1.0)
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    _refused(fifo, "not a regular file", seconds=1.0)
    utf16 = tmp_path / "utf16.csv"
    utf16.write_text("\n".join([HEADER, *_rows("a")]), encoding="utf-16")
    _refused(utf16, r"line 1: not UTF-8 text \(byte 0")
    bom = tmp_path / "bom.csv"
    bom.write_text("\n".join([HEADER, *_rows("a")]), encoding="utf-8-sig")  # a UTF-8 byte-order mark is fine
    assert len(load_recordings_csv(bom)) == 1


def _report_sized_file(path: Path) -> Path:
    """~11 MB like the reported file: 1,300 tosses of 200 samples at 200 Hz."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(HEADER + "\n")
        for k in range(1300):
            fh.write("\n".join(_rows(f"right_{k:04d}", 200, t0=1.8e9 + 100.0 * k)) + "\n")
    return path


def test_the_reported_11_mb_file_ends_in_seconds_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from studio.cli import main

    path = _report_sized_file(tmp_path / "huge.csv")
    assert 10e6 < path.stat().st_size < MAX_CSV_BYTES
    t0 = time.perf_counter()
    code = main(["toss", "--csv", str(path)])
    elapsed = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and elapsed < 20.0, (code, elapsed, err)
    assert "huge.csv: line 100002, column toss_id: toss 'right_0500' is one more than the 500 tosses allowed" in err


@pytest.fixture(scope="module")
def right_recordings() -> recordings.TossRecordings:
    from studio.toss.defaults import default_recordings_path

    return load_recordings_csv(default_recordings_path("right"))


def test_a_200_toss_file_is_modelled_in_seconds(right_recordings: recordings.TossRecordings) -> None:
    from studio.robot.model import load_robot
    from studio.toss.defaults import default_toss
    from studio.toss.model import TossModel

    many = tuple(
        recordings.TossRecording(toss_id=f"{r.toss_id}_{k}", t=r.t + 100.0 * k, p=r.p)
        for k in range(10)
        for r in right_recordings.recordings
    )
    primitive = default_toss(load_robot(), "right")
    t0 = time.perf_counter()
    model = TossModel.from_recordings(primitive, recordings.TossRecordings(many))
    elapsed = time.perf_counter() - t0
    assert model.n_tosses == 200 and elapsed < 30.0, elapsed  # 55 s with the dense t_lift fit, 0.7 s now
    single = TossModel.from_recordings(primitive, right_recordings)
    assert model.t_lift == pytest.approx(single.t_lift, abs=1e-4)  # the same tosses ten times over (times shifted)


def _dense_rss(K: int, k_all: np.ndarray, n_k: np.ndarray, x: np.ndarray, r: np.ndarray) -> float:
    """The t_lift fit's RSS by the dense least squares used before (2K-1 unknowns)."""
    s1, s2 = (np.bincount(k_all, weights=w, minlength=K) for w in (x, x * x))
    r0 = np.stack([np.bincount(k_all, weights=r[:, j], minlength=K) for j in range(3)], axis=1)
    r1 = np.stack([np.bincount(k_all, weights=x * r[:, j], minlength=K) for j in range(3)], axis=1)
    ata = np.zeros((2 * K - 1, 2 * K - 1))
    ata[np.arange(K), np.arange(K)] = n_k
    j = np.arange(K - 1)
    ata[j, K + j] = ata[K + j, j] = s1[:-1]
    ata[K - 1, K:] = ata[K:, K - 1] = -s1[-1]
    ata[K:, K:] = s2[-1]
    ata[K + j, K + j] += s2[:-1]
    atr = np.vstack([r0, r1[:-1] - r1[-1:]])
    coef, *_ = np.linalg.lstsq(ata, atr, rcond=None)
    return float(np.sum(r * r) - np.sum(coef * atr))


@pytest.mark.parametrize("case", ["plain", "no samples", "none after", "one after", "only one with slope"])
def test_the_linear_lift_fit_equals_the_dense_least_squares(case: str) -> None:
    from studio.toss.lift_time import _constrained_rss

    rng = np.random.default_rng(7)
    K, ts = 6, []
    for k in range(K):
        t = np.sort(rng.uniform(-0.1, 0.2, 40))
        if (case == "no samples" and k == 2) or (case == "only one with slope" and k < K - 1):
            t = t[t < 0] if case != "no samples" else t[:0]
        if case == "none after" and k == 3:
            t = t[t < 0]
        if case == "one after" and k == 0:
            t = np.concatenate([t[t < 0], [0.05]])
        ts.append(t)
    k_all = np.concatenate([np.full(t.size, k) for k, t in enumerate(ts)])
    t_all = np.concatenate(ts)
    n_k = np.bincount(k_all, minlength=K).astype(float)
    x = np.where(t_all >= 0, t_all, 0.0)
    b, d = rng.normal(0, 0.003, (K, 3)), rng.normal(0, 0.05, (K, 3))
    r = b[k_all] + x[:, None] * d[k_all] + rng.normal(0, 0.003, (t_all.size, 3))
    assert _constrained_rss(K, k_all, n_k, x, r) == pytest.approx(_dense_rss(K, k_all, n_k, x, r), rel=1e-12)


def test_generating_more_tosses_than_can_be_read_is_refused_up_front(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from studio.cli import main

    with pytest.raises(SystemExit) as stop:  # the command line's own bound
        main(["toss", "--generate", "--out", str(tmp_path / "gen"), "--n", str(MAX_TOSSES + 1)])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "argument --n: '501' is outside the allowed range [2, 500]" in err
    assert not (tmp_path / "gen").exists()
    from studio.toss.defaults import generate_default_recordings

    with pytest.raises(InvalidInputError, match=r"n must be a whole number of tosses in \[2, 500\], got 501"):
        generate_default_recordings(tmp_path / "gen", n=MAX_TOSSES + 1)  # the function's, for callers from Python
    assert not (tmp_path / "gen" / "right.csv").exists()


def test_the_other_sides_recordings_are_refused_naming_the_file(capsys: pytest.CaptureFixture[str]) -> None:
    from studio.cli import main
    from studio.toss.defaults import default_recordings_path

    left = default_recordings_path("left")
    assert main(["toss", "--side", "right", "--csv", str(left)]) == 2
    err = capsys.readouterr().err
    assert f"{left}: toss 'left_00': while in the cup the ball is 0.600 m from the cup path of toss_right" in err
    assert "Traceback" not in err
    assert main(["toss", "--side", "left", "--csv", str(left)]) == 0  # its own side
