"""Serve capability envelope (the paper's Fig. 3b): net-crossing speed and spin of legal serves.

Reads the evaluation logs of optimization runs (``<run>/evaluations.jsonl`` and
``run.json`` of ``serve-studio optimize`` / ``train``), re-evaluates every distinct serve
logged as legal on the mean toss with the current physics, and prints the legal serves'
envelope: the largest topspin, backspin and sidespin at the net crossing, the fastest and
the spinniest serve, each with its speed, spin and run. ``--json FILE`` also writes the
points (speed, topspin, sidespin, |w| at the net per legal serve) for plots, and
``--serves DIR`` the extreme serves as serve files (``serve-studio evaluate`` reproduces them).
``--within-efforts`` keeps only serves whose exported motion stays within every joint's
effort limit (``robots/serve_robot.toml``): what the robot can run without raising a limit.

    .venv/bin/python experiments/envelope.py RUN_DIR [RUN_DIR ...] [--max 400] [--json FILE] [--serves DIR] [--within-efforts]

A run folder may also be a folder of run folders (``experiments/table2/backspin``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from studio.serve.efforts import effort_report
from studio.serve.evaluate import EvaluationContext, evaluate_serve

from studio.serve.params import GENE_NAMES, HandServe, LimitScale, ServeParams, save_serve


def run_folders(paths: list[Path]) -> list[Path]:
    """Every folder holding an ``evaluations.jsonl`` and ``run.json`` under ``paths``."""
    found = [p for path in paths for p in [path, *sorted(path.glob("*"))] if (p / "evaluations.jsonl").is_file()]
    return [p for p in found if (p / "run.json").is_file()]


def legal_candidates(run: Path) -> list[tuple[str, ServeParams, LimitScale]]:
    """(side, parameters, limit scale) of the serves a run logged as legal, without repeats."""
    meta = json.loads((run / "run.json").read_text(encoding="utf-8"))
    scale = LimitScale(**meta.get("limit_scale", {})) if isinstance(meta.get("limit_scale"), dict) else LimitScale()
    seen: set[tuple[float, ...]] = set()
    out = []
    for line in (run / "evaluations.jsonl").read_text(encoding="utf-8").splitlines():
        rec = json.loads(line) if line.strip() else {}
        if not rec.get("legal"):
            continue
        x = tuple(round(float(rec["params"][g]), 9) for g in GENE_NAMES)
        if x not in seen:
            seen.add(x)
            out.append((str(meta["side"]), ServeParams.from_vector(x), scale))
    return out


def net_point(
    ctx: EvaluationContext, side: str, params: ServeParams, scale: LimitScale, *, within_efforts: bool = False
) -> dict[str, float] | None:
    """Net-crossing speed [m/s] and spin [rad/s] of a serve legal on the mean toss, else None
    (also None with ``within_efforts`` when a joint's peak effort is beyond its limit)."""
    ev = evaluate_serve(HandServe(name="c", side=side, params=params, limit_scale=scale), ctx)  # type: ignore[arg-type]
    net = ev.metrics.net if ev.legal and ev.metrics is not None else None
    if net is None:
        return None
    if within_efforts:
        report = effort_report(ev.motion, ctx.robot)
        if report is None or not report.within:
            return None
    w = np.asarray(net["w"], dtype=float)
    return {"speed": float(net["speed"]), "topspin": float(net["topspin"]), "sidespin": float(net["sidespin"]),
            "spin": float(np.linalg.norm(w))}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--max", type=int, default=400, help="at most this many serves per run (the last logged)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--serves", type=Path, default=None, help="write the extreme serves as serve files here")
    ap.add_argument("--within-efforts", action="store_true", help="only serves within every joint's effort limit")
    args = ap.parse_args()
    ctx = EvaluationContext.default()
    points: list[dict[str, object]] = []
    for run in run_folders(args.runs):
        for side, params, scale in legal_candidates(run)[-args.max :]:
            pt = net_point(ctx, side, params, scale, within_efforts=args.within_efforts)
            if pt is not None:
                points.append({**pt, "run": str(run), "side": side, "serve": (params, scale)})
    if not points:
        print("no legal serve in these runs")
        return
    print(f"{len(points)} serves legal on the mean toss (current physics), from {len(run_folders(args.runs))} runs")
    rows = [("largest topspin", max(points, key=lambda p: p["topspin"])),  # type: ignore[arg-type,return-value]
            ("largest backspin", min(points, key=lambda p: p["topspin"])),  # type: ignore[arg-type,return-value]
            ("largest sidespin", max(points, key=lambda p: abs(p["sidespin"]))),  # type: ignore[arg-type,return-value]
            ("spinniest", max(points, key=lambda p: p["spin"])),  # type: ignore[arg-type,return-value]
            ("fastest", max(points, key=lambda p: p["speed"]))]  # type: ignore[arg-type,return-value]  # fmt: skip
    print(f"{'':18} {'speed m/s':>9} {'top/back':>9} {'side':>7} {'|w|':>6}  run")
    for label, p in rows:
        print(f"{label:18} {p['speed']:9.2f} {p['topspin']:9.0f} {p['sidespin']:7.0f} {p['spin']:6.0f}  {p['run']}")
        if args.serves is not None:
            params, scale = p["serve"]  # type: ignore[misc]
            name = label.replace(" ", "_")
            note = f"{label} of the legal serves in {p['run']}: {p['speed']:.2f} m/s, top/back {p['topspin']:+.0f}, side {p['sidespin']:+.0f} rad/s at the net"
            args.serves.mkdir(parents=True, exist_ok=True)
            save_serve(args.serves / f"{name}.json", HandServe(name=name, side=p["side"], params=params, notes=note, limit_scale=scale))  # type: ignore[arg-type]
    if args.json is not None:
        for p in points:
            del p["serve"]
        args.json.write_text(json.dumps(points, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
