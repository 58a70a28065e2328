"""Paths confined to their folder: no symbolic link is followed out of a library.

A library folder is written by this program and read by a robot controller; a symlink
placed inside it (``pruned/`` pointing elsewhere, ``matches.jsonl`` linked to another
file) would make a prune or a match record write outside the folder the user named.
"""

from __future__ import annotations

from pathlib import Path

from studio.errors import DataFileError


def confined(folder: str | Path, path: str | Path) -> Path:
    """``path`` (absolute, or relative to ``folder``) when it lies inside ``folder`` with no
    symbolic link on the way from ``folder`` to it; DataFileError naming it otherwise.
    ``path`` itself need not exist."""
    base = Path(folder)
    target = base / path
    try:
        rel = target.relative_to(base)
    except ValueError:
        raise DataFileError(target, f"outside the folder {base}") from None
    if ".." in rel.parts:
        raise DataFileError(target, f"outside the folder {base} ('..' in the path)")
    current = base
    for part in rel.parts:
        current = current / part
        if current.is_symlink():
            raise DataFileError(
                current, f"is a symbolic link: inside {base} only the program's own files are read and written"
            )
    return target
