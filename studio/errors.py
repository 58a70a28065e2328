"""Domain exceptions of the serve studio.

Every error that bad user input can cause derives from :class:`StudioError` and says
what was wrong and where (file, field, slider), so the GUIs can show it instead of
crashing.
"""

from __future__ import annotations


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
