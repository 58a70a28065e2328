"""The shared input validation: what is wrong, and where."""

from __future__ import annotations

import numpy as np
import pytest

from studio.errors import DataFileError, InvalidInputError, StudioError, checked_array


def test_checked_array_names_shape_index_and_type() -> None:
    a = checked_array([1, 2, 3], (3,), "target velocity")
    assert a.dtype == float and not a.flags.writeable
    assert checked_array(np.zeros((2, 2)), (2, 2), "x", read_only=False).flags.writeable
    with pytest.raises(InvalidInputError, match=r"target velocity: expected shape \(3,\), got \(2,\)"):
        checked_array([1, 2], (3,), "target velocity")
    with pytest.raises(InvalidInputError, match=r"q is not finite at index \(1, 0\)"):
        checked_array([[0.0, 1.0], [np.nan, 2.0]], (2, 2), "q")
    with pytest.raises(InvalidInputError, match="u: not an array of numbers"):
        checked_array(["a", "b"], (2,), "u")


def test_error_hierarchy_lets_the_guis_catch_one_type() -> None:
    e = DataFileError("lib/index.json", "entries[2].tau: not a number")
    assert isinstance(e, InvalidInputError) and isinstance(e, StudioError) and isinstance(e, ValueError)
    assert str(e) == "lib/index.json: entries[2].tau: not a number" and e.path == "lib/index.json"
