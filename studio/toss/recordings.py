"""Toss recordings (synthetic or real) and their ``toss_id,t,x,y,z`` CSV format.

A recording holds the ball centre positions of one toss as a tracking system measured
them, on the recording's own clock (any origin); world frame, SI units.

Work limits of a recordings file (issue 18: an 11 MB file of ~1,300 tosses kept
``serve-studio toss`` busy for more than 4 minutes): at most :data:`MAX_CSV_BYTES`,
:data:`MAX_SAMPLES` rows, :data:`MAX_TOSSES` tosses of at most
:data:`MAX_SAMPLES_PER_TOSS` samples; times within :data:`MAX_ABS_TIME`, samples of a toss
at least :data:`MIN_SAMPLE_STEP` apart and within :data:`MAX_TOSS_DURATION`, positions
within :data:`MAX_ABS_POSITION`. A file within them is read and modelled in seconds, and
the file of the report is refused early (figures: ``docs/measured.md``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np
import numpy.typing as npt

from studio.errors import DataFileError, InvalidInputError

FloatArray = npt.NDArray[np.float64]

MIN_SAMPLES_PER_TOSS: Final[int] = 20
"""Fewest samples a recorded toss must have (0.1 s at 200 Hz)."""

CSV_COLUMNS: Final[tuple[str, ...]] = ("toss_id", "t", "x", "y", "z")
"""Required columns of a toss recording CSV file."""

MAX_CSV_BYTES: Final[int] = 16 * 2**20
"""Largest recordings file read [bytes] (the shipped ones: ~170 KB for 20 tosses)."""
MAX_SAMPLES: Final[int] = 200_000
"""Most data rows (samples, all tosses) in one recordings file."""
MAX_TOSSES: Final[int] = 500
"""Most tosses in one recordings file."""
MAX_SAMPLES_PER_TOSS: Final[int] = 5_000
"""Most samples of one toss (5 s at 1 kHz; the shipped tosses: ~200 at 200 Hz)."""
MAX_ABS_TIME: Final[float] = 1e10
"""Largest time magnitude [s] (a Unix time stamp is ~1.8e9 s)."""
MIN_SAMPLE_STEP: Final[float] = 1e-5
"""Least time between two samples of a toss [s] (100 kHz; trackers run at 100-1000 Hz)."""
MAX_TOSS_DURATION: Final[float] = 60.0
"""Longest time span of one toss's samples [s] (a toss lasts ~1 s)."""
MAX_ABS_POSITION: Final[float] = 100.0
"""Largest position coordinate magnitude [m] (world frame: origin at the table centre)."""


@dataclass(frozen=True, eq=False)
class TossRecording:
    """One recorded toss: ball centre positions from a tracking system.

    Times are on the recording's own clock (any origin); positions in the world frame.
    """

    toss_id: str
    """Identifier of the toss, unique within its :class:`TossRecordings`."""
    t: FloatArray
    """Sample times (M,) [s], strictly increasing, on the recording clock."""
    p: FloatArray
    """Ball centre positions (M, 3) [m], world frame."""

    def __post_init__(self) -> None:
        if not self.toss_id or any(ch in self.toss_id for ch in ',\n\r"') or self.toss_id != self.toss_id.strip():
            raise InvalidInputError(
                f"TossRecording: toss_id {self.toss_id!r} must be non-empty, without commas, quotes, newlines or surrounding spaces"
            )
        t = np.array(self.t, dtype=float)
        p = np.array(self.p, dtype=float)
        if t.ndim != 1 or p.shape != (t.size, 3):
            raise InvalidInputError(
                f"TossRecording {self.toss_id!r}: t must be (M,) and p (M, 3), got {t.shape}, {p.shape}"
            )
        if t.size < MIN_SAMPLES_PER_TOSS:
            raise InvalidInputError(f"TossRecording {self.toss_id!r}: {t.size} samples < {MIN_SAMPLES_PER_TOSS}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise InvalidInputError(f"TossRecording {self.toss_id!r}: non-finite values")
        if np.any(np.diff(t) <= 0.0):
            k = int(np.argmax(np.diff(t) <= 0.0))
            raise InvalidInputError(f"TossRecording {self.toss_id!r}: times not strictly increasing at sample {k + 1}")
        t.setflags(write=False)
        p.setflags(write=False)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "p", p)


@dataclass(frozen=True, eq=False)
class TossTruth:
    """What really happened in a synthetic toss (unknown for real recordings)."""

    clock_offset: float
    """Recording clock minus command clock [s]."""
    release_time: float
    """Release time on the command clock [s] (after timing jitter)."""
    release_p: FloatArray
    """Ball position at release (3,) [m]."""
    release_v: FloatArray
    """Ball velocity at release (3,) [m/s] (after arm vibration)."""
    wind: FloatArray
    """Air velocity during the flight (3,) [m/s]."""


