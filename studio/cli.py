"""Command line of the serve studio: ``serve-studio <command> ...``.

Commands import their modules lazily so that ``serve-studio --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

Handler = Callable[[argparse.Namespace], int]


def _cmd_app(args: argparse.Namespace) -> int:
    from studio.app import run_app

    run_app(host=args.host, port=args.port, serves_dir=args.serves, library_dir=args.library)
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from studio.evaluate import EvaluationContext, evaluate_robust, evaluate_serve, report_markdown
    from studio.serve import load_serve

    serve = load_serve(args.serve)
    context = EvaluationContext.default()
    task = args.task or serve.task or "topspin_velocity"
    if args.tosses > 1:
        robust = evaluate_robust(serve, context, task=task, tosses=args.tosses, min_legal_fraction=args.legal_fraction)
        evaluation = robust.evaluations[0]
        payload = robust.to_json()
    else:
        evaluation = evaluate_serve(serve, context, task=task, mujoco=args.mujoco)
        payload = evaluation.to_json()
    if args.export:
        from studio.library import ServeLibrary

        entry = ServeLibrary(args.export).add(evaluation, provenance={"kind": "hand-designed", "file": str(args.serve)}, task=task)
        payload["exported"] = {"library": str(args.export), "id": entry.id}
    if args.json:
        print(json.dumps(payload, indent=2))
    else:
        status, checks, metrics = report_markdown(evaluation)
        print(f"{serve.name} ({serve.side} toss, task {task})\n")
        print(status, checks, metrics, sep="\n\n")
        if args.tosses > 1:
            print(f"\nover {args.tosses} recorded tosses: legal fraction {payload['legal_fraction']:.2f}, mean reward {payload['reward']:+.3f}, legal: {payload['legal']}")
        if args.export:
            print(f"\nexported to {args.export} as {payload['exported']['id']}")
    return 0 if payload["legal"] else 1


def _cmd_optimize(args: argparse.Namespace) -> int:
    import threading
    import time
    from pathlib import Path

    from studio.evaluate import EvaluationContext, evaluate_serve
    from studio.optimizer import optimize_serve
    from studio.serve import HandServe, load_serve

    seeds = [load_serve(p) for p in args.seeds]
    run_dir = Path(args.run_dir or f"runs/{time.strftime('%Y%m%d-%H%M%S')}-{args.side}-{args.task}")
    start = time.perf_counter()

    def progress(done: int, total: int, best: float, _params: object) -> None:
        print(f"\r{done:5d}/{total} evaluations  best reward {best:+.3f}  {time.perf_counter() - start:6.1f} s", end="", flush=True)

    stop = threading.Event()
    try:
        result = optimize_serve(
            side=args.side,
            task=args.task,
            run_dir=run_dir,
            seeds=seeds,
            iterations=args.iterations,
            population=args.population,
            tosses=args.tosses,
            seed=args.seed,
            workers=args.workers,
            progress=progress,
            stop=stop,
            resume=args.resume,
        )
    except KeyboardInterrupt:
        print(f"\ninterrupted: every evaluation so far is in {run_dir}; continue with --resume --run-dir {run_dir}")
        return 130
    print()
    if result.best is None or result.summary is None:
        print("nothing evaluated")
        return 1
    s = result.summary
    print(f"chosen serve: mean reward {s.mean_reward:+.3f} on {len(s.rewards)} fresh tosses, legal on {100 * s.legal_fraction:.0f} % ({'legal' if s.legal else 'not legal'})")
    best = HandServe(name=args.name or f"{args.task} {args.side} seed {args.seed}", side=args.side, params=result.best.params, task=args.task, notes=f"HEBO run {run_dir}, seed {args.seed}")
    out = run_dir / "best_serve.json"
    from studio.serve import save_serve

    save_serve(out, best)
    print(f"best serve written to {out}")
    if args.export:
        from studio.library import ServeLibrary

        evaluation = evaluate_serve(best, EvaluationContext.default(), task=args.task)
        entry = ServeLibrary(args.export).add(evaluation, provenance={"kind": "hebo", "run": str(run_dir), "seed": args.seed}, task=args.task)
        print(f"exported to {args.export} as {entry.id}")
    return 0 if s.legal else 1


def _cmd_dashboard(args: argparse.Namespace) -> int:
    from studio.dashboard import run_dashboard

    run_dashboard(library_dir=args.library, host=args.host, port=args.port, studio_url=args.studio_url)
    return 0


def _cmd_toss(args: argparse.Namespace) -> int:
    from studio.toss import toss_report

    print(toss_report(side=args.side, csv_path=args.csv))
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from studio.ball_calibration import main as calibration_main

    return calibration_main([] if args.folds is None else ["--folds", str(args.folds)])


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, Handler]]:
    parser = argparse.ArgumentParser(prog="serve-studio", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    handlers: dict[str, Handler] = {}

    p = sub.add_parser("app", help="start the serve design studio (viser, in the browser)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default: localhost only)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    p.add_argument("--serves", default=None, help="folder of hand-designed serve JSON files (default: examples/serves)")
    p.add_argument("--library", default=None, help="serve library folder to export to (default: ./serve-library)")
    handlers["app"] = _cmd_app

    p = sub.add_parser("evaluate", help="plan, simulate, check and score a serve JSON file")
    p.add_argument("serve", help="hand-designed serve JSON file")
    p.add_argument("--task", default=None, help="reward task preset (default: the serve's task or topspin_velocity)")
    p.add_argument("--tosses", type=int, default=1, help="evaluate on K recorded tosses (robust evaluation)")
    p.add_argument("--legal-fraction", type=float, default=0.8, help="fraction of legal tosses for a legal serve (with --tosses)")
    p.add_argument("--mujoco", action="store_true", help="check with the MuJoCo rollout instead of the analytic predictor")
    p.add_argument("--json", action="store_true", help="print the metrics as JSON")
    p.add_argument("--export", default=None, metavar="DIR", help="write the plan to the serve library folder DIR")
    handlers["evaluate"] = _cmd_evaluate

    p = sub.add_parser("optimize", help="optimize one serve with HEBO, seeded from hand-designed serves")
    p.add_argument("seeds", nargs="*", help="hand-designed serve JSON files observed before the first suggestion")
    p.add_argument("--side", choices=("right", "left"), default="right")
    p.add_argument("--task", default="topspin_velocity", help="reward task preset")
    p.add_argument("--iterations", type=int, default=100, help="HEBO batches (paper: 100)")
    p.add_argument("--population", type=int, default=20, help="suggestions per batch (paper: 20)")
    p.add_argument("--tosses", type=int, default=5, help="recorded tosses per evaluation (default 5; 1: mean toss only, which overfits it)")
    p.add_argument("--workers", type=int, default=2, help="evaluation processes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--name", default=None, help="name of the resulting serve")
    p.add_argument("--run-dir", default=None, help="run folder (evaluations.jsonl, run.json); default runs/<time>-<side>-<task>")
    p.add_argument("--resume", action="store_true", help="continue the run in --run-dir without repeating evaluations")
    p.add_argument("--export", default=None, metavar="DIR", help="export the chosen serve to this serve library")
    handlers["optimize"] = _cmd_optimize

    p = sub.add_parser("dashboard", help="serve the Panel dashboard of a serve library")
    p.add_argument("--library", default="serve-library", help="serve library folder (default ./serve-library)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default: localhost only)")
    p.add_argument("--port", type=int, default=5006)
    p.add_argument("--studio-url", default="http://127.0.0.1:8080", help="link to the studio shown beside each serve")
    handlers["dashboard"] = _cmd_dashboard

    p = sub.add_parser("toss", help="analyse toss recordings: lift time, rise, spread")
    p.add_argument("--side", choices=("right", "left"), default="right")
    p.add_argument("--csv", default=None, help="recordings CSV (toss_id,t,x,y,z); default: the shipped recordings")
    handlers["toss"] = _cmd_toss

    p = sub.add_parser("calibrate", help="fit the racket impact model on the bounce data and print cross-validated errors")
    p.add_argument("--folds", type=int, default=None)
    handlers["calibrate"] = _cmd_calibrate
    return parser, handlers


def main(argv: Sequence[str] | None = None) -> int:
    parser, handlers = build_parser()
    args = parser.parse_args(argv)
    from studio.errors import StudioError

    try:
        return handlers[args.command](args)
    except StudioError as err:
        print(f"serve-studio {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
