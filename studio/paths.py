"""Locations of the data shipped with the package (robot models, default tosses)."""

from __future__ import annotations

from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
"""The installed ``studio`` package folder."""

DATA_DIR = PACKAGE_DIR / "data"
"""Default data shipped with the package (toss recordings, ...)."""


def robots_dir() -> Path:
    """Folder holding the robot descriptions (``robots/`` in a checkout).

    In a source checkout (editable install) this is the repository's ``robots/``; in a
    wheel the folder is packed as ``studio/_robots``.
    """
    for candidate in (PACKAGE_DIR.parent / "robots", PACKAGE_DIR / "_robots"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        f"robot descriptions not found: looked in {PACKAGE_DIR.parent / 'robots'} and {PACKAGE_DIR / '_robots'}"
    )


def example_serves_dir() -> Path:
    """Folder of the example serve files (``examples/serves/`` in a checkout; packed as
    ``studio/_example_serves`` in a wheel)."""
    for candidate in (PACKAGE_DIR.parent / "examples" / "serves", PACKAGE_DIR / "_example_serves"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        f"example serves not found: looked in {PACKAGE_DIR.parent / 'examples' / 'serves'} and {PACKAGE_DIR / '_example_serves'}"
    )


SHARED_DATA_DIR = PACKAGE_DIR.parent.parent / "shared" / "data"
"""The project's shared data sets beside a checkout (``../shared/data``: match data,
robot serve contacts); not shipped."""