@dataclass(frozen=True, eq=False)
class TossRecordings:
    """A set of recorded executions of one toss primitive."""

    recordings: tuple[TossRecording, ...]
    """The tosses, in recording order; ids are unique."""
    truth: tuple[TossTruth, ...] | None = None
    """Ground truth per toss for synthetic recordings (same order), else ``None``."""

    def __post_init__(self) -> None:
        recs = tuple(self.recordings)
        if not recs:
            raise InvalidInputError("TossRecordings: no recordings")
        ids = [r.toss_id for r in recs]
        if len(set(ids)) != len(ids):
            dup = next(i for i in ids if ids.count(i) > 1)
            raise InvalidInputError(f"TossRecordings: duplicate toss_id {dup!r}")
        if self.truth is not None and len(self.truth) != len(recs):
            raise InvalidInputError("TossRecordings: truth must have one entry per recording")
        object.__setattr__(self, "recordings", recs)
        if self.truth is not None:
            object.__setattr__(self, "truth", tuple(self.truth))

    def __len__(self) -> int:
        return len(self.recordings)


def save_recordings_csv(
    path: str | Path, recordings: TossRecordings, *, decimals: int = 6, comment: str | None = None
) -> None:
    """Write recordings as CSV (format of :func:`load_recordings_csv`).

    Args:
        path: output file; written atomically (temporary file, then rename).
        recordings: the tosses to write (the ground truth is not written).
        decimals: digits after the decimal point for t, x, y, z (4 = 0.1 mm / 0.1 ms).
        comment: optional text written as ``#`` comment lines before the header.
    """
    path = Path(path)
    if not (isinstance(decimals, int) and 1 <= decimals <= 12):
        raise InvalidInputError(f"save_recordings_csv: decimals must be an int in [1, 12], got {decimals!r}")
    lines: list[str] = []
    if comment:
        lines.extend(f"# {line}".rstrip() for line in comment.splitlines())
    lines.append(",".join(CSV_COLUMNS))
    fmt = f"{{:.{decimals}f}}"
    for rec in recordings.recordings:
        for ti, pi in zip(rec.t, rec.p):
            lines.append(
                ",".join([rec.toss_id, fmt.format(ti), fmt.format(pi[0]), fmt.format(pi[1]), fmt.format(pi[2])])
            )
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def load_recordings_csv(path: str | Path) -> TossRecordings:
    """Read toss recordings from a CSV file.

    Format (UTF-8 text):

    - optional comment lines starting with ``#`` and blank lines anywhere (ignored);
    - a header line naming the columns; it must contain ``toss_id,t,x,y,z`` (any
      order). Extra columns (e.g. a tracker's confidence) are allowed and ignored;
    - one row per sample: ``toss_id`` (any text without commas/quotes), ``t`` time [s]
      on any clock (each toss may use its own origin), ``x, y, z`` ball centre [m] in
      the world frame (origin at the table centre, +X towards the receiver, +Z up).
      Values must be finite decimal numbers.
    - rows of a toss need not be contiguous, but its times must strictly increase in
      file order; each toss needs at least :data:`MIN_SAMPLES_PER_TOSS` samples.

    - work limits and physical bounds (module doc): at most :data:`MAX_CSV_BYTES`,
      :data:`MAX_SAMPLES` rows, :data:`MAX_TOSSES` tosses of at most
      :data:`MAX_SAMPLES_PER_TOSS` samples; |t| <= :data:`MAX_ABS_TIME`, samples of a toss
      at least :data:`MIN_SAMPLE_STEP` apart and within :data:`MAX_TOSS_DURATION`,
      |x|, |y|, |z| <= :data:`MAX_ABS_POSITION`.

    Raises:
        DataFileError: unreadable file (not a regular file, too large, not UTF-8) or any
            violation above; the message names the file, the line number (1-based) and
            the column, or the limit.
    """
    path = Path(path)
    text = _read_text(path)
    header: list[str] | None = None
    col: dict[str, int] = {}
    data: dict[str, tuple[list[float], list[list[float]], int]] = {}
    rows = 0
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        cells = [c.strip() for c in line.split(",")]
        if header is None:
            header, col = cells, _header_columns(path, lineno, line, cells)
            continue
        if len(cells) != len(header):
            raise DataFileError(path, f"line {lineno}: {len(cells)} fields, the header has {len(header)}")
        rows += 1
        if rows > MAX_SAMPLES:
            raise DataFileError(path, f"line {lineno}: more than {MAX_SAMPLES} samples (data rows) in one file")
        _add_row(path, lineno, cells, col, data)
    if header is None:
        raise DataFileError(path, f"no header line (expected {','.join(CSV_COLUMNS)})")
    if not data:
        raise DataFileError(path, "no data rows")
    recs = []
    for tid, (ts, ps, last_line) in data.items():
        if len(ts) < MIN_SAMPLES_PER_TOSS:
            raise DataFileError(
                path,
                f"toss {tid!r} (last row line {last_line}): {len(ts)} samples, at least {MIN_SAMPLES_PER_TOSS} needed",
            )
        recs.append(TossRecording(toss_id=tid, t=np.array(ts), p=np.array(ps)))
    return TossRecordings(recordings=tuple(recs))


