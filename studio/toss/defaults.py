"""The shipped default tosses: their primitives, the recordings in ``studio/data/tosses``,
their toss models (cached), and the generator of those recordings
(``serve-studio toss --generate``).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING, Final

import numpy as np

from studio.errors import InvalidInputError
from studio.paths import DATA_DIR
from studio.toss.model import TossModel
from studio.toss.noise import TossNoise
from studio.toss.primitive import TOSS_SIDES, TossPrimitive, TossSide
from studio.toss.recordings import MAX_TOSSES, load_recordings_csv, save_recordings_csv
from studio.toss.synthesis import make_toss
from studio.toss.synthetic import simulate_tosses

if TYPE_CHECKING:
    from studio.robot.model import Robot

DEFAULT_TOSS_DIR: Final[Path] = DATA_DIR / "tosses"
"""Folder of the shipped toss recordings ``right.csv`` and ``left.csv``."""

DEFAULT_N_TOSSES: Final[int] = 20
"""Number of synthetic tosses per side in the shipped recordings."""

DEFAULT_SEED: Final[int] = 20251215
"""Seed of the shipped synthetic recordings (side index appended)."""


def default_toss(robot: Robot, side: TossSide) -> TossPrimitive:
    """The default toss primitive of a side: :func:`~studio.toss.synthesis.make_toss` with its defaults
    (deterministic: the same robot gives the same commands)."""
    return make_toss(robot, side)


def default_recordings_path(side: TossSide) -> Path:
    """Path of the shipped recordings of ``side``."""
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"toss side must be one of {TOSS_SIDES}, got {side!r}")
    return DEFAULT_TOSS_DIR / f"{side}.csv"


@functools.lru_cache(maxsize=2)
def _default_model_cached(side: TossSide) -> TossModel:
    from studio.robot.model import load_robot

    robot = load_robot()
    return TossModel.from_recordings(default_toss(robot, side), load_recordings_csv(default_recordings_path(side)))


def load_default_toss_model(side: TossSide, robot: Robot | None = None) -> TossModel:
    """Toss model of ``side`` from the shipped recordings (``studio/data/tosses``).

    The primitive is rebuilt with :func:`default_toss` on ``robot`` (default: the
    shipped robot, and the model is cached per side) and the recordings are loaded
    from ``<side>.csv``.

    Raises:
        InvalidInputError: unknown side; DataFileError: a bad recordings file.
    """
    if side not in TOSS_SIDES:
        raise InvalidInputError(f"toss side must be one of {TOSS_SIDES}, got {side!r}")
    if robot is None:
        return _default_model_cached(side)
    return TossModel.from_recordings(default_toss(robot, side), load_recordings_csv(default_recordings_path(side)))


def generate_default_recordings(
    out_dir: str | Path = DEFAULT_TOSS_DIR, *, n: int = DEFAULT_N_TOSSES, seed: int = DEFAULT_SEED
) -> list[Path]:
    """Write synthetic ``right.csv`` and ``left.csv`` (deterministic for a seed).

    Each side: :func:`default_toss` on the shipped robot, :func:`~studio.toss.synthetic.simulate_tosses` with
    the default :class:`~studio.toss.noise.TossNoise` and ``np.random.default_rng([seed, side_index])``,
    toss ids ``<side>_<k>``, saved with 4 decimals (0.1 ms, 0.1 mm): ~165 KiB per side.
    ``n`` is at most :data:`~studio.toss.recordings.MAX_TOSSES` (more could not be read back).
    """
    from studio.robot.model import load_robot

    if isinstance(n, bool) or not isinstance(n, int) or not 2 <= n <= MAX_TOSSES:
        raise InvalidInputError(f"toss --generate: n must be a whole number of tosses in [2, {MAX_TOSSES}], got {n!r}")

    robot = load_robot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for idx, side in enumerate(TOSS_SIDES):
        prim = default_toss(robot, side)
        recs = simulate_tosses(robot, prim, n, np.random.default_rng([seed, idx]), noise=TossNoise(), id_prefix=side)
        path = out / f"{side}.csv"
        save_recordings_csv(
            path,
            recs,
            decimals=4,
            comment=(
                f"Synthetic recordings of the default {side} toss (serve-studio toss --generate, "
                f"seed {seed}, {n} tosses, default TossNoise).\n"
                "Columns: toss_id, t [s] (camera clock, random offset per toss), x, y, z [m] ball centre, "
                "world frame (origin table centre, +X to the receiver, +Z up)."
            ),
        )
        written.append(path)
    return written
