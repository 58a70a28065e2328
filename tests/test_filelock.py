"""Library writers exclude each other: the lock itself, and real concurrent CLI processes
(exports beside match-point records) that lose no entry and no count."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from studio.storage.filelock import LOCK_NAME, LockTimeoutError, locked

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "import sys; from studio.cli import main; sys.exit(main())"]
EXAMPLES = sorted((ROOT / "examples" / "serves").glob("*.json"))
RAISED = ["--effort-limit", "gantry_x=6000"]  # the x1.5 / x2 examples need more gantry force than the robot's limit


def test_lock_excludes_other_processes_and_times_out_with_a_clear_message(tmp_path: Path) -> None:
    folder = tmp_path / "lib"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from studio.storage.filelock import locked\nwith locked(sys.argv[1]):\n    print('held', flush=True); time.sleep(30)", str(folder)],
        stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        t0 = time.perf_counter()
        with pytest.raises(LockTimeoutError, match=rf"lib.*busy.*pid {holder.pid}.*0.3 s"):
            with locked(folder, timeout=0.3):
                pass
        assert 0.3 <= time.perf_counter() - t0 < 2.0
        # a library writer waiting for it: exit 2 with the message, nothing written
        env = {**os.environ, "SERVE_STUDIO_LOCK_TIMEOUT": "0.3"}
        cmd = CLI + ["library", "record", str(folder), "--server", "opponent", "--winner", "robot"]
        r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 2 and "is busy" in r.stderr and f"pid {holder.pid}" in r.stderr and "Traceback" not in r.stderr
        assert not (folder / "matches.jsonl").exists()
    finally:
        holder.kill()
        holder.wait()
    with locked(folder, timeout=2.0):  # a dead holder's lock is gone with it (flock)
        assert (folder / LOCK_NAME).exists()


def test_lock_is_reentrant_in_a_thread_and_excludes_other_threads(tmp_path: Path) -> None:
    order: list[str] = []
    with locked(tmp_path):
        with locked(tmp_path):  # nested (record -> sync usage -> rewrite index): no self-deadlock
            order.append("outer")

            def other() -> None:
                with locked(tmp_path, timeout=5.0):
                    order.append("other")

            th = threading.Thread(target=other)
            th.start()
            time.sleep(0.3)
            order.append("still outer")  # the other thread waits until both levels are released
    th.join(5.0)
    assert order == ["outer", "still outer", "other"]


def _run(args: list[str]) -> subprocess.Popen[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return subprocess.Popen(CLI + args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def test_concurrent_exports_and_records_lose_nothing(tmp_path: Path) -> None:
    """8 `evaluate --export` beside 20 `library record` processes on one library: every
    export is in the index, every point in the log, the counters equal the points."""
    lib = tmp_path / "lib"
    base = []
    for serve in EXAMPLES[:2]:  # two serves to record points for
        p = _run(["evaluate", str(serve), "--export", str(lib), *RAISED])
        out, err = p.communicate(timeout=300)
        assert p.returncode in (0, 1), err
        base.append(out.rsplit(" as ", 1)[1].split()[0])
    exports = [_run(["evaluate", str(EXAMPLES[k % len(EXAMPLES)]), "--export", str(lib), *RAISED]) for k in range(8)]
    records = []
    for k in range(20):
        extra = ["--ace"] if k % 5 == 0 else []
        records.append(_run(["library", "record", str(lib), "--serve", base[k % 2], "--winner", "robot" if k % 5 in (0, 1, 3) else "opponent", *extra]))
    exported = []
    for p in exports:
        out, err = p.communicate(timeout=600)
        assert p.returncode in (0, 1), err
        exported.append(out.rsplit(" as ", 1)[1].split()[0])
    for p in records:
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    v = subprocess.run(CLI + ["library", "validate", str(lib)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert v.returncode == 0, v.stderr
    index = json.loads((lib / "index.json").read_text())
    ids = [e["id"] for e in index["serves"]]
    assert sorted(ids) == sorted(base + exported)  # no export lost
    assert sorted(p.name for p in lib.glob("*.npz")) == sorted(f"{i}.npz" for i in ids)  # no orphan
    lines = (lib / "matches.jsonl").read_text().splitlines()
    assert len(lines) == 20
    usage = {e["id"]: e["usage"] for e in index["serves"]}
    assert usage[base[0]]["used"] == usage[base[1]]["used"] == 10
    assert sum(u["used"] for u in usage.values()) == 20
    assert sum(u["won"] for u in usage.values()) == 12 and sum(u["aces"] for u in usage.values()) == 4
