"""Evaluate a hand-designed serve: plan, collision check, ball flight, ITTF checks, reward.

The serve file (default ``examples/serves/backspin_left.json``) is evaluated on the mean
toss path for a reward task, printing the verdict, the legality chain and the metrics
(the same Markdown the studio shows; the first evaluation's plan time includes building
the planner's caches), then robustly on 10 recorded tosses (one plan, ten
ball flights), printing the legal fraction and the failing checks.

Run: ``.venv/bin/python examples/03_evaluate_serve.py [SERVE.json] [TASK]``
(tasks: aiming, topspin_velocity, backspin, sidespin, and their ``_low`` variants).
"""

from __future__ import annotations

import sys
from pathlib import Path

import studio

DEFAULT_SERVE = Path(__file__).resolve().parent / "serves" / "backspin_left.json"
ROBUST_TOSSES = 10
"""Recorded tosses of the robust evaluation."""


def main(serve_path: Path, task: str) -> None:
    context = studio.EvaluationContext.default()  # robot, toss models, planner, collision model
    serve = studio.load_serve(serve_path)
    ev = studio.evaluate_serve(serve, context, task=task)
    status, checks, metrics = studio.report_markdown(ev)
    print(status, checks, metrics, sep="\n\n")
    robust = studio.evaluate_robust(serve, context, task=task, tosses=ROBUST_TOSSES)
    print(
        f"\nover {ROBUST_TOSSES} recorded tosses: legal on {100 * robust.legal_fraction:.0f} % "
        f"(robustly legal: {robust.legal}), mean reward {robust.reward:+.3f}, failing checks {robust.failed_checks() or 'none'}"
    )


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_SERVE, sys.argv[2] if len(sys.argv) > 2 else "backspin")
