"""Command line of the serve studio: ``serve-studio <command> ...``.

Commands import their modules lazily so that ``serve-studio --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from studio.optimize.optimizer import OptimizationResult
    from studio.serve.efforts import EffortReport
    from studio.serve.evaluate import Evaluation, EvaluationContext, RobustEvaluation
    from studio.serve.params import HandServe, LimitScale

Handler = Callable[[argparse.Namespace], int]

ROBUSTIFY_HELP = (
    "then search N candidates around the chosen serve for one legal on more recorded tosses, keeping its spin "
    "(serve-studio robustify; ~0.1 s a candidate, logged in <run>/robustify/ and resumed; default 0: off)"
)
LIMIT_SCALE_HELP = (
    "dynamic limit expansion: a factor on the joint acceleration and jerk limits (e.g. 1.3), "
    "or velocity=..,acceleration=..,jerk=.. factors"
)


def _cmd_app(args: argparse.Namespace) -> int:
    from studio.ui.app import run_app

    run_app(host=args.host, port=args.port, serves_dir=args.serves, library_dir=args.library)
    return 0


EFFORT_LIMIT_HELP = (
    "raise (or set) a joint's effort limit for this export on purpose, JOINT=VALUE [N | N m], repeatable, e.g. gantry_x=4700: "
    "a plan beyond the robot's limits (robots/serve_robot.toml, stated estimates) is refused otherwise; the entry records the raised limits"
)


def _effort_limits(args: argparse.Namespace) -> dict[str, float]:
    """The ``--effort-limit JOINT=VALUE`` options as {joint: limit} (InvalidInputError if bad)."""
    from studio.robot.description import load_spec
    from studio.serve.efforts import parse_limits

    return parse_limits(args.effort_limit, load_spec().joint_names)


@dataclass
class _EvaluateRun:
    """What ``serve-studio evaluate`` found for one serve, gathered for the export and the report."""

    serve: HandServe
    """The serve evaluated (its limit scale replaced by ``--limit-scale``)."""
    task: str
    """Reward task preset."""
    evaluation: Evaluation
    """The evaluation shown (with ``--tosses``: the first recorded toss's)."""
    robust: RobustEvaluation | None
    """The robust evaluation (``--tosses`` > 1), else None."""
    payload: dict[str, Any]
    """The JSON report."""
    efforts: EffortReport | None = None
    """The effort report with the ``--effort-limit`` limits, if the plan has one."""
    exported_note: str = ""
    """Added to the export line of the report."""
    refused: str | None = None
    """Why the library refused the export, if it did."""


def _check_evaluate_args(args: argparse.Namespace) -> None:
    """Refuse option combinations ``evaluate`` cannot honour (InvalidInputError)."""
    from studio.errors import InvalidInputError

    if args.mujoco and args.tosses > 1:
        raise InvalidInputError(
            "--mujoco cannot be combined with --tosses > 1: the MuJoCo rollout tosses the ball from the cup as the motion "
            "predicts, it cannot replay recorded tosses (use --mujoco alone, or --tosses without it)"
        )


def _evaluated_serve(args: argparse.Namespace) -> HandServe:
    """The ``evaluate`` command's serve file, with the ``--limit-scale`` given."""
    from dataclasses import replace

    from studio.serve.params import LimitScale, load_serve

    serve = load_serve(args.serve)
    if args.limit_scale is not None:
        serve = replace(serve, limit_scale=LimitScale.parse(args.limit_scale))
    return serve


def _run_evaluation(args: argparse.Namespace, serve: HandServe, context: EvaluationContext) -> _EvaluateRun:
    """Evaluate the serve on the mean toss (or ``--mujoco``), or on ``--tosses`` recorded tosses."""
    from studio.serve.evaluate import evaluate_robust, evaluate_serve

    task = args.task or serve.task or "topspin_velocity"
    if args.tosses > 1:
        robust = evaluate_robust(serve, context, task=task, tosses=args.tosses, min_legal_fraction=args.legal_fraction)
        evaluation = robust.evaluations[0]  # the checks and metrics shown: one recorded toss
        return _EvaluateRun(serve, task, evaluation, robust, robust.to_json())
    evaluation = evaluate_serve(serve, context, task=task, mujoco=args.mujoco)
    return _EvaluateRun(serve, task, evaluation, None, evaluation.to_json())


def _robust_provenance(robust: RobustEvaluation) -> dict[str, object]:
    """The robust result as it goes into a library entry's provenance."""
    return {
        "tosses": len(robust.evaluations),
        "toss_samples": list(robust.samples),
        "legal": robust.legal,
        "legal_fraction": robust.legal_fraction,
        "min_legal_fraction": robust.min_legal_fraction,
        "mean_reward": robust.reward,
    }


def _export_evaluation(
    args: argparse.Namespace, run: _EvaluateRun, context: EvaluationContext, effort_limits: dict[str, float]
) -> None:
    """Add the evaluated plan to the ``--export`` library; the outcome (or refusal) goes into ``run``."""
    from studio.optimize.workflow import export_evaluation
    from studio.serve.efforts import EffortLimitError
    from studio.serve.evaluate import evaluate_motion

    exported = run.evaluation
    provenance: dict[str, object] = {"kind": "hand-designed", "file": str(args.serve)}
    if run.robust is not None:
        # The library holds mean-toss evaluations (as optimize and train export): the same
        # plan on the mean toss path, never one sampled toss's; the robust result goes along.
        exported = evaluate_motion(run.evaluation.motion, context, task=run.task)
        provenance["robust"] = _robust_provenance(run.robust)
        run.exported_note = (
            f" (the mean toss path's evaluation: {'legal' if exported.legal else 'not legal'}, reward {exported.reward.total:+.3f}; "
            "the robust result is in its provenance)"
        )
    try:
        entry = export_evaluation(
            args.export, exported, context=context, task=run.task, provenance=provenance, effort_limits=effort_limits
        )
    except EffortLimitError as err:  # the report goes out first, then the refusal
        run.refused = str(err)
        run.payload["exported"] = {"library": str(args.export), "refused": run.refused}
    else:
        run.payload["exported"] = {
            "library": str(args.export),
            "id": entry.id,
            "toss": "mean",
            "legal": exported.legal,
            "reward": exported.reward.total,
        }


def _print_evaluation(args: argparse.Namespace, run: _EvaluateRun) -> None:
    """Print the ``evaluate`` report for a person: checks, metrics, efforts, robust verdict, export."""
    from studio.serve.evaluate import report_markdown

    serve, robust, payload = run.serve, run.robust, run.payload
    status, checks, metrics = report_markdown(run.evaluation)
    print(f"{serve.name} ({serve.side} toss, task {run.task})\n")
    if robust is not None and robust.samples:
        print(
            f"checks and metrics of recorded toss {robust.samples[0] + 1} (the first of {len(robust.evaluations)} drawn; the verdict over all of them is at the end)\n"
        )
    print(status, checks, metrics, sep="\n\n")
    if run.efforts is not None:
        print("\n" + run.efforts.markdown())
    if args.tosses > 1:
        print(
            f"\nover {args.tosses} recorded tosses: legal fraction {payload['legal_fraction']:.2f}, mean reward {payload['reward']:+.3f}, legal: {payload['legal']}"
        )
    if run.refused is not None:
        print(f"\nnot exported to {args.export}: {run.refused}")
    elif args.export:
        print(f"\nexported to {args.export} as {payload['exported']['id']}{run.exported_note}")


def _cmd_evaluate(args: argparse.Namespace) -> int:
    """Plan, simulate, check and score a serve file; optionally export it to a serve library."""
    import json

    from studio.serve.efforts import effort_report
    from studio.serve.evaluate import EvaluationContext

    _check_evaluate_args(args)
    effort_limits = _effort_limits(args)
    serve = _evaluated_serve(args)
    context = EvaluationContext.default()
    run = _run_evaluation(args, serve, context)
    efforts = effort_report(run.evaluation.motion, context.robot)
    run.efforts = efforts.with_limits(effort_limits) if efforts is not None else None
    run.payload["efforts"] = run.efforts.to_json() if run.efforts is not None else None
    if args.export:
        _export_evaluation(args, run, context, effort_limits)
    if args.json:
        print(json.dumps(run.payload, indent=2))
    else:
        _print_evaluation(args, run)
    return 0 if run.payload["legal"] and run.refused is None else 1


def _optimize_limit_scale(args: argparse.Namespace, seeds: list[HandServe]) -> LimitScale | None:
    """``--limit-scale``, else the seed serves' common scale (InvalidInputError if they differ), else None."""
    from studio.errors import InvalidInputError
    from studio.serve.params import LimitScale

    limit_scale = LimitScale.parse(args.limit_scale) if args.limit_scale is not None else None
    if limit_scale is None and not args.resume and seeds:  # the seeds' own scale
        scales = {s.limit_scale for s in seeds}
        if len(scales) > 1:
            raise InvalidInputError(
                f"the seed serves plan with different limit scales {[s.to_json() for s in scales]}: choose one with --limit-scale"
            )
        limit_scale = scales.pop()
    return limit_scale


def _run_optimize(
    args: argparse.Namespace, run_dir: Path, seeds: list[HandServe], limit_scale: LimitScale | None
) -> OptimizationResult:
    """Run the HEBO optimization the options ask for, printing its progress on one line."""
    import time

    from studio.optimize.optimizer import OptimizeOptions, optimize_serve

    start = time.perf_counter()

    def progress(done: int, total: int, best: float, _params: object) -> None:
        print(
            f"\r{done:5d}/{total} evaluations  best reward {best:+.3f}  {time.perf_counter() - start:6.1f} s",
            end="",
            flush=True,
        )

    options = OptimizeOptions(
        side=args.side,
        task=args.task,
        iterations=args.iterations,
        population=args.population,
        tosses=args.tosses,
        seed=args.seed,
        workers=args.workers,
        overlap=False if args.sequential else None,
        limit_scale=limit_scale,
    )
    return optimize_serve(options, run_dir=run_dir, seeds=seeds, resume=args.resume, progress=progress)


def _final_serve(args: argparse.Namespace, chosen: HandServe, run_dir: Path) -> HandServe:
    """The chosen serve made robust with ``--robustify``, written to the run folder."""
    from studio.optimize.workflow import make_robust
    from studio.serve.params import save_serve

    best = make_robust(
        chosen, run_dir, evaluations=args.robustify, task=args.task, say=lambda line: print(line, flush=True)
    )
    out = run_dir / "best_serve.json"
    save_serve(out, best)
    print(f"best serve written to {out}")
    return best


def _export_optimized(
    args: argparse.Namespace, best: HandServe, run_dir: Path, effort_limits: dict[str, float]
) -> None:
    """Evaluate the final serve on the mean toss and add it to the ``--export`` library."""
    from studio.optimize.workflow import export_evaluation, hebo_provenance
    from studio.serve.evaluate import EvaluationContext, evaluate_serve

    context = EvaluationContext.default()
    evaluation = evaluate_serve(best, context, task=args.task)
    entry = export_evaluation(
        args.export,
        evaluation,
        context=context,
        task=args.task,
        provenance=hebo_provenance(run_dir, args.seed),
        effort_limits=effort_limits,
    )
    print(f"exported to {args.export} as {entry.id}")


def _cmd_optimize(args: argparse.Namespace) -> int:
    """Optimize one serve with HEBO; write the chosen serve and optionally export it to a library."""
    from studio.errors import StudioError
    from studio.optimize.workflow import chosen_serve, new_run_dir
    from studio.serve.params import load_serve

    effort_limits = _effort_limits(args)
    seeds = [load_serve(p) for p in args.seeds]
    limit_scale = _optimize_limit_scale(args, seeds)
    run_dir = Path(args.run_dir) if args.run_dir else new_run_dir("runs", args.side, args.task)
    try:
        result = _run_optimize(args, run_dir, seeds, limit_scale)
    except KeyboardInterrupt:
        print(f"\ninterrupted: every evaluation so far is in {run_dir}; continue with --resume --run-dir {run_dir}")
        return 130
    except StudioError:  # e.g. a worker process died (optimizer.WorkerDiedError): end the progress line first
        print(flush=True)
        raise
    print()
    name = args.name or f"{args.task} {args.side} seed {args.seed}"
    chosen = chosen_serve(result, name=name, notes=f"HEBO run {run_dir}, seed {args.seed}")
    if chosen is None or result.summary is None:
        print("nothing evaluated")
        return 1
    s = result.summary
    print(
        f"chosen serve: mean reward {s.mean_reward:+.3f} on {len(s.rewards)} fresh tosses, legal on {100 * s.legal_fraction:.0f} % ({'legal' if s.legal else 'not legal'})"
    )
    best = _final_serve(args, chosen, run_dir)
    if args.export:
        _export_optimized(args, best, run_dir, effort_limits)
    return 0 if s.legal else 1


def _cmd_robustify(args: argparse.Namespace) -> int:
    """Search around a serve for one legal on more recorded tosses (studio.optimize.robust)."""
    import time
    from pathlib import Path

    from studio.optimize.robust import RobustifyOptions, RobustScore, robustify_serve
    from studio.serve.params import load_serve, save_serve

    serve = load_serve(args.serve)
    run_dir = Path(args.run_dir) if args.run_dir else None
    start = time.perf_counter()

    def progress(done: int, total: int, best: RobustScore) -> None:
        print(
            f"\r{done:4d}/{total} candidates  best legal on {best.legal}/{best.tosses} tosses  {time.perf_counter() - start:5.1f} s",
            end="",
            flush=True,
        )

    options = RobustifyOptions(
        task=args.task, keep_spin=args.keep_spin, sigma=args.sigma, evaluations=args.evaluations, seed=args.seed
    )
    try:
        res = robustify_serve(
            serve,
            options,
            run_dir=run_dir,
            resume=args.resume,
            progress=progress,
        )
    except KeyboardInterrupt:
        where = f"; continue with --resume --run-dir {run_dir}" if run_dir else " (give --run-dir to be able to resume)"
        print(f"\ninterrupted{where}")
        return 130
    print()
    print(res.summary())
    if not res.improved:
        print("nothing written")
        return 1
    out = Path(args.out) if args.out else Path(args.serve).with_name(Path(args.serve).stem + "_robust.json")
    save_serve(out, res.serve)
    print(f"written to {out}")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    """Train ``count`` serves for a task (one HEBO run each, seeds seed0, seed0+1, ...),
    export each legal chosen serve to the library, and print a Table II-like summary."""
    from pathlib import Path

    from studio.optimize.training import TrainConfig, TrainedServe, finished_runs, summary_table, train_serves
    from studio.serve.params import LimitScale, load_serve

    cfg = TrainConfig(
        task=args.task,
        count=args.count,
        side=args.side,
        iterations=args.iterations,
        population=args.population,
        tosses=args.tosses,
        seed=args.seed,
        workers=args.workers,
        seeds=tuple(load_serve(p) for p in args.seeds),
        runs_dir=Path(args.runs or f"runs/train-{args.task}"),
        overlap=False if args.sequential else None,
        limit_scale=LimitScale.parse(args.limit_scale) if args.limit_scale is not None else LimitScale(),
        robustify=args.robustify,
    )

    def progress(r: TrainedServe, total: int) -> None:
        if r.reason == "already trained":
            print(f"[{r.index + 1}/{total}] {r.run_dir.name}: already trained", flush=True)
            return
        verdict = f"exported as {r.entry_id}" if r.entry_id else f"not legal ({r.reason}), not exported"
        print(
            f"[{r.index + 1}/{total}] {r.run_dir.name}: reward {r.reward:+.3f}, {verdict} ({r.seconds:.0f} s)",
            flush=True,
        )

    if args.report:
        done = finished_runs(cfg)
        print(f"{len(done)} of {cfg.count} {cfg.task} runs finished in {cfg.runs_dir}\n")
        print(summary_table(done, cfg.task))
        return 0
    if args.library is None:
        print("error: --library is required to train (or pass --report)", file=sys.stderr)
        return 2
    where = f"on the Ray cluster {args.ray}" if args.ray else f"locally, {args.workers} evaluation processes per run"
    print(f"training {cfg.count} {cfg.task} serves {where}; run folders in {cfg.runs_dir}", flush=True)
    try:
        results = train_serves(cfg, args.library, ray_address=args.ray, progress=progress)
    except KeyboardInterrupt:
        print(
            f"\ninterrupted: finished runs and every logged evaluation are in {cfg.runs_dir}; run the same command again to resume"
        )
        return 130
    print()
    print(summary_table(results, cfg.task))
    return 0


def _cmd_dashboard(args: argparse.Namespace) -> int:
    from studio.errors import InvalidInputError
    from studio.ui.dashboard import run_dashboard

    if args.library_dir is not None and args.library is not None and Path(args.library_dir) != Path(args.library):
        raise InvalidInputError(f"two library folders given: {args.library_dir} and --library {args.library}")
    library = args.library_dir or args.library or "serve-library"
    if args.reference is not None and not Path(args.reference).is_file():
        raise InvalidInputError(f"--reference {args.reference}: no such file")
    run_dashboard(
        library_dir=library,
        host=args.host,
        port=args.port,
        studio_url=args.studio_url,
        runs_dir=args.runs,
        reference=args.reference,
    )
    return 0


def _cmd_toss(args: argparse.Namespace) -> int:
    from studio.toss.report import toss_report

    if args.generate:
        from studio.toss.defaults import DEFAULT_N_TOSSES, DEFAULT_SEED, DEFAULT_TOSS_DIR, generate_default_recordings

        out = args.out or DEFAULT_TOSS_DIR
        n, seed = args.n or DEFAULT_N_TOSSES, DEFAULT_SEED if args.seed is None else args.seed
        for path in generate_default_recordings(out, n=n, seed=seed):
            print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")
        args.csv = args.csv or str(Path(out) / f"{args.side}.csv")
    print(toss_report(side=args.side, csv_path=args.csv))
    return 0


def _cmd_robot_files(args: argparse.Namespace) -> int:
    """Write the URDF and MJCF from the robot TOML, or ``--check`` them (exit 1 when stale)."""
    from studio.robot.description import check_files, write_files

    if args.check:
        stale = check_files(args.out, spec_path=args.toml)
        if stale:
            print(f"out of date: {', '.join(stale)} (run serve-studio robot-files)", file=sys.stderr)
            return 1
        print("robot description files are up to date")
        return 0
    for path in write_files(args.out, spec_path=args.toml):
        print(f"wrote {path}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from studio.errors import DataFileError, InvalidInputError
    from studio.physics import ball_calibration as BC
    from studio.physics import flight_calibration as FC

    folds = 5 if args.folds is None else args.folds
    if args.no_serve_contacts and args.serve_contacts is not None:
        print("error: --serve-contacts and --no-serve-contacts exclude each other", file=sys.stderr)
        return 2
    if args.write and args.no_cv:
        print("error: --write records cross-validated figures: drop --no-cv", file=sys.stderr)
        return 2
    contacts = None if args.no_serve_contacts else (args.serve_contacts or BC.SERVE_CONTACTS_CSV)
    try:
        FC.load_match_events(args.match)  # a missing or malformed match file fails before the racket fits
        racket = BC.calibrate(folds=folds, repeats=args.repeats, serve_contacts=contacts)
        print("Racket impact model (velocity / spin error norms, RMS; CV = cross-validated per data set):")
        print(BC.format_table(racket))
        print()
        flight = FC.calibrate_flight(args.match, folds=folds, player_cv=not args.no_cv, rally_cv=not args.no_cv)
        print(FC.format_flight_table(flight))
    except (DataFileError, InvalidInputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.write:
        BC.write_models_json(racket)
        FC.write_flight_json(flight)
        print(
            f"\nwrote {BC.RACKET_MODELS_JSON} and {FC.FLIGHT_MODEL_JSON} (the defaults in studio/physics/ball.py follow the flight record by hand)"
        )
    return 0


def _cmd_library(args: argparse.Namespace) -> int:
    return int(args.library_handler(args))


def _library_list(args: argparse.Namespace) -> int:
    from studio.library.selection import serve_cluster, usage_count
    from studio.library.store import ServeLibrary

    entries = ServeLibrary(args.dir).entries()
    print(f"{len(entries)} serves in {args.dir}")
    print("| id | name | side | task | cluster | reward | legal | used | won | lost | aces |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for e in entries:
        d = e.data
        usage = d.get("usage")
        u: dict[str, Any] = usage if isinstance(usage, dict) else {}
        print(
            f"| {e.id} | {d['name']} | {d['side']} | {d.get('task') or ''} | {serve_cluster(e)} | {float(d['reward']):+.3f} "
            f"| {'yes' if d['legal'] else 'no'} | {usage_count(e)} | {u.get('won', 0)} | {u.get('lost', 0)} | {u.get('aces', 0)} |"
        )
    return 0


def _library_show(args: argparse.Namespace) -> int:
    import json

    from studio.library.selection import serve_cluster
    from studio.library.store import ServeLibrary

    entry = ServeLibrary(args.dir).get(args.id)
    print(f"cluster: {serve_cluster(entry)}")
    print(json.dumps(entry.data, indent=2))
    return 0


def _library_validate(args: argparse.Namespace) -> int:
    from studio.errors import DataFileError
    from studio.library.match import MATCH_LOG, load_points
    from studio.library.store import ServeLibrary, orphan_files

    lib = ServeLibrary(args.dir)
    try:
        if not lib.index_path.exists():
            raise DataFileError(lib.index_path, "missing: not a serve library")
        entries = lib.entries()
        for e in entries:
            e.arrays()
        points = load_points(lib.folder / MATCH_LOG)
    except DataFileError as err:
        print(f"serve-studio library validate: invalid: {err}", file=sys.stderr)
        return 1
    leftovers = orphan_files(lib, entries)
    print(f"{args.dir}: valid ({len(entries)} serves with their arrays, {len(points)} logged points)")
    if leftovers:  # valid, but files no entry refers to: left by a crash or by hand
        print(
            f"note: {len(leftovers)} file(s) no entry refers to (kept; delete them by hand if unwanted): "
            + ", ".join(leftovers[:10])
        )
    return 0


def _library_select(args: argparse.Namespace) -> int:
    from studio.library.match import next_serve
    from studio.library.selection import serve_cluster, usage_count
    from studio.library.store import ServeLibrary

    entry = next_serve(ServeLibrary(args.dir), args.previous, strict=True)
    print(f"{entry.id}\t{entry.data['name']}\t{serve_cluster(entry)}\tused {usage_count(entry)}")
    return 0


def _library_record(args: argparse.Namespace) -> int:
    from studio.errors import InvalidInputError
    from studio.library.match import record_point
    from studio.library.store import ServeLibrary

    if args.server == "robot" and args.serve is None:  # the flags named (record_point checks the same)
        raise InvalidInputError("--serve ID is required when the robot serves")
    if args.server == "opponent" and args.serve is not None:
        raise InvalidInputError("--serve is only for robot serves (--server robot)")
    points = record_point(
        ServeLibrary(args.dir),
        server=args.server,
        winner=args.winner,
        serve=args.serve,
        ace=args.ace,
        opponent=args.opponent,
    )
    print(
        f"recorded point {len(points)}: server {args.server}, serve {args.serve or '-'}, winner {args.winner}{', ace' if args.ace else ''}"
    )
    return 0


def _library_stats(args: argparse.Namespace) -> int:
    from studio.library.match import MATCH_LOG, load_points, stats_report
    from studio.library.store import ServeLibrary

    lib = ServeLibrary(args.dir)
    print(stats_report(lib.entries(), load_points(lib.folder / MATCH_LOG), min_uses=args.min_uses))
    return 0


def _library_prune(args: argparse.Namespace) -> int:
    from studio.library.match import MATCH_LOG, PRUNED_DIR, load_points, prune, prune_candidates, serve_records
    from studio.library.store import ServeLibrary

    lib = ServeLibrary(args.dir)
    entries = lib.entries()
    records = serve_records(load_points(lib.folder / MATCH_LOG), [e.id for e in entries])
    candidates, total = prune_candidates(records, min_uses=args.min_uses)
    baseline = "-" if total.n == 0 else f"{100 * total.rate:.1f} %"
    print(
        f"library serving win rate {baseline} over {total.n} serves; rule: used >= {args.min_uses} and Wilson 95 % upper bound below it"
    )
    for c in candidates:
        r = c.record
        print(f"  {r.id}: {r.won}/{r.used} won, upper bound {100 * c.upper:.1f} %")
    if not candidates:
        print("nothing to prune")
    elif args.dry_run:
        print(f"dry run: {len(candidates)} serve(s) would be pruned")
    else:
        pruned = prune(lib, [c.record.id for c in candidates])
        print(f"pruned {len(pruned)} serve(s) into {lib.folder / PRUNED_DIR}: {', '.join(pruned)}")
    return 0


def _bounded(kind: type, low: float, high: float) -> Any:
    """An argparse type: a ``kind`` (int or float) number in [low, high], else a usage error
    naming the range (argparse exits 2 with it; NaN, inf and text are refused)."""

    def convert(text: str) -> Any:
        import math

        try:
            value = kind(text)
        except (TypeError, ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"{text!r} is outside the allowed range [{low:g}, {high:g}]")
        return value

    return convert


def _add_app_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]) -> None:
    """Add the ``app`` command and its handler."""
    p = sub.add_parser("app", help="start the serve design studio (viser, in the browser)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default: localhost only)")
    p.add_argument("--port", type=_bounded(int, 1, 65535), default=8080, help="port (default 8080)")
    p.add_argument(
        "--serves",
        default=None,
        help="folder of hand-designed serve JSON files, read and written by 'save as seed' (default: ./serves; the shipped examples are listed too)",
    )
    p.add_argument("--library", default=None, help="serve library folder to export to (default: ./serve-library)")
    handlers["app"] = _cmd_app


def _add_evaluate_parser(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]
) -> None:
    """Add the ``evaluate`` command and its handler."""
    p = sub.add_parser("evaluate", help="plan, simulate, check and score a serve JSON file")
    p.add_argument("serve", help="hand-designed serve JSON file")
    p.add_argument("--task", default=None, help="reward task preset (default: the serve's task or topspin_velocity)")
    p.add_argument(
        "--tosses", type=_bounded(int, 1, 200), default=1, help="evaluate on K recorded tosses (robust evaluation)"
    )
    p.add_argument(
        "--legal-fraction",
        type=_bounded(float, 0.0, 1.0),
        default=0.8,
        help="fraction of legal tosses for a legal serve (with --tosses)",
    )
    p.add_argument(
        "--mujoco",
        action="store_true",
        help="check with the MuJoCo rollout (ball tossed from the cup, robot and ball in MuJoCo) instead of the analytic predictor; not with --tosses > 1",
    )
    p.add_argument("--json", action="store_true", help="print the metrics as JSON")
    p.add_argument(
        "--export",
        default=None,
        metavar="DIR",
        help="write the plan to the serve library folder DIR (with --tosses: its mean-toss evaluation, the robust result in the provenance)",
    )
    p.add_argument(
        "--limit-scale",
        default=None,
        metavar="S",
        help=LIMIT_SCALE_HELP + " (default: the serve file's limit_scale, else 1)",
    )
    p.add_argument("--effort-limit", action="append", default=[], metavar="JOINT=VALUE", help=EFFORT_LIMIT_HELP)
    handlers["evaluate"] = _cmd_evaluate


def _add_robustify_parser(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]
) -> None:
    """Add the ``robustify`` command and its handler."""
    p = sub.add_parser(
        "robustify", help="search around a serve for one legal on more recorded tosses, keeping its spin"
    )
    p.add_argument("serve", help="hand-designed serve JSON file")
    p.add_argument("--task", default=None, help="reward task of the tie-break (default: the serve's)")
    p.add_argument(
        "--keep-spin",
        type=_bounded(float, 0.0, 1.0),
        default=0.9,
        help="fraction of each spin component (top/back, side) at the net to keep (default 0.9)",
    )
    p.add_argument(
        "--sigma",
        type=_bounded(float, 1e-6, 0.5),
        default=0.03,
        help="CMA-ES step on the normalized genome, at most 0.5 (default 0.03)",
    )
    p.add_argument(
        "--evaluations",
        type=_bounded(int, 1, 1_000_000),
        default=600,
        help="candidates in all, in whole generations of 12 (default 600, ~1 min); a resume counts the logged ones",
    )
    p.add_argument("--seed", type=_bounded(int, 0, 2**31 - 2), default=0)
    p.add_argument(
        "--out", default=None, help="where to write the robust serve (default: <serve>_robust.json beside it)"
    )
    p.add_argument("--run-dir", default=None, help="log every candidate here (robustify.jsonl) to be able to resume")
    p.add_argument("--resume", action="store_true", help="continue the search logged in --run-dir")
    handlers["robustify"] = _cmd_robustify


