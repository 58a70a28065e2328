"""Thread-pool environment (studio.optimize.threads)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from studio.optimize.threads import THREAD_VARS, single_thread_env


def test_single_thread_env_keeps_or_overrides_user_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    for var in THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "4")
    assert single_thread_env(keep_user_settings=True)
    assert os.environ["OMP_NUM_THREADS"] == os.environ["OPENBLAS_NUM_THREADS"] == "1"
    assert os.environ["MKL_NUM_THREADS"] == "4"
    assert not single_thread_env(keep_user_settings=True)  # nothing left to change
    assert single_thread_env(keep_user_settings=False)
    assert all(os.environ[v] == "1" for v in THREAD_VARS)


def test_module_does_not_import_numpy() -> None:
    """The CLI sets the variables before numpy loads: importing the module must not load it."""
    code = "import sys, studio.optimize.threads; print('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
