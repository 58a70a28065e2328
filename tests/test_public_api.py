"""``import studio``: the documented public API, loaded lazily."""

from __future__ import annotations

import subprocess
import sys

import pytest

import studio


@pytest.mark.parametrize("name", studio.__all__)
def test_every_public_name_resolves_to_its_module_object(name: str) -> None:
    value = getattr(studio, name)
    module = __import__(studio._API[name], fromlist=[name])
    assert value is getattr(module, name) and (getattr(value, "__doc__", None) or callable(value))


def test_the_api_is_small_and_unknown_names_fail() -> None:
    assert 20 <= len(studio.__all__) <= 48 and "evaluate_serve" in dir(studio)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        studio.nope  # noqa: B018


def test_import_studio_loads_no_heavy_library() -> None:
    code = "import sys, studio; print(sorted(m for m in ('numpy', 'casadi', 'pinocchio', 'mujoco', 'torch', 'viser') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.strip() == "[]"


def test_all_lists_exactly_the_lazy_names() -> None:
    assert studio.__all__ == sorted(studio._API)