def _add_optimize_parser(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]
) -> None:
    """Add the ``optimize`` command and its handler."""
    p = sub.add_parser("optimize", help="optimize one serve with HEBO, seeded from hand-designed serves")
    p.add_argument("seeds", nargs="*", help="hand-designed serve JSON files observed before the first suggestion")
    p.add_argument("--side", choices=("right", "left"), default="right")
    p.add_argument("--task", default="topspin_velocity", help="reward task preset")
    p.add_argument("--iterations", type=_bounded(int, 0, 10_000), default=100, help="HEBO batches (paper: 100)")
    p.add_argument("--population", type=_bounded(int, 1, 1000), default=20, help="suggestions per batch (paper: 20)")
    p.add_argument(
        "--tosses",
        type=_bounded(int, 1, 200),
        default=5,
        help="recorded tosses per evaluation (default 5; 1: mean toss only, which overfits it)",
    )
    p.add_argument("--workers", type=_bounded(int, 1, 64), default=2, help="evaluation processes")
    p.add_argument("--seed", type=_bounded(int, 0, 2**32 - 1), default=0)
    p.add_argument("--name", default=None, help="name of the resulting serve")
    p.add_argument(
        "--run-dir", default=None, help="run folder (evaluations.jsonl, run.json); default runs/<time>-<side>-<task>"
    )
    p.add_argument("--resume", action="store_true", help="continue the run in --run-dir without repeating evaluations")
    p.add_argument("--export", default=None, metavar="DIR", help="export the chosen serve to this serve library")
    p.add_argument(
        "--sequential",
        action="store_true",
        help="suggest each batch after the previous one is evaluated (default with 2+ workers: the next batch is suggested while the workers evaluate)",
    )
    p.add_argument(
        "--limit-scale",
        default=None,
        metavar="S",
        help=LIMIT_SCALE_HELP + " (default: the seed serves' own scale, else 1; on --resume: the run's own)",
    )
    p.add_argument("--effort-limit", action="append", default=[], metavar="JOINT=VALUE", help=EFFORT_LIMIT_HELP)
    p.add_argument("--robustify", type=_bounded(int, 0, 1_000_000), default=0, metavar="N", help=ROBUSTIFY_HELP)
    handlers["optimize"] = _cmd_optimize


