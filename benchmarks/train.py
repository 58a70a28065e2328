"""Time to train one serve with HEBO (paper budget: 100 iterations x 20 = 2000 evaluations).

    .venv/bin/python benchmarks/train.py                       # default HeboConfig, 5 tosses, 2 workers, overlapped
    .venv/bin/python benchmarks/train.py --config full_refit   # the suggestions before warm starts
    .venv/bin/python benchmarks/train.py --tosses 1            # the mean toss only (not robust)
    .venv/bin/python benchmarks/train.py --sequential          # suggest after each batch
    .venv/bin/python benchmarks/train.py --compare             # + HEBO defaults and CMA-ES
    .venv/bin/python benchmarks/train.py --compare --skip-main --compare-evaluations 2000 \
        --compare-seeds 0 1 2 3 4 --optimizers overlap full_refit --workers 1 --tosses 1

Prints a table: wall time, HEBO suggestion CPU time (this process) and wall time per batch,
evaluation wall time per batch and per evaluation, the machine's load (all users: the
machine is shared) and the chosen serve's legal count and mean reward on 10 recorded
tosses drawn independently of the run (and on every recording); the last line is one
JSON object of the same figures. ``--compare`` runs, at equal evaluations
(``--compare-evaluations``, default 400 = 20 x 20, because HEBO's own settings cost ~30 s
per suggestion at 2000 points), the default config sequential (``chosen``) and overlapped
(``overlap``), :meth:`HeboConfig.full_refit` overlapped (``full_refit``), HEBO's defaults
(:meth:`HeboConfig.hebo_defaults`, sequential as HEBO runs) and CMA-ES (``cma``,
population 20, sigma0 0.25 on the normalized box), and prints the best reward so far
against evaluations and against seconds. Rewards at equal evaluations do not depend on
the worker count (evaluations are deterministic and the overlapped loop suggests from the
same observations), so ``--workers 1`` compares optimizers on one core.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from studio.optimize.optimizer import EvaluatorPool, HeboConfig, OptimizeOptions, bounds_for_toss, optimize_serve  # noqa: E402
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
    options = OptimizeOptions(
        side=args.side, task=args.task, iterations=iterations, population=args.population, tosses=args.tosses,
        seed=args.seed, workers=args.workers, config=config, overlap=overlap, limit_scale=args.scale,
    )  # fmt: skip
    res = optimize_serve(options, run_dir=run_dir, seeds=seeds, progress=progress)
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


class Machine:
    """The machine's state over a measurement: load averages (``/proc/loadavg``) at its
    start and end, and how many cores were busy on average (``/proc/stat``; all users:
    the machine is shared, so other people's work is in it too)."""

    def __init__(self) -> None:
        self.load0 = self._load()
        self.stat0 = self._stat()

    @staticmethod
    def _load() -> str:
        try:
            return " ".join(Path("/proc/loadavg").read_text().split()[:3])
        except OSError:
            return "?"

    @staticmethod
    def _stat() -> tuple[int, int] | None:
        try:
            v = [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
        except (OSError, ValueError):
            return None
        return sum(v), v[3] + v[4]  # all jiffies, idle + iowait

    def report(self) -> dict[str, object]:
        """Load averages at start and end [1/5/15 min], busy cores in between [cores]."""
        out: dict[str, object] = {"load_start": self.load0, "load_end": self._load(), "cores": os.cpu_count()}
        s1 = self._stat()
        if self.stat0 is not None and s1 is not None and s1[0] > self.stat0[0]:
            total, idle = s1[0] - self.stat0[0], s1[1] - self.stat0[1]
            out["busy_cores"] = round((os.cpu_count() or 1) * (total - idle) / total, 2)
        return out

    def line(self) -> str:
        r = self.report()
        return f"load average {r['load_start']} at the start, {r['load_end']} at the end; {r.get('busy_cores', '?')} of {r['cores']} cores busy on average (all users)"


def fresh_toss_check(serve: object, task: str, seed: int, tosses: int = 10) -> dict[str, object]:
    """The chosen serve on ``tosses`` recorded tosses drawn independently of the run (not
    the draws its final pick used) and on every recording, planned as ``train`` exports
    (:meth:`EvaluationContext.default`)."""
    from studio.serve.evaluate import EvaluationContext, evaluate_robust

    ctx = EvaluationContext.default()
    rng = np.random.default_rng(np.random.SeedSequence([seed, 16]))
    fresh = evaluate_robust(serve, ctx, task=task, tosses=tosses, rng=rng)  # type: ignore[arg-type]
    n_all = ctx.toss_model(serve.side).n_tosses  # type: ignore[attr-defined]
    every = evaluate_robust(serve, ctx, task=task, tosses=n_all, rng=np.random.default_rng(0))  # type: ignore[arg-type]
    return {
        "fresh_legal": sum(e.legal for e in fresh.evaluations), "fresh_tosses": tosses, "fresh_reward": fresh.reward,
        "all_legal": sum(e.legal for e in every.evaluations), "all_tosses": n_all, "all_reward": every.reward,
    }  # fmt: skip


def timing_rows(res: object, args: argparse.Namespace) -> list[tuple[str, str]]:
    """Wall time and its parts, per batch where that is what matters."""
    t = res.timings  # type: ignore[attr-defined]
    n_eval, batches = max(1, res.evaluations), max(1, args.iterations)  # type: ignore[attr-defined]
    fits = ", ".join(f"{v} {k}" for k, v in sorted(res.gp_fits.items())) or "-"  # type: ignore[attr-defined]
    return [
        ("evaluations", f"{res.evaluations}"),  # type: ignore[attr-defined]
        ("wall time", f"{t['total']:.1f} s"),
        (f"  HEBO suggestion per batch of {args.population}: CPU (this process)", f"{1000 * t['suggest_cpu'] / batches:.0f} ms ({t['suggest_cpu']:.1f} s in all; GP fits: {fits})"),
        ("  HEBO suggestion per batch: wall", f"{1000 * t['suggest'] / batches:.0f} ms ({t['suggest']:.1f} s in all, {t['suggest_overlapped']:.1f} s of it while the workers evaluated)"),
        ("  evaluation per batch: wall, hand-over to last result (overlapped suggestion included)", f"{1000 * t['evaluate'] / batches:.0f} ms ({t['evaluate']:.1f} s in all, {args.workers} workers)"),
        ("  evaluation: worker wall time per evaluation", f"{1000 * t['evaluate_cpu'] / n_eval:.1f} ms ({args.tosses} tosses each; {t['evaluate_cpu']:.1f} s in all)"),
        ("  final pick (the top candidates on 10 fresh tosses each)", f"{t['final']:.1f} s ({len(res.candidates)} candidates)"),  # type: ignore[attr-defined]
        ("  start-up (imports, toss model, worker spawn) and blocking suggestions", f"{t['total'] - t['evaluate'] - t['final']:.1f} s"),
    ]


def main_run(args: argparse.Namespace, cfg: HeboConfig, tmp: Path, out: dict[str, object]) -> None:
    """The full-budget run: one table, its figures added to ``out``."""
    machine = Machine()
    trace, res = run_hebo(args, cfg, args.iterations, tmp / "main", overlap=not args.sequential)
    state = machine.report()
    t, s = res.timings, res.summary
    log = [json.loads(line) for line in (tmp / "main" / "evaluations.jsonl").read_text().splitlines()]
    failed = sum(r["status"] in ("planner_failed", "collision") for r in log)
    rows = timing_rows(res, args) + [
        ("machine during the run", machine.line()),
        ("best training reward (mean over the tosses of an evaluation)", f"{float(res.history.max()):+.3f}"),
        ("legal training evaluations", f"{sum(r['legal'] for r in log)} of {len(log)} (planner failed or collision: {failed})"),
        ("final pick: chosen serve's mean reward / legal fraction on its 10 tosses", f"{s.mean_reward:+.3f} / {s.legal_fraction:.2f}" if s else "-"),
    ]
    if res.best is not None:  # after the timing: the chosen serve on fresh tosses and on the mean toss
        check = fresh_toss_check(res.best, args.task, args.seed)
        rows.append(("chosen serve on 10 fresh recorded tosses (another draw): legal, mean reward", f"{check['fresh_legal']} of {check['fresh_tosses']}, {check['fresh_reward']:+.3f}"))
        rows.append(("chosen serve on every recorded toss: legal, mean reward", f"{check['all_legal']} of {check['all_tosses']}, {check['all_reward']:+.3f}"))
        out.update(check)
        rows += mean_toss_rows(res.best, args.task, out)
    slow = sorted(r["seconds"] for r in log)
    rows.append(("evaluation time median / p95 / max", f"{1000 * slow[len(slow) // 2]:.0f} / {1000 * slow[int(0.95 * len(slow))]:.0f} / {1000 * slow[-1]:.0f} ms"))
    for status in sorted({r["status"] for r in log}):
        sec = sorted(r["seconds"] for r in log if r["status"] == status)
        rows.append((f"  status {status}: count, median, sum", f"{len(sec)}, {1000 * sec[len(sec) // 2]:.0f} ms, {sum(sec):.1f} s"))
    print(f"\nHEBO training, task {args.task}, {args.side} toss, {args.iterations} x {args.population}, {args.tosses} tosses per evaluation, {args.workers} workers, config {args.config}")
    print("| what | figure |\n| --- | --- |")
    for k, v in rows:
        print(f"| {k} | {v} |")
    out.update(
        evaluations=res.evaluations, seconds=round(t["total"], 2), suggest_seconds=round(t["suggest"], 2), suggest_cpu_seconds=round(t["suggest_cpu"], 2),
        suggest_cpu_ms_per_batch=round(1000 * t["suggest_cpu"] / max(1, args.iterations), 1), evaluate_seconds=round(t["evaluate"], 2),
        best_train_reward=float(res.history.max()), best_reward=s.mean_reward if s else None, legal=bool(s.legal) if s else False,
        legal_fraction=s.legal_fraction if s else None, best_params=res.best.to_json()["params"] if res.best else None, gp_fits=res.gp_fits, machine=state,
    )  # fmt: skip


def mean_toss_rows(serve: object, task: str, out: dict[str, object]) -> list[tuple[str, str]]:
    """What the chosen serve does on the mean toss (as ``train`` exports it)."""
    from studio.serve.evaluate import EvaluationContext, evaluate_serve

    ev = evaluate_serve(serve, EvaluationContext.default(), task=task)  # type: ignore[arg-type]
    sb = ev.metrics.second_bounce if ev.metrics is not None else None
    if sb is None:
        return [("chosen serve, mean toss", ev.status)]
    out["second_bounce"] = {"v": sb["v"], "topspin": sb["topspin"], "sidespin": sb["sidespin"], "status": ev.status}
    return [("chosen serve, mean toss: ball at the second bounce", f"v_x {sb['v'][0]:+.2f} m/s, |v| {float(np.linalg.norm(sb['v'])):.2f} m/s, top/back {sb['topspin']:+.0f} rad/s, side {sb['sidespin']:+.0f} rad/s ({ev.status})")]


COMPARE_NAMES = {
    "chosen": "HEBO default config, sequential",
    "overlap": "HEBO default config, overlapped suggestions (default loop)",
    "full_refit": "HEBO full refits (HeboConfig.full_refit: the default before warm starts), overlapped",
    "defaults": "HEBO defaults",
    "cma": "CMA-ES (pop 20)",
}


def compare(args: argparse.Namespace, cfg: HeboConfig, tmp: Path, out: dict[str, object]) -> None:
    """The optimizers at equal evaluations, per seed, then the best reward over the seeds."""
    n = args.compare_evaluations
    iters = max(1, n // args.population)
    marks = [n // 4, n // 2, 3 * n // 4, n]
    names = {k: COMPARE_NAMES[k] for k in args.optimizers}
    finals: dict[str, list[tuple[float, float]]] = {name: [] for name in names.values()}
    configs = {"chosen": (cfg, False), "overlap": (cfg, True), "full_refit": (HeboConfig.full_refit(), True), "defaults": (HeboConfig.hebo_defaults(), False)}
    for seed in args.compare_seeds:
        a = argparse.Namespace(**{**vars(args), "seed": seed})
        runs: dict[str, Trace] = {}
        machine = Machine()
        for key in args.optimizers:
            if key == "cma":
                runs[names[key]], _ = run_cma(a, iters * args.population)
            else:
                c, overlap = configs[key]
                runs[names[key]], _ = run_hebo(a, c, iters, tmp / f"cmp_{key}_{seed}", overlap=overlap)
        print(f"\nComparison at {iters * args.population} evaluations (task {args.task}, {args.side} toss, {args.tosses} tosses, seed {seed}; {machine.line()}): best reward so far / seconds")
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


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="topspin_velocity")
    ap.add_argument("--side", default="right", choices=("right", "left"))
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--population", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tosses", type=int, default=5, help="recorded tosses per evaluation (default 5, as serve-studio optimize and train; 1: the mean toss only, which overfits it)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", choices=("default", "full_refit"), default="default", help="HEBO configuration of the main run and of 'chosen'/'overlap' in --compare: HeboConfig() or HeboConfig.full_refit() (the default before warm starts)")
    ap.add_argument("--seed-serve", action="append", default=[], help="hand-designed serve JSON to seed HEBO with")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--compare-evaluations", type=int, default=400)
    ap.add_argument("--compare-seeds", type=int, nargs="+", default=[0], help="seeds of the comparison runs (README: 0 1 2 at 800 evaluations)")
    ap.add_argument("--skip-main", action="store_true", help="with --compare: skip the full-budget run")
    ap.add_argument("--optimizers", nargs="+", choices=tuple(COMPARE_NAMES), default=["chosen", "overlap", "defaults", "cma"], help="with --compare: which optimizers to run")
    ap.add_argument("--sequential", action="store_true", help="main run: suggest each batch after the previous one is evaluated (default: overlapped)")
    ap.add_argument("--limit-scale", default="1", help="dynamic limit expansion of the runs (serve-studio optimize --limit-scale): 1.5 = acceleration and jerk limits x1.5")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    args.scale = LimitScale.parse(args.limit_scale)
    return args


def main() -> None:
    args = parse_args()
    cfg = HeboConfig() if args.config == "default" else HeboConfig.full_refit()
    out: dict[str, object] = {"task": args.task, "side": args.side, "workers": args.workers, "tosses": args.tosses, "limit_scale": args.scale.to_json(), "config": cfg.to_json()}
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_main:
            main_run(args, cfg, Path(tmp), out)
        if args.compare:
            compare(args, cfg, Path(tmp), out)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
