"""The numbered examples: type-checked with mypy and run end to end (small budgets)."""

from __future__ import annotations

import re

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = sorted((ROOT / "examples").glob("[0-9][0-9]_*.py"))


def _run(args: list[str], cwd: Path) -> str:
    out = subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-4000:]
    return out.stdout


def test_examples_are_numbered_and_type_check(tmp_path: Path) -> None:
    assert [p.name[:2] for p in EXAMPLES] == [f"{i:02d}" for i in range(1, len(EXAMPLES) + 1)]
    args = ["-m", "mypy", "--follow-imports=silent", "--ignore-missing-imports", "--disallow-untyped-defs",
            "--cache-dir", str(ROOT / ".mypy_cache"), *map(str, EXAMPLES)]
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_runs(path: Path, tmp_path: Path) -> None:
    extra = {
        "01_ball_spin_trajectories": [str(tmp_path / "spin.png")],
        "04_optimize_serve": ["--iterations", "1", "--population", "4", "--run-dir", str(tmp_path / "run")],
        "05_robustify_serve": ["--evaluations", "24", "--run-dir", str(tmp_path / "run")],
    }.get(path.stem, [])
    out = _run([str(path), *extra], cwd=tmp_path)
    if path.stem == "01_ball_spin_trajectories":
        assert (tmp_path / "spin.png").stat().st_size > 10_000
    elif path.stem == "02_plan_strike":
        assert "plan:      ok" in out and "collision-free" in out and "tolerance" in out  # the sweep ends beyond reach
    elif path.stem == "03_evaluate_serve":
        assert "### LEGAL" in out and "over 10 recorded tosses" in out
    elif path.stem == "04_optimize_serve":
        assert "5 evaluations, then 9 after the resume" in out
        assert sum(1 for _ in open(tmp_path / "run" / "evaluations.jsonl")) == 9
    elif path.stem == "05_robustify_serve":
        assert "stopped after 12 candidates; resuming" in out and "24 candidates logged" in out
        assert re.search(r"Start: legal on \d+/20 recorded tosses", out)