def _add_train_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]) -> None:
    """Add the ``train`` command and its handler."""
    p = sub.add_parser(
        "train", help="train COUNT serves for a task (one HEBO run each) into a library, print a Table II-like summary"
    )
    p.add_argument("--task", required=True, help="reward task preset")
    p.add_argument("--count", type=_bounded(int, 1, 10_000), default=25)
    p.add_argument("--library", default=None, help="serve library folder to export to (required to train)")
    p.add_argument(
        "--report", action="store_true", help="print the summary of the finished runs in --runs and exit (no training)"
    )
    p.add_argument("--seeds", nargs="*", default=[], help="hand-designed serve JSON files to seed every run")
    p.add_argument("--side", choices=("right", "left", "both"), default="both")
    p.add_argument("--iterations", type=_bounded(int, 0, 10_000), default=100)
    p.add_argument("--population", type=_bounded(int, 1, 1000), default=20)
    p.add_argument("--tosses", type=_bounded(int, 1, 200), default=5)
    p.add_argument("--workers", type=_bounded(int, 1, 64), default=2, help="evaluation processes per run")
    p.add_argument(
        "--seed", type=_bounded(int, 0, 2**32 - 1), default=0, help="seed of the first run (run i uses seed + i)"
    )
    p.add_argument(
        "--runs", default=None, help="folder of the run folders (default runs/train-<task>); rerun to resume"
    )
    p.add_argument("--sequential", action="store_true", help="no overlapped suggestions (see optimize --sequential)")
    p.add_argument(
        "--limit-scale", default=None, metavar="S", help=LIMIT_SCALE_HELP + " (default 1; resumed runs must match)"
    )
    p.add_argument("--robustify", type=_bounded(int, 0, 1_000_000), default=0, metavar="N", help=ROBUSTIFY_HELP)
    p.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help="run the runs as tasks on a Ray cluster (ray.init address: auto or host:6379 on a node of the cluster, see docs/cluster.md; 'local' starts a local instance)",
    )
    handlers["train"] = _cmd_train


