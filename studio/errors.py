"""Domain exceptions of the serve studio.

Every error that bad user input can cause derives from :class:`StudioError` and says
what was wrong and where (file, field, slider), so the GUIs can show it instead of
crashing.
"""

from __future__ import annotations

from typing import Any


class StudioError(Exception):
    """Base class of all serve-studio errors."""


class InvalidInputError(StudioError, ValueError):
    """A value given by a user or a file is malformed, out of range or not finite."""


class RobotModelError(StudioError):
    """A robot description (URDF/MJCF/spec) is missing, malformed or inconsistent."""


class DataFileError(InvalidInputError):
    """A data file (CSV recording, serve JSON, library entry) failed validation.

    The message names the file and the offending field or line.
    """

    def __init__(self, path: object, message: str) -> None:
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


def checked_array(value: Any, shape: tuple[int, ...], name: str, *, read_only: bool = True) -> Any:
    """``value`` as a new float array of ``shape`` with finite entries, read-only unless
    ``read_only=False``; otherwise :class:`InvalidInputError` naming ``name``, the shape
    found or the first non-finite index (numpy, imported here only)."""
    import numpy as np

    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: not an array of numbers ({type(value).__name__}: {exc})") from exc
    if arr.shape != shape:
        raise InvalidInputError(f"{name}: expected shape {shape}, got {arr.shape}")
    bad = ~np.isfinite(arr)
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InvalidInputError(f"{name} is not finite at index {idx}")
    if read_only:
        arr.setflags(write=False)
    return arr
