"""Optimize a serve with HEBO, seeded from a hand-designed serve, and resume the run.

A short HEBO run (``--iterations`` batches of ``--population``, evaluated in this
process on the mean toss) for a reward task, seeded with an example serve: the seed is
evaluated and observed before the first suggestion. Progress is printed after each
batch; every evaluation is logged to ``RUN_DIR/evaluations.jsonl`` as it finishes. The
run is then resumed with more batches: the logged evaluations are read back, none is
repeated. The chosen serve is the best mean over fresh recorded tosses of the top
candidates, printed with its genes.

Run: ``.venv/bin/python examples/04_optimize_serve.py [--iterations 3] [--population 10]
[--task backspin] [--run-dir examples/out/04_run]`` (the paper's budget is 100 x 20; use
``serve-studio optimize`` with worker processes for that).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import studio

SEED_SERVE = Path(__file__).resolve().parent / "serves" / "backspin_right.json"


def progress(done: int, total: int, best: float, params: studio.ServeParams | None) -> None:
    tau = f", best tau {params.tau:.3f} s" if params is not None else ""
    print(f"  {done:4d} / {total} evaluations, best reward {best:+.3f}{tau}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--population", type=int, default=10)
    parser.add_argument("--task", default="backspin")
    parser.add_argument("--run-dir", type=Path, default=Path(__file__).resolve().parent / "out" / "04_run")
    args = parser.parse_args()
    seed = studio.load_serve(SEED_SERVE)
    context = studio.EvaluationContext.for_training()  # in-process evaluation, no IPOPT fallback
    shutil.rmtree(args.run_dir, ignore_errors=True)

    def run_batches(iterations: int, *, resume: bool) -> studio.OptimizationResult:
        options = studio.OptimizeOptions(
            side=seed.side,
            task=args.task,
            iterations=iterations,
            population=args.population,
            seed=0,
            workers=1,
            top_k=3,
            final_tosses=5,
        )
        return studio.optimize_serve(
            options, run_dir=args.run_dir, context=context, seeds=[seed], progress=progress, resume=resume
        )

    print(f"HEBO, {args.iterations} x {args.population}, seeded with {seed.name!r}:")
    first = run_batches(args.iterations, resume=False)
    print(f"resumed for {args.iterations} more batches:")
    run = run_batches(2 * args.iterations, resume=True)
    print(
        f"\n{first.evaluations} evaluations, then {run.evaluations} after the resume (log: {args.run_dir / 'evaluations.jsonl'})"
    )
    if run.best is None or run.summary is None:
        print("nothing evaluated")
        return
    s = run.summary
    p = run.best.params
    print(
        f"chosen serve: mean reward {s.mean_reward:+.3f} on {len(s.rewards)} fresh tosses, legal on "
        f"{100 * s.legal_fraction:.0f} %\n  tau {p.tau:.3f} s, racket velocity {tuple(round(v, 2) for v in p.velocity)} m/s, "
        f"yaw {p.yaw:.2f} rad, roll {p.roll:.2f} rad, return {p.t_return:.2f} s, offset {tuple(round(v, 3) for v in p.offset)} m"
    )


if __name__ == "__main__":
    main()