def _add_dashboard_parser(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]
) -> None:
    """Add the ``dashboard`` command and its handler."""
    p = sub.add_parser("dashboard", help="serve the Panel dashboard of a serve library")
    p.add_argument(
        "library_dir",
        nargs="?",
        default=None,
        metavar="LIBRARY",
        help="serve library folder (default ./serve-library; or --library)",
    )
    p.add_argument("--library", default=None, help="serve library folder (the same as LIBRARY)")
    p.add_argument(
        "--reference",
        default=None,
        metavar="FILE",
        help="match file in the Ace public format: its robot and human serves are drawn beside the library's in the net-crossing plots (read only)",
    )
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default: localhost only)")
    p.add_argument("--port", type=_bounded(int, 1, 65535), default=5006)
    p.add_argument("--studio-url", default="http://127.0.0.1:8080", help="link to the studio shown beside each serve")
    p.add_argument(
        "--runs",
        default="runs",
        help="folder of HEBO run folders for the convergence plots (default ./runs; runs elsewhere are not read)",
    )
    handlers["dashboard"] = _cmd_dashboard


def _add_toss_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]) -> None:
    """Add the ``toss`` command and its handler."""
    from studio.toss.recordings import MAX_TOSSES

    p = sub.add_parser("toss", help="analyse toss recordings: lift time, rise, spread")
    p.add_argument("--side", choices=("right", "left"), default="right")
    p.add_argument("--csv", default=None, help="recordings CSV (toss_id,t,x,y,z); default: the shipped recordings")
    p.add_argument(
        "--generate", action="store_true", help="first write the default synthetic recordings (right.csv, left.csv)"
    )
    p.add_argument("--out", default=None, help="folder for --generate (default: the shipped data)")
    p.add_argument(
        "--n",
        type=_bounded(int, 2, MAX_TOSSES),
        default=None,
        help="tosses per side for --generate (default: the shipped 20)",
    )
    p.add_argument(
        "--seed",
        type=_bounded(int, 0, 2**32 - 1),
        default=None,
        help="random seed for --generate (default: the shipped data's)",
    )
    handlers["toss"] = _cmd_toss


