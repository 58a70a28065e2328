"""Time to train one serve with HEBO (paper budget: 100 iterations x 20 = 2000 evaluations).

    .venv/bin/python benchmarks/train.py                       # chosen HeboConfig, 2 workers, overlapped (default)
    .venv/bin/python benchmarks/train.py --sequential          # suggest after each batch
    .venv/bin/python benchmarks/train.py --compare             # + HEBO defaults and CMA-ES
    .venv/bin/python benchmarks/train.py --compare --compare-evaluations 400
    .venv/bin/python benchmarks/train.py --compare --skip-main --compare-evaluations 800 --compare-seeds 0 1 2

Prints a table; the last line is one JSON object (task, evaluations, seconds, best_reward,
legal, ...). ``--compare`` runs, at equal evaluations (``--compare-evaluations``, default
400 = 20 x 20, because HEBO's own settings cost ~30 s per suggestion at 2000 points),
the chosen config, the same with suggestions overlapping the evaluation, HEBO's defaults
(:meth:`HeboConfig.hebo_defaults`, sequential suggest-evaluate loop as HEBO runs) and CMA-ES
(``cma``, population 20, sigma0 0.25 on the normalized box), and prints the best reward
so far against evaluations and against seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from studio.optimize.optimizer import EvaluatorPool, HeboConfig, bounds_for_toss, optimize_serve  # noqa: E402
from studio.serve.params import LimitScale, load_serve  # noqa: E402
from studio.toss.defaults import load_default_toss_model  # noqa: E402

Trace = list[tuple[int, float, float]]
"""(evaluations done, seconds since start, best reward so far)."""


def run_hebo(args: argparse.Namespace, config: HeboConfig, iterations: int, run_dir: Path, *, overlap: bool) -> tuple[Trace, object]:
    trace: Trace = []
    t0 = time.perf_counter()

    def progress(done: int, total: int, best: float, params: object) -> None:
        trace.append((done, time.perf_counter() - t0, best))
        if args.verbose:
            print(f"  {done:5d}/{total} evaluations  {time.perf_counter() - t0:7.1f} s  best {best:+.3f}", flush=True)

    seeds = [load_serve(Path(p)) for p in args.seed_serve]
    res = optimize_serve(
        side=args.side, task=args.task, run_dir=run_dir, seeds=seeds, iterations=iterations, population=args.population,
        tosses=args.tosses, seed=args.seed, workers=args.workers, progress=progress, config=config, overlap=overlap,
        limit_scale=args.scale,
    )  # fmt: skip
    return trace, res


def run_cma(args: argparse.Namespace, evaluations: int) -> tuple[Trace, float]:
    import cma

    t0 = time.perf_counter()
    bounds = bounds_for_toss(load_default_toss_model(args.side))
    low, high = bounds.lows_highs()
    es = cma.CMAEvolutionStrategy(np.full(10, 0.5), 0.25, {"popsize": args.population, "bounds": [0.0, 1.0], "seed": args.seed + 1, "verbose": -9})
    trace: Trace = []
    best = -np.inf
    done = 0
    with EvaluatorPool(side=args.side, task=args.task, workers=args.workers, limit_scale=args.scale) as pool:
        while done < evaluations:
            Z = np.clip(np.array(es.ask()), 0.0, 1.0)
            out = [o for o, _ in pool.map(low + Z * (high - low), tosses=args.tosses, rng_seeds=range(done, done + len(Z)))]
            F = np.array([o.reward for o in out])
            es.tell(list(Z), list(-F))
            done += len(Z)
            best = max(best, float(F.max()))
            trace.append((done, time.perf_counter() - t0, best))
    return trace, time.perf_counter() - t0


def at(trace: Trace, n: int) -> tuple[float, float]:
    """(seconds, best reward) when ``n`` evaluations were done."""
    for done, sec, best in trace:
        if done >= n:
            return sec, best
    return trace[-1][1], trace[-1][2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="topspin_velocity")
    ap.add_argument("--side", default="right", choices=("right", "left"))
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--population", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tosses", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seed-serve", action="append", default=[], help="hand-designed serve JSON to seed HEBO with")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--compare-evaluations", type=int, default=400)
    ap.add_argument("--compare-seeds", type=int, nargs="+", default=[0], help="seeds of the comparison runs (README: 0 1 2 at 800 evaluations)")
    ap.add_argument("--skip-main", action="store_true", help="with --compare: skip the full-budget run")
    ap.add_argument("--optimizers", nargs="+", choices=("chosen", "overlap", "defaults", "cma"), default=["chosen", "overlap", "defaults", "cma"], help="with --compare: which optimizers to run")
    ap.add_argument("--sequential", action="store_true", help="main run: suggest each batch after the previous one is evaluated (default: overlapped)")
    ap.add_argument("--limit-scale", default="1", help="dynamic limit expansion of the runs (serve-studio optimize --limit-scale): 1.5 = acceleration and jerk limits x1.5")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    args.scale = LimitScale.parse(args.limit_scale)

    cfg = HeboConfig()
    out: dict[str, object] = {"task": args.task, "side": args.side, "workers": args.workers, "tosses": args.tosses, "limit_scale": args.scale.to_json(), "config": cfg.to_json()}
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_main:
            trace, res = run_hebo(args, cfg, args.iterations, Path(tmp) / "main", overlap=not args.sequential)
            t = res.timings
            s = res.summary
            log = [json.loads(line) for line in (Path(tmp) / "main" / "evaluations.jsonl").read_text().splitlines()]
            failed = sum(r["status"] in ("planner_failed", "collision") for r in log)
            rows = [
                ("evaluations", f"{res.evaluations}"),
                ("wall time", f"{t['total']:.1f} s"),
                ("  HEBO suggest, all", f"{t['suggest']:.1f} s ({1000 * t['suggest'] / max(1, args.iterations):.0f} ms per batch of {args.population}; {t['suggest_overlapped']:.1f} s of it while the workers evaluated)"),
                ("  batches (hand-over to last result, overlapped suggestions included)", f"{t['evaluate']:.1f} s ({1000 * t['evaluate'] / max(1, res.evaluations):.1f} ms per evaluation on {args.workers} workers)"),
                ("  evaluation (sum of worker wall times)", f"{t['evaluate_cpu']:.1f} s ({1000 * t['evaluate_cpu'] / max(1, res.evaluations):.1f} ms per evaluation)"),
                ("  final pick (top 5 x 10 tosses)", f"{t['final']:.1f} s"),
                ("  start-up (imports, toss model, worker spawn) and blocking suggestions", f"{t['total'] - t['evaluate'] - t['final']:.1f} s"),
                ("best training reward", f"{float(res.history.max()):+.3f}"),
                ("legal training evaluations", f"{sum(r['legal'] for r in log)} of {len(log)} (planner failed or collision: {failed})"),
                ("final serve: mean reward (10 tosses)", f"{s.mean_reward:+.3f}" if s else "-"),
                ("final serve: legal fraction", f"{s.legal_fraction:.2f}" if s else "-"),
            ]
            if res.best is not None:  # what the chosen serve does on the mean toss (after the timing)
                from studio.serve.evaluate import EvaluationContext, evaluate_serve

                ev = evaluate_serve(res.best, EvaluationContext.default(), task=args.task)  # as train exports
                sb = ev.metrics.second_bounce if ev.metrics is not None else None
                if sb is not None:
                    rows.append(("final serve, mean toss: ball at the second bounce", f"v_x {sb['v'][0]:+.2f} m/s, |v| {float(np.linalg.norm(sb['v'])):.2f} m/s, top/back {sb['topspin']:+.0f} rad/s, side {sb['sidespin']:+.0f} rad/s ({ev.status})"))
                    out["second_bounce"] = {"v": sb["v"], "topspin": sb["topspin"], "sidespin": sb["sidespin"], "status": ev.status}
            slow = sorted(r["seconds"] for r in log)
            rows.append(("evaluation time median / p95 / max", f"{1000 * slow[len(slow) // 2]:.0f} / {1000 * slow[int(0.95 * len(slow))]:.0f} / {1000 * slow[-1]:.0f} ms"))
            for status in sorted({r["status"] for r in log}):
                sec = sorted(r["seconds"] for r in log if r["status"] == status)
                rows.append((f"  status {status}: count, median, sum", f"{len(sec)}, {1000 * sec[len(sec) // 2]:.0f} ms, {sum(sec):.1f} s"))
            print(f"\nHEBO training, task {args.task}, {args.side} toss, {args.iterations} x {args.population}, {args.workers} workers")
            print("| what | figure |\n| --- | --- |")
            for k, v in rows:
                print(f"| {k} | {v} |")
            out.update(
                evaluations=res.evaluations, seconds=round(t["total"], 2), suggest_seconds=round(t["suggest"], 2), evaluate_seconds=round(t["evaluate"], 2),
                best_train_reward=float(res.history.max()), best_reward=s.mean_reward if s else None, legal=bool(s.legal) if s else False,
                legal_fraction=s.legal_fraction if s else None, best_params=res.best.to_json()["params"] if res.best else None,
            )  # fmt: skip
        if args.compare:
            n = args.compare_evaluations
            iters = max(1, n // args.population)
            marks = [n // 4, n // 2, 3 * n // 4, n]
            names = {"chosen": "HEBO chosen config, sequential", "overlap": "HEBO chosen config, overlapped suggestions (default)", "defaults": "HEBO defaults", "cma": "CMA-ES (pop 20)"}
            finals: dict[str, list[tuple[float, float]]] = {names[k]: [] for k in args.optimizers}
            for seed in args.compare_seeds:
                a = argparse.Namespace(**{**vars(args), "seed": seed})
                runs: dict[str, Trace] = {}
                if "chosen" in args.optimizers:
                    runs[names["chosen"]], _ = run_hebo(a, cfg, iters, Path(tmp) / f"cmp_chosen_{seed}", overlap=False)
                if "overlap" in args.optimizers:
                    runs[names["overlap"]], _ = run_hebo(a, cfg, iters, Path(tmp) / f"cmp_overlap_{seed}", overlap=True)
                if "defaults" in args.optimizers:
                    runs[names["defaults"]], _ = run_hebo(a, HeboConfig.hebo_defaults(), iters, Path(tmp) / f"cmp_default_{seed}", overlap=False)
                if "cma" in args.optimizers:
                    runs[names["cma"]], _ = run_cma(a, iters * args.population)
                print(f"\nComparison at {iters * args.population} evaluations (task {args.task}, {args.side} toss, seed {seed}): best reward so far / seconds")
                print("| optimizer | " + " | ".join(f"{m} evals" for m in marks) + " |")
                print("| --- |" + " --- |" * len(marks))
                for name, tr in runs.items():
                    print(f"| {name} | " + " | ".join(f"{at(tr, m)[1]:+.3f} @ {at(tr, m)[0]:.0f} s" for m in marks) + " |")
                    finals[name].append((tr[-1][2], tr[-1][1]))
            print(f"\nBest reward at {iters * args.population} evaluations over seeds {args.compare_seeds}")
            print("| optimizer | " + " | ".join(f"seed {s_}" for s_ in args.compare_seeds) + " | mean |")
            print("| --- |" + " --- |" * (len(args.compare_seeds) + 1))
            for name, f in finals.items():
                print(f"| {name} | " + " | ".join(f"{b:+.3f} / {sec:.0f} s" for b, sec in f) + f" | {np.mean([b for b, _ in f]):+.3f} |")
            out["compare"] = {name: {"seeds": args.compare_seeds, "best_reward": [b for b, _ in f], "seconds": [round(sec, 2) for _, sec in f], "mean_best_reward": float(np.mean([b for b, _ in f]))} for name, f in finals.items()}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
