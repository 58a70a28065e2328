"""Serve evaluations per second, with the split between planning, collision, racket
kinematics, ball prediction and checks.

Runs every example serve (``examples/serves``) on the mean toss, then robustly on K=10
recorded tosses (one plan, ten ball predictions). Prints a table; the last line is one
JSON object. Goal (issue 4): <= 30 ms median for one single-toss evaluation.

    uv run python benchmarks/evaluate.py [--repeat N]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from studio.serve.evaluate import EvaluationContext, evaluate_robust, evaluate_serve
from studio.serve.params import load_serve

EXAMPLES = sorted((Path(__file__).resolve().parent.parent / "examples" / "serves").glob("*.json"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    context = EvaluationContext.default()
    serves = [load_serve(p) for p in EXAMPLES]
    for s in serves:  # warm-up: builds planner, collision model, toss models
        evaluate_serve(s, context)
    totals: list[float] = []
    stages: dict[str, list[float]] = {}
    for _ in range(args.repeat):
        for s in serves:
            t0 = time.perf_counter()
            ev = evaluate_serve(s, context)
            totals.append(1000 * (time.perf_counter() - t0))
            for k, v in ev.timings_ms.items():
                stages.setdefault(k, []).append(v)
    robust: list[float] = []
    for s in serves:
        t0 = time.perf_counter()
        evaluate_robust(s, context, tosses=10)
        robust.append(1000 * (time.perf_counter() - t0))
    print(f"{'stage':<22}{'median ms':>12}{'p95 ms':>10}")
    for k, v in stages.items():
        print(f"{k:<22}{np.median(v):>12.2f}{np.percentile(v, 95):>10.2f}")
    print(f"{'single-toss total':<22}{np.median(totals):>12.2f}{np.percentile(totals, 95):>10.2f}")
    print(f"{'K=10 robust total':<22}{np.median(robust):>12.2f}{np.percentile(robust, 95):>10.2f}")
    print(f"evaluations/s: single toss {1000 / np.median(totals):.1f}, K=10 {1000 / np.median(robust):.1f}")
    print(
        json.dumps(
            {
                "n": len(totals),
                "single_median_ms": round(float(np.median(totals)), 2),
                "single_p95_ms": round(float(np.percentile(totals, 95)), 2),
                "k10_median_ms": round(float(np.median(robust)), 2),
                "stages_median_ms": {k: round(float(np.median(v)), 2) for k, v in stages.items()},
            }
        )
    )


if __name__ == "__main__":
    main()