def _add_robot_files_parser(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]
) -> None:
    """Add the ``robot-files`` command and its handler."""
    p = sub.add_parser(
        "robot-files", help="write robots/serve_robot.urdf and .xml from robots/serve_robot.toml (--check: verify)"
    )
    p.add_argument(
        "--check", action="store_true", help="only verify the committed files are up to date (exit 1 when stale)"
    )
    p.add_argument("--toml", type=Path, default=None, help="robot TOML (default: robots/serve_robot.toml)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: robots/)")
    handlers["robot-files"] = _cmd_robot_files


def _add_calibrate_parser(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]
) -> None:
    """Add the ``calibrate`` command and its handler."""
    p = sub.add_parser(
        "calibrate",
        help="refit the racket, flight and table models on real data and print one table: before, after (cross-validated), noise",
    )
    p.add_argument("--folds", type=_bounded(int, 2, 100), default=None, help="cross-validation folds (default 5)")
    p.add_argument(
        "--repeats",
        type=_bounded(int, 1, 100),
        default=1,
        help="random fold splits pooled for the racket CV (default 1)",
    )
    p.add_argument(
        "--serve-contacts",
        type=Path,
        default=None,
        help="robot serve contacts CSV in the Ace format (default: the shipped studio/data/robot_serve_contacts)",
    )
    p.add_argument("--no-serve-contacts", action="store_true", help="fit the racket on the racket-at-rest bounces only")
    p.add_argument(
        "--match",
        type=Path,
        default=None,
        help="match events CSV in the Ace public format (default ../shared/data/ace_match/match_data_dev.csv)",
    )
    p.add_argument("--no-cv", action="store_true", help="skip the flight model's cross-validations (~2 min)")
    p.add_argument(
        "--write",
        action="store_true",
        help="write the fitted parameter records (racket_models.json, flight_model.json)",
    )
    handlers["calibrate"] = _cmd_calibrate