def _read_text(path: Path) -> str:
    """The text of a recordings file: a regular file of at most :data:`MAX_CSV_BYTES`,
    UTF-8 (a byte-order mark is skipped); DataFileError otherwise."""
    from studio.storage.jsonfile import decode_text, read_file_bytes

    data = read_file_bytes(path, max_bytes=MAX_CSV_BYTES)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:  # the project's message, for the line that holds the bad byte
        first = data.rfind(b"\n", 0, exc.start) + 1
        end = data.find(b"\n", exc.start)
        decode_text(data[first : end if end >= 0 else len(data)], path, line=data.count(b"\n", 0, exc.start) + 1)
        raise  # not reached: that line is not UTF-8 either


def _header_columns(path: Path, lineno: int, line: str, header: list[str]) -> dict[str, int]:
    """Index of each of :data:`CSV_COLUMNS` in the header cells (DataFileError if one is
    missing or a column is repeated)."""
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise DataFileError(
            path, f"line {lineno}: header {line!r} lacks column(s) {', '.join(missing)} (need {','.join(CSV_COLUMNS)})"
        )
    dups = sorted({c for c in header if header.count(c) > 1})
    if dups:
        raise DataFileError(path, f"line {lineno}: duplicate column(s) {', '.join(dups)} in the header")
    return {c: header.index(c) for c in CSV_COLUMNS}


def _add_row(
    path: Path,
    lineno: int,
    cells: list[str],
    col: dict[str, int],
    data: dict[str, tuple[list[float], list[list[float]], int]],
) -> None:
    """Append the sample of one data row to ``data`` ({toss_id: (times, positions, last
    line)}); DataFileError for a bad id, a bad or out-of-range number, a time not after the
    toss's last by :data:`MIN_SAMPLE_STEP` or a toss or file over its limits."""
    tid = cells[col["toss_id"]]
    if not tid or '"' in tid:
        raise DataFileError(path, f"line {lineno}, column toss_id: empty or quoted id {tid!r}")
    vals = [_number(path, lineno, name, cells[col[name]]) for name in ("t", "x", "y", "z")]
    if tid not in data and len(data) >= MAX_TOSSES:
        raise DataFileError(
            path,
            f"line {lineno}, column toss_id: toss {tid!r} is one more than the {MAX_TOSSES} tosses allowed in one file",
        )
    ts, ps, last_line = data.setdefault(tid, ([], [], lineno))
    if ts and not vals[0] >= ts[-1] + MIN_SAMPLE_STEP:
        raise DataFileError(
            path,
            f"line {lineno}, column t: time {vals[0]!r} of toss {tid!r} not after {ts[-1]!r} (line {last_line}) "
            f"by at least {MIN_SAMPLE_STEP} s; times must strictly increase within a toss",
        )
    if ts and vals[0] - ts[0] > MAX_TOSS_DURATION:
        raise DataFileError(
            path,
            f"line {lineno}, column t: toss {tid!r} spans {vals[0] - ts[0]:.6g} s from its first sample; "
            f"at most {MAX_TOSS_DURATION} s per toss (a toss lasts ~1 s)",
        )
    if len(ts) >= MAX_SAMPLES_PER_TOSS:
        raise DataFileError(path, f"line {lineno}: toss {tid!r} has more than {MAX_SAMPLES_PER_TOSS} samples")
    ts.append(vals[0])
    ps.append(vals[1:])
    data[tid] = (ts, ps, lineno)


def _number(path: Path, lineno: int, name: str, cell: str) -> float:
    """The value of column ``name`` (t or x, y, z): a finite decimal number within its
    physical bound (:data:`MAX_ABS_TIME`, :data:`MAX_ABS_POSITION`)."""
    try:
        v = float(cell)
    except ValueError:
        raise DataFileError(path, f"line {lineno}, column {name}: {cell!r} is not a number") from None
    if not math.isfinite(v):
        raise DataFileError(path, f"line {lineno}, column {name}: {cell!r} is not finite")
    bound, unit = (MAX_ABS_TIME, "s") if name == "t" else (MAX_ABS_POSITION, "m")
    if abs(v) > bound:
        raise DataFileError(
            path, f"line {lineno}, column {name}: {cell} {unit} is outside [-{bound:g}, {bound:g}] {unit}"
        )
    return v
