"""Studio latency: slider change -> re-plan, ball prediction, checks -> updated scene.

Runs the real studio app in-process on a viser server (no browser): for each sample a
slider value changes (v_x, v_z, tau or roll, small steps around the example serve), the
change is submitted as the GUI callback does, and the time until the worker has
published the new scene and panels is measured. Prints a table; the last line is one
JSON object. Goal (issue 6): <= 100 ms median.

    uv run python benchmarks/studio_latency.py [--n 60]
"""

from __future__ import annotations

import argparse
import json
import socket
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
import viser

from studio.ui.app import StudioApp
from studio.serve.evaluate import EvaluationContext


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=60)
    args = parser.parse_args()
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    with TemporaryDirectory() as tmp:
        app = StudioApp(server, context=EvaluationContext.default(), serves_dir=Path(tmp), library_dir=Path(tmp) / "lib")
        app.worker.wait_idle(300)
        rng = np.random.default_rng(0)
        handles = {"v_x": app.form.vx, "v_z": app.form.vz, "tau": app.form.tau, "roll": app.form.roll}
        base = {k: h.value for k, h in handles.items()}
        steps = {"v_x": 0.2, "v_z": 0.2, "tau": 0.01, "roll": 2.0}
        rows: dict[str, list[float]] = {k: [] for k in handles}
        totals: list[float] = []
        published_before = app.last
        for i in range(args.n):
            key = list(handles)[i % len(handles)]
            app._suspend = True
            handles[key].value = float(base[key] + steps[key] * rng.uniform(-1.0, 1.0))
            app._suspend = False
            t0 = time.perf_counter()
            app._changed()
            app.worker.wait_idle(120)
            dt = 1000 * (time.perf_counter() - t0)
            assert app.last is not published_before
            published_before = app.last
            rows[key].append(dt)
            totals.append(dt)
        app.worker.close()
    server.stop()
    print(f"{'slider':<10}{'n':>4}{'median ms':>12}{'p95 ms':>10}")
    for k, v in rows.items():
        print(f"{k:<10}{len(v):>4}{np.median(v):>12.1f}{np.percentile(v, 95):>10.1f}")
    print(f"{'all':<10}{len(totals):>4}{np.median(totals):>12.1f}{np.percentile(totals, 95):>10.1f}")
    print(json.dumps({"n": len(totals), "median_ms": round(float(np.median(totals)), 1), "p95_ms": round(float(np.percentile(totals, 95)), 1)}))


if __name__ == "__main__":
    main()
