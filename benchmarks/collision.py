"""Collision check of the strike part of serve motions: conservative advancement (default)
against the exhaustive 1 kHz check (``exhaustive=True``).

Motions: the six example serves and perturbed copies (racket velocity pushed downwards,
short returns, offsets; about half of them collide). Each strike part (from the hand-over
to the end of the return, ~1200 samples at 1 kHz) is checked both ways; the reports must
be identical. Prints a table; the last line is one JSON object.

    uv run python benchmarks/collision.py [--perturbed N] [--repeat R]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from studio.serve.evaluate import EvaluationContext, plan_motion
from studio.serve.params import load_serve

EXAMPLES = sorted((Path(__file__).resolve().parent.parent / "examples" / "serves").glob("*.json"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--perturbed", type=int, default=60)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    ctx = EvaluationContext.default()
    checker = ctx.collision
    serves = [load_serve(p) for p in EXAMPLES]
    rng = np.random.default_rng(0)
    variants = list(serves)
    for k in range(args.perturbed):
        s = serves[k % len(serves)]
        p = s.params
        v = np.asarray(p.velocity) + rng.normal(0.0, 1.5, 3) - [0.0, 0.0, rng.uniform(0.0, 5.0)]
        p2 = dataclasses.replace(
            p, velocity=tuple(v), t_return=float(rng.uniform(0.3, 0.8)), offset=tuple(rng.normal(0.0, 0.05, 3)),
            yaw=float(p.yaw + rng.normal(0.0, 0.3)), roll=float(p.roll + rng.normal(0.0, 0.3)),
        )
        variants.append(dataclasses.replace(s, params=p2))
    rows: dict[str, dict[str, list[float]]] = {"free": {"fast": [], "exhaustive": []}, "colliding": {"fast": [], "exhaustive": []}}
    samples: list[int] = []
    for s in variants:
        m = plan_motion(s, ctx)
        if m.q is None or m.plan is None:
            continue
        n = len(m.plan.t)
        t, q = m.t[-n:], m.q[-n:]
        samples.append(n)
        ref = checker.check(t, q, exhaustive=True)
        fast = checker.check(t, q)
        if fast != ref:
            raise SystemExit(f"{s.name}: fast {fast} != exhaustive {ref}")
        kind = "colliding" if ref.collides else "free"
        for mode, exhaustive in (("fast", False), ("exhaustive", True)):
            best = min(_timed(checker, t, q, exhaustive) for _ in range(args.repeat))
            rows[kind][mode].append(best)
    print(f"strike parts: {len(samples)} motions, {int(np.median(samples))} samples median (1 kHz), reports identical")
    print(f"{'motions':<12}{'n':>5}{'mode':>12}{'median ms':>12}{'p95 ms':>10}")
    out: dict[str, float] = {}
    for kind, modes in rows.items():
        for mode, v in modes.items():
            if not v:
                continue
            med, p95 = float(np.median(v)), float(np.percentile(v, 95))
            print(f"{kind:<12}{len(v):>5}{mode:>12}{med:>12.2f}{p95:>10.2f}")
            out[f"{kind}_{mode}_median_ms"] = round(med, 2)
            out[f"{kind}_{mode}_p95_ms"] = round(p95, 2)
    print(json.dumps(out))


def _timed(checker: object, t: np.ndarray, q: np.ndarray, exhaustive: bool) -> float:
    t0 = time.perf_counter()
    checker.check(t, q, exhaustive=exhaustive)  # type: ignore[attr-defined]
    return 1000 * (time.perf_counter() - t0)


if __name__ == "__main__":
    main()