def _add_library_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser], handlers: dict[str, Handler]) -> None:
    """Add the ``library`` command and its handler."""
    p = sub.add_parser(
        "library", help="serve library: list, show, validate, select the next serve, record points, statistics, prune"
    )
    lsub = p.add_subparsers(dest="library_command", required=True)
    q = lsub.add_parser("list", help="table of the serves with spin cluster, reward, legality and usage")
    q.add_argument("dir", help="serve library folder")
    q.set_defaults(library_handler=_library_list)
    q = lsub.add_parser("show", help="one serve's index entry")
    q.add_argument("dir", help="serve library folder")
    q.add_argument("id", help="serve id")
    q.set_defaults(library_handler=_library_show)
    q = lsub.add_parser(
        "validate", help="load the index, every NPZ and the match log; exit 1 naming file and field on failure"
    )
    q.add_argument("dir", help="serve library folder")
    q.set_defaults(library_handler=_library_validate)
    q = lsub.add_parser(
        "select", help="the next serve: least used, from a spin cluster other than the previous serve's"
    )
    q.add_argument("dir", help="serve library folder")
    q.add_argument(
        "--previous",
        default=None,
        metavar="ID",
        help="id of the serve executed last (default: the robot's last serve in the match log)",
    )
    q.set_defaults(library_handler=_library_select)
    q = lsub.add_parser("record", help="append a point to DIR/matches.jsonl and update the usage counters")
    q.add_argument("dir", help="serve library folder")
    q.add_argument("--serve", default=None, metavar="ID", help="the robot's serve (required when the robot serves)")
    q.add_argument("--winner", required=True, choices=("robot", "opponent"))
    q.add_argument("--ace", action="store_true", help="the serve won the point directly")
    q.add_argument("--server", choices=("robot", "opponent"), default="robot")
    q.add_argument("--opponent", default=None, metavar="NAME", help="opponent's name")
    q.set_defaults(library_handler=_library_record)
    q = lsub.add_parser("stats", help="Table-I-like summary (Wilson 95 %% intervals, aces) and per-serve records")
    q.add_argument("dir", help="serve library folder")
    q.add_argument(
        "--min-uses",
        type=_bounded(int, 1, 10**9),
        default=10,
        help="minimum uses before a serve is flagged for pruning",
    )
    q.set_defaults(library_handler=_library_stats)
    q = lsub.add_parser("prune", help="move the statistically worst serves to DIR/pruned/")
    q.add_argument("dir", help="serve library folder")
    q.add_argument(
        "--min-uses",
        type=_bounded(int, 1, 10**9),
        default=10,
        help="minimum uses before a serve can be pruned (default 10)",
    )
    q.add_argument("--dry-run", action="store_true", help="only report what would be pruned")
    q.set_defaults(library_handler=_library_prune)
    handlers["library"] = _cmd_library


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, Handler]]:
    """The ``serve-studio`` argument parser and the handler of each command."""
    parser = argparse.ArgumentParser(prog="serve-studio", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    handlers: dict[str, Handler] = {}
    _add_app_parser(sub, handlers)
    _add_evaluate_parser(sub, handlers)
    _add_robustify_parser(sub, handlers)
    _add_optimize_parser(sub, handlers)
    _add_train_parser(sub, handlers)
    _add_dashboard_parser(sub, handlers)
    _add_toss_parser(sub, handlers)
    _add_robot_files_parser(sub, handlers)
    _add_calibrate_parser(sub, handlers)
    _add_library_parser(sub, handlers)
    return parser, handlers


def single_thread_pools(args: argparse.Namespace) -> bool:
    """For ``optimize``/``train`` that evaluate in this process (``--workers 1``): one
    BLAS/OpenMP thread, set in the environment before numpy loads (unless the user set
    them; measurements: :mod:`studio.optimize.threads`). Returns True when it set something."""
    if args.command not in ("optimize", "train") or getattr(args, "workers", 2) != 1 or getattr(args, "ray", None):
        return False
    from studio.optimize.threads import single_thread_env  # numpy-free

    return single_thread_env(keep_user_settings=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser, handlers = build_parser()
    args = parser.parse_args(argv)
    single_thread_pools(args)  # before any numpy import (the commands import lazily)
    from studio.errors import StudioError

    try:
        return handlers[args.command](args)
    except StudioError as err:
        print(f"serve-studio {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except OSError as err:  # the file system refused (disk full, permissions, a file where a folder goes)
        where = f"{err.filename}: " if err.filename else ""
        print(f"serve-studio {args.command}: error: {where}{err.strerror or err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
