"""Make a serve robust to the toss's variability, keeping its spin, and resume the search.

A serve designed on the mean toss path meets a ball a centimetre off on a real toss. This
example scores an example serve on the 20 recorded tosses, then searches around it with
CMA-ES (:func:`studio.optimize.robust.robustify_serve`) for a serve legal on more of them whose
spin at the net keeps 90 % of each component, logging every candidate to
``RUN_DIR/robustify.jsonl``. The search is stopped half-way and resumed: the resumed
search replays the log and goes on exactly as an uninterrupted one would.

Run: ``.venv/bin/python examples/05_robustify_serve.py [--evaluations 120]
[--serve examples/serves/sidespin_left.json] [--run-dir examples/out/05_run]`` (600
candidates, ~1 min, is the CLI's default: ``serve-studio robustify SERVE.json``).
"""

from __future__ import annotations

import argparse
import shutil
import threading
from pathlib import Path

import studio

DEFAULT_SERVE = Path(__file__).resolve().parent / "serves" / "sidespin_left.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--serve", type=Path, default=DEFAULT_SERVE)
    parser.add_argument("--evaluations", type=int, default=120)
    parser.add_argument("--run-dir", type=Path, default=Path(__file__).resolve().parent / "out" / "05_run")
    args = parser.parse_args()
    shutil.rmtree(args.run_dir, ignore_errors=True)
    serve = studio.load_serve(args.serve)
    context = studio.EvaluationContext.default()

    stop = threading.Event()

    def progress(done: int, total: int, best: studio.RobustScore) -> None:
        print(f"  {done:4d} / {total} candidates, best legal on {best.legal}/{best.tosses} recorded tosses")
        if done >= args.evaluations // 2:
            stop.set()  # as a user pressing Stop (or Ctrl+C on the CLI)

    options = studio.RobustifyOptions(evaluations=args.evaluations)  # keep_spin 0.9, sigma 0.03, seed 0: defaults
    first = studio.robustify_serve(serve, options, context=context, run_dir=args.run_dir, progress=progress, stop=stop)
    print(f"stopped after {first.evaluations} candidates; resuming")
    res = studio.robustify_serve(
        serve, options, context=context, run_dir=args.run_dir, resume=True,
        progress=lambda done, total, best: print(f"  {done:4d} / {total} candidates, best legal on {best.legal}/{best.tosses}"),
    )  # fmt: skip
    print(res.summary())
    logged = sum(1 for _ in open(args.run_dir / "robustify.jsonl"))
    print(f"{logged} candidates logged in {args.run_dir}")
    if res.improved:
        print(
            f"genes: tau {res.serve.params.tau:.4f} s, racket velocity {tuple(round(v, 3) for v in res.serve.params.velocity)} m/s"
        )


if __name__ == "__main__":
    main()
