"""HEBO serve optimization: seeding, logging, resume, reproducibility, NaN guard, stop, quiet stdout."""

from __future__ import annotations

import dataclasses

import json
import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from studio.errors import InvalidInputError
from studio.optimize.hebo_adapter import HeboAdapter, HeboConfig
from studio.optimize.optimizer import OptimizeOptions, Outcome, bounds_for_toss, optimize_serve
from studio.serve.params import GENE_NAMES, GenomeBounds, HandServe, ServeParams

BOUNDS = GenomeBounds(tau=(0.65, 1.0))
# cheap HEBO settings: GP from the 5th observation on, small NSGA-II
FAST = HeboConfig(rand_sample=5, es_pop=16, es_iters=4, gp_epochs=10, max_train=16, keep_best=6)
TARGET = np.array([0.3, 0.7, 0.4, 0.6, 0.5, 0.2, 0.8, 0.5, 0.5, 0.5])


class FakeEvaluation:
    """Cheap deterministic objective on the normalized genome; NaN in one corner."""

    def __init__(self) -> None:
        self.calls: list[tuple[float, ...]] = []

    def __call__(self, serve: HandServe, tosses: int, rng: np.random.Generator) -> Outcome:
        z = serve.params.normalize(BOUNDS)
        self.calls.append(tuple(np.round(z, 12)))
        if z[1] > 0.9:  # "the simulator blew up"
            return Outcome(math.nan, False, "illegal", "nan")
        base = 1.0 - float(np.sum((z - TARGET) ** 2))
        rewards = tuple(base + 0.05 * rng.standard_normal() for _ in range(max(1, tosses)))
        return Outcome(float(np.mean(rewards)), base > 0.5, "legal" if base > 0.5 else "illegal", None, 1.0, rewards if tosses > 1 else ())


def seed_serves() -> list[HandServe]:
    zs = [np.full(10, 0.5), np.array([0.35, 0.65, 0.4, 0.55, 0.5, 0.25, 0.75, 0.5, 0.5, 0.5])]
    return [HandServe(name=f"hand{i}", side="right", params=ServeParams.denormalize(z, BOUNDS)) for i, z in enumerate(zs)]


def run(tmp: Path, fake: FakeEvaluation | None = None, **kw: object):
    args = dict(side="right", task="topspin_velocity", run_dir=tmp, seeds=seed_serves(), iterations=3, population=4, workers=1, bounds=BOUNDS, config=FAST, seed=3, top_k=3, final_tosses=4, evaluate=fake or FakeEvaluation())
    args.update(kw)
    return call(**args)


RUNTIME = ("run_dir", "context", "seeds", "resume", "progress", "stop", "on_record", "evaluate")
"""optimize_serve's runtime arguments; the rest are OptimizeOptions fields."""


def call(**kw: object):
    """optimize_serve with the options and the runtime arguments in one set of keywords."""
    runtime = {k: kw.pop(k) for k in RUNTIME if k in kw}
    return optimize_serve(OptimizeOptions(**kw), **runtime)  # type: ignore[arg-type]


def read_log(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "evaluations.jsonl").read_text().splitlines()]


def test_bounds_for_toss_spans_falling_ball_to_5cm_above_table() -> None:
    from studio.toss.defaults import load_default_toss_model

    toss = load_default_toss_model("right")
    b = bounds_for_toss(toss)
    i_apex = int(np.argmax(toss.p[:, 2]))
    assert b.tau[0] == pytest.approx(toss.t[i_apex] + 0.02, abs=1e-9)
    assert toss.mean_state(b.tau[0]).v[2] < -0.1  # falling at the earliest contact
    assert toss.mean_state(b.tau[1]).p[2] == pytest.approx(0.05, abs=2e-3)  # 5 cm above the table
    assert 0.6 < b.tau[0] < b.tau[1] < 1.05
    assert b.velocity == GenomeBounds().velocity and b.offset == GenomeBounds().offset


def test_adapter_replaces_nan_restores_threads_and_is_quiet(capsys: pytest.CaptureFixture[str]) -> None:
    import torch

    threads = torch.get_num_threads()
    a = HeboAdapter(3, seed=1, config=FAST, penalty=10.0)
    assert torch.get_num_threads() == threads
    a.observe(np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]), np.array([1.5, np.nan]))
    np.testing.assert_array_equal(a.y, [1.5, 10.0])  # NaN became the penalty, not dropped
    np.testing.assert_array_equal(a.X, [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    rng = np.random.default_rng(0)
    Z = rng.random((6, 3))
    a.observe(Z, np.sum(Z**2, axis=1))
    s = a.suggest(4)
    assert s.shape == (4, 3) and np.all((s >= 0) & (s <= 1))
    assert torch.get_num_threads() == threads
    with pytest.raises(InvalidInputError):
        a.observe(np.array([[np.nan, 0.0, 0.0]]), np.array([1.0]))
    assert capsys.readouterr().out == ""


def test_adapter_same_seed_same_suggestions_and_global_rng_untouched() -> None:
    rng = np.random.default_rng(5)
    Z = rng.random((8, 4))
    y = np.sum((Z - 0.3) ** 2, axis=1)
    out = []
    for seed in (7, 7, 8):
        a = HeboAdapter(4, seed=seed, config=FAST)
        a.observe(Z, y)
        np.random.seed(123)
        s = a.suggest(3)
        assert np.random.rand() == np.random.RandomState(123).rand()  # global numpy state restored
        out.append(s)
    np.testing.assert_array_equal(out[0], out[1])
    assert not np.allclose(out[0], out[2])


def test_capped_training_set_keeps_best_and_recent() -> None:
    a = HeboAdapter(2, seed=0, config=HeboConfig(max_train=10, keep_best=4))
    Z = np.linspace(0, 1, 40).reshape(20, 2)
    y = np.arange(20.0)[::-1]  # the most recent points are the best
    y[3] = -5.0  # one early very good point
    a.observe(Z, y)
    X, yy = a._training_set()
    assert len(yy) == 10
    assert -5.0 in yy.ravel()  # the early best point is kept
    np.testing.assert_array_equal(X.to_numpy()[-1], Z[-1])  # the most recent too


def test_seeds_are_observed_first_and_everything_is_logged(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    fake = FakeEvaluation()
    res = run(tmp_path, fake)
    seeds = seed_serves()
    # HEBO's observations start with the two seeds, normalized, with y = -F
    np.testing.assert_allclose(res.observed_X[:2], [s.params.normalize(BOUNDS) for s in seeds], atol=1e-12)
    log = read_log(tmp_path)
    assert [r["source"] for r in log[:2]] == ["seed:hand0", "seed:hand1"]
    np.testing.assert_allclose(res.observed_y, [-r["reward"] for r in log])
    assert len(log) == res.evaluations == 2 + 3 * 4 and [r["index"] for r in log] == list(range(14))
    assert all(set(r["params"]) == set(GENE_NAMES) and r["seconds"] >= 0 for r in log)
    run_json = json.loads((tmp_path / "run.json").read_text())
    assert run_json["seed"] == 3 and run_json["bounds"]["tau"] == [0.65, 1.0] and run_json["side"] == "right"
    # final pick: best mean over fresh tosses among distinct top candidates (legal ones first)
    assert res.summary is not None and len(res.summary.rewards) == 4
    assert res.summary.mean_reward == pytest.approx(np.mean(res.summary.rewards))
    assert res.summary.mean_reward == max(c.mean_reward for c in res.candidates if c.legal == res.summary.legal)
    assert res.best is not None and res.best.params == res.summary.params
    assert len(fake.calls) == 14 + 3
    assert capsys.readouterr().out == ""


def test_nan_rewards_become_the_penalty(tmp_path: Path) -> None:
    class AlwaysNan(FakeEvaluation):
        def __call__(self, serve: HandServe, tosses: int, rng: np.random.Generator) -> Outcome:
            super().__call__(serve, tosses, rng)
            return Outcome(math.nan, False, "illegal", "nan")

    res = run(tmp_path, AlwaysNan(), iterations=2, seeds=(), top_k=0)
    assert res.observed_y.shape == (8,) and np.all(res.observed_y == 10.0)
    assert all(r["reward"] == -10.0 for r in read_log(tmp_path))


def test_same_seed_same_run_and_resume_at_batch_boundary_is_exact(tmp_path: Path) -> None:
    a = run(tmp_path / "a")
    b = run(tmp_path / "b")
    ga = [r["genome"] for r in read_log(tmp_path / "a")]
    assert ga == [r["genome"] for r in read_log(tmp_path / "b")]
    np.testing.assert_array_equal(a.history, b.history)
    c = run(tmp_path / "c", seed=4)
    assert [r["genome"] for r in read_log(tmp_path / "c")][2:] != ga[2:]

    # kill after the second batch (the progress callback raises), then resume
    calls = []

    def killer(done: int, total: int, best: float, params: ServeParams | None) -> None:
        calls.append(done)
        if done == 2 + 2 * 4:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "k", progress=killer)
    assert len(read_log(tmp_path / "k")) == 10
    fake = FakeEvaluation()
    r = run(tmp_path / "k", fake, resume=True)
    assert len(fake.calls) == 4 + 3  # one missing batch + the final re-evaluation
    assert [x["genome"] for x in read_log(tmp_path / "k")] == ga  # identical to the uninterrupted run
    assert r.evaluations == 14


def test_resume_after_torn_batch_repeats_nothing(tmp_path: Path) -> None:
    run(tmp_path, iterations=2)
    path = tmp_path / "evaluations.jsonl"
    lines = path.read_text().splitlines(keepends=True)
    assert len(lines) == 10
    kept = lines[:7]  # batch 1 lost 3 of its 4 points, and the last write was torn
    path.write_text("".join(kept) + lines[7][:25])
    fake = FakeEvaluation()
    res = run(tmp_path, fake, iterations=3, resume=True)
    log = read_log(tmp_path)
    assert len(log) == res.evaluations == 2 + 3 * 4
    assert [r["index"] for r in log] == list(range(14))
    assert [r["batch"] for r in log] == [-1, -1] + [0] * 4 + [1] * 4 + [2] * 4
    assert len(fake.calls) == 3 + 4 + 3  # the 3 missing of batch 1, batch 2, final pick
    genomes = [tuple(r["genome"]) for r in log]
    assert len(set(genomes)) == len(genomes)  # nothing evaluated twice
    assert [list(g) for g in genomes[:7]] == [json.loads(line)["genome"] for line in kept]
    np.testing.assert_allclose(res.observed_X, np.array(genomes))


def test_resume_refuses_a_different_run(tmp_path: Path) -> None:
    run(tmp_path, iterations=1)
    with pytest.raises(InvalidInputError, match="seed"):
        run(tmp_path, seed=99, resume=True)
    with pytest.raises(InvalidInputError, match="resume"):
        run(tmp_path)


def test_stop_event_stops_between_batches(tmp_path: Path) -> None:
    stop = threading.Event()
    seen: list[int] = []

    def progress(done: int, total: int, best: float, params: ServeParams | None) -> None:
        seen.append(done)
        assert total == 2 + 10 * 4 and math.isfinite(best) and params is not None
        if done >= 2 + 4:
            stop.set()

    res = run(tmp_path, iterations=10, progress=progress, stop=stop)
    assert res.stopped and res.evaluations == 2 + 4 and seen == [2, 6]
    assert res.best is not None  # the final pick still ran


def test_real_evaluation_of_a_seed_in_process(tmp_path: Path) -> None:
    from studio.serve.evaluate import EvaluationContext
    from studio.serve.params import load_serve

    ctx = EvaluationContext.default()
    seed = load_serve(Path(__file__).resolve().parents[1] / "examples" / "serves" / "topspin_right.json")
    res = optimize_serve(OptimizeOptions(side="right", task="topspin_velocity", iterations=0, workers=1, top_k=1, final_tosses=3), run_dir=tmp_path, context=ctx, seeds=[seed])
    log = read_log(tmp_path)
    assert log[0]["status"] == "legal" and log[0]["reward"] > 0
    assert res.summary is not None and len(res.summary.rewards) == 3
    assert res.best is not None and res.best.side == "right"
    with pytest.raises(InvalidInputError, match="left toss"):
        left = HandServe(name="l", side="left", params=seed.params)
        optimize_serve(OptimizeOptions(side="right", task="topspin_velocity", iterations=0, workers=1), run_dir=tmp_path / "x", context=ctx, seeds=[left])


def test_hebo_prints_go_to_the_logger(capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    import logging

    from hebo.models.gp import gp as hebo_gp

    a = HeboAdapter(3, seed=0, config=dataclasses.replace(FAST, fast_gp=False))  # HEBO's own gpytorch GP
    rng = np.random.default_rng(1)
    Z = rng.random((8, 3))
    a.observe(Z, np.sum(Z, axis=1))
    original = hebo_gp.GP.fit

    def noisy_fit(self, *args, **kw):  # what HEBO does on a Cholesky retry
        print("jitter = 1e-06")
        return original(self, *args, **kw)

    monkeypatch.setattr(hebo_gp.GP, "fit", noisy_fit)
    with caplog.at_level(logging.DEBUG, logger="studio.hebo"):
        a.suggest(2)
    assert capsys.readouterr().out == ""
    assert any("jitter = 1e-06" in r.getMessage() for r in caplog.records)


def test_run_history_reads_the_log_and_flags_corrupt_lines(tmp_path: Path) -> None:
    from studio.errors import DataFileError
    from studio.optimize.optimizer import load_run_history

    res = run(tmp_path / "r")
    h = load_run_history(tmp_path / "r")
    assert (h.task, h.side) == ("topspin_velocity", "right")
    assert len(h.reward) == res.evaluations == 2 + 3 * 4
    np.testing.assert_allclose(h.reward, res.history)
    np.testing.assert_allclose(h.best_so_far, np.maximum.accumulate(res.history))
    assert list(h.batch[:2]) == [-1, -1] and h.batch[-1] == 2
    assert np.all(h.best_legal_so_far[h.legal] >= h.reward[h.legal])
    log = tmp_path / "r" / "evaluations.jsonl"
    log.write_bytes(log.read_bytes() + b'{"index": 14, "batch"')  # torn tail of a live run: ignored
    assert len(load_run_history(tmp_path / "r").reward) == 14
    lines = log.read_text().splitlines()
    lines[3] = '{"index": 3, "reward": "high"}'
    log.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFileError, match=r"evaluations.jsonl.*line 4"):
        load_run_history(tmp_path / "r")
    with pytest.raises(DataFileError, match="run.json"):
        load_run_history(tmp_path)


def test_overlap_suggests_from_the_batches_before_the_previous_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[int, int, int]] = []
    pendings: list[set[tuple[float, ...]]] = []
    real = HeboAdapter.suggest

    def spy(self, n, *, upto=None, skip=None, pending=None):  # type: ignore[no-untyped-def]
        calls.append((n, upto, self.n_observed))
        pendings.append(set() if pending is None else {tuple(p) for p in np.asarray(pending)})
        return real(self, n, upto=upto, skip=skip, pending=pending)

    monkeypatch.setattr(HeboAdapter, "suggest", spy)
    res = run(tmp_path / "lag", iterations=4, overlap=True)
    # 2 seeds, batches of 4: batch i >= 1 is suggested from seeds + batches <= i - 2
    assert [upto for _, upto, _ in calls] == [2, 2, 6, 10]
    assert [seen for _, _, seen in calls] == [2, 2, 6, 10]  # batch i+1 is asked for before batch i is observed
    log = read_log(tmp_path / "lag")
    genomes = [tuple(r["genome"]) for r in log]
    assert len(set(genomes)) == len(genomes) == res.evaluations  # the Sobol start does not repeat points
    # ... with batch i (in flight) as its pending points, which it does not suggest again
    assert pendings[0] == set()
    for i in range(1, 4):
        assert pendings[i] == {tuple(r["genome"]) for r in log if r["batch"] == i - 1}
        assert not pendings[i] & {tuple(r["genome"]) for r in log if r["batch"] == i}
    calls.clear()
    run(tmp_path / "sync", iterations=4)  # the default: sequential
    assert [upto for _, upto, _ in calls] == [2, 6, 10, 14]


def test_resume_keeps_the_runs_own_loop_unless_one_is_asked_for(tmp_path: Path) -> None:
    run(tmp_path / "r", iterations=2, overlap=True)
    assert json.loads((tmp_path / "r" / "run.json").read_text())["overlap"] is True
    res = run(tmp_path / "r", iterations=3, resume=True)  # overlap not given: the run's own (overlapped)
    assert json.loads((tmp_path / "r" / "run.json").read_text())["overlap"] is True
    assert res.evaluations == 2 + 3 * 4
    with pytest.raises(InvalidInputError, match="overlap"):
        run(tmp_path / "r", iterations=4, resume=True, overlap=False)  # an explicit different loop is refused
    run(tmp_path / "d", iterations=1)  # default with in-process evaluation: sequential
    assert json.loads((tmp_path / "d" / "run.json").read_text())["overlap"] is False


def test_resume_takes_the_runs_own_hebo_configuration(tmp_path: Path) -> None:
    import dataclasses

    other = dataclasses.replace(FAST, es_iters=FAST.es_iters + 1)
    run(tmp_path / "r", iterations=1, config=other)
    res = run(tmp_path / "r", iterations=2, resume=True, config=None)  # not given: the run's own
    assert json.loads((tmp_path / "r" / "run.json").read_text())["config"]["es_iters"] == other.es_iters
    assert res.evaluations == 2 + 2 * 4
    old = json.loads((tmp_path / "r" / "run.json").read_text())
    del old["config"]["fast_gp"], old["config"]["fantasize"]  # a run logged before those options
    (tmp_path / "r" / "run.json").write_text(json.dumps(old))
    run(tmp_path / "r", iterations=3, resume=True, config=None)
    assert json.loads((tmp_path / "r" / "run.json").read_text())["config"]["fast_gp"] is False  # kept gpytorch


def test_resume_of_a_run_logged_before_warm_starts_keeps_its_cold_fits(tmp_path: Path) -> None:
    run(tmp_path / "r", iterations=1)
    assert json.loads((tmp_path / "r" / "run.json").read_text())["config"]["refit_every"] == FAST.refit_every
    old = json.loads((tmp_path / "r" / "run.json").read_text())
    for key in ("refit_every", "warm_epochs", "refit_tolerance", "lean_nsga"):
        del old["config"][key]  # a run logged before these options
    (tmp_path / "r" / "run.json").write_text(json.dumps(old))
    res = run(tmp_path / "r", iterations=2, resume=True, config=None)
    cfg = json.loads((tmp_path / "r" / "run.json").read_text())["config"]
    assert cfg["refit_every"] is None and cfg["lean_nsga"] is False  # cold fits, pymoo's NSGA-II, as it ran
    assert res.evaluations == 2 + 2 * 4 and res.timings["suggest_cpu"] > 0


def test_the_final_pick_puts_serves_legal_on_the_fresh_tosses_first(tmp_path: Path) -> None:
    """The best training candidate has the best mean over the fresh tosses but is legal on
    too few of them: the chosen serve is the best legal one."""

    class MostlyLegal(FakeEvaluation):
        def __init__(self) -> None:
            super().__init__()
            self.train: list[tuple[np.ndarray, float]] = []

        def __call__(self, serve: HandServe, tosses: int, rng: np.random.Generator) -> Outcome:
            out = super().__call__(serve, tosses, rng)
            z = serve.params.normalize(BOUNDS)
            if tosses < 4:  # training
                self.train.append((z, out.reward))
                return out
            if np.allclose(z, max(self.train, key=lambda zr: zr[1])[0], atol=1e-9):  # legal on 2 of 4, a high mean
                return Outcome(out.reward + 5.0, False, "illegal", "net", 0.5, out.rewards)
            return Outcome(out.reward, True, "legal", None, 1.0, out.rewards)

    res = run(tmp_path, MostlyLegal(), tosses=1, final_tosses=4, min_legal_fraction=0.75)
    assert [c.legal for c in res.candidates] == [True, True, False]
    assert res.candidates[-1].mean_reward > res.candidates[0].mean_reward  # the best mean is not chosen
    assert res.summary is res.candidates[0] and res.summary.legal_fraction == 1.0
    assert res.candidates[0].mean_reward >= res.candidates[1].mean_reward
    G = np.array([c.genome for c in res.candidates])  # at least final_spread (0.05) apart
    assert min(np.linalg.norm(G[i] - G[j]) for i in range(3) for j in range(i)) > 0.05
    with pytest.raises(InvalidInputError, match="final_spread"):
        run(tmp_path / "x", final_spread=-0.1)


def test_overlap_with_fantasies_needs_the_fast_gp_before_anything_runs(tmp_path: Path) -> None:
    import dataclasses

    with pytest.raises(InvalidInputError, match="fast_gp"):
        run(tmp_path / "x", overlap=True, config=dataclasses.replace(FAST, fast_gp=False))
    assert not (tmp_path / "x" / "evaluations.jsonl").exists()


def test_resumed_torn_overlapped_batch_knows_its_logged_part(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    run(tmp_path / "t", iterations=3, overlap=True)
    lines = (tmp_path / "t" / "evaluations.jsonl").read_text().splitlines()
    recs = [json.loads(x) for x in lines]
    keep = [x for x, r in zip(lines, recs) if r["batch"] < 2] + [x for x, r in zip(lines, recs) if r["batch"] == 2][:2]
    (tmp_path / "t" / "evaluations.jsonl").write_text("\n".join(keep) + "\n")  # killed in the middle of batch 2
    seen: list[set] = []
    real = HeboAdapter.suggest

    def spy(self, n, *, upto=None, skip=None, pending=None):  # type: ignore[no-untyped-def]
        seen.append(set() if pending is None else {tuple(p) for p in np.asarray(pending)})
        return real(self, n, upto=upto, skip=skip, pending=pending)

    monkeypatch.setattr(HeboAdapter, "suggest", spy)
    run(tmp_path / "t", iterations=3, resume=True)
    logged_2 = {tuple(json.loads(x)["genome"]) for x in keep[-2:]}
    assert logged_2 <= seen[0]  # the re-suggestion of batch 2's missing part sees its logged part as pending
    genomes = [tuple(r["genome"]) for r in read_log(tmp_path / "t")]
    assert len(genomes) == len(set(genomes)) == 2 + 3 * 4


def test_limit_scale_reaches_every_candidate_is_logged_and_kept_on_resume(tmp_path: Path) -> None:
    from studio.serve.params import LimitScale

    scales: list[LimitScale] = []
    fake = FakeEvaluation()

    def evaluate(serve: HandServe, tosses: int, rng: np.random.Generator) -> Outcome:
        scales.append(serve.limit_scale)
        return fake(serve, tosses, rng)

    scale = LimitScale.uniform(1.4)
    res = run(tmp_path, iterations=1, evaluate=evaluate, limit_scale=scale)
    assert scales and all(s == scale for s in scales)  # seeds, suggestions and the final pick
    assert json.loads((tmp_path / "run.json").read_text())["limit_scale"] == {"velocity": 1.0, "acceleration": 1.4, "jerk": 1.4}
    assert res.best is not None and res.best.limit_scale == scale
    # resumed without a scale: the run's own; with another scale: refused by name
    scales.clear()
    res2 = run(tmp_path, iterations=2, evaluate=evaluate, resume=True)
    assert scales and all(s == scale for s in scales) and res2.best is not None and res2.best.limit_scale == scale
    with pytest.raises(InvalidInputError, match="limit_scale"):
        run(tmp_path, iterations=3, evaluate=evaluate, resume=True, limit_scale=LimitScale())


def test_runs_logged_before_limit_scale_resume_with_the_robots_limits(tmp_path: Path) -> None:
    run(tmp_path, iterations=1)
    meta = json.loads((tmp_path / "run.json").read_text())
    del meta["limit_scale"]
    (tmp_path / "run.json").write_text(json.dumps(meta))
    res = run(tmp_path, iterations=2, resume=True)
    assert res.best is not None and res.best.limit_scale.is_identity


def test_list_runs_filters_summarizes_and_reports_unreadable_folders(tmp_path: Path) -> None:
    from studio.optimize.optimizer import list_runs

    run(tmp_path / "a-run", iterations=1)
    run(tmp_path / "b-run", iterations=2, side="right", task="backspin")
    (tmp_path / "c-broken").mkdir()
    (tmp_path / "c-broken" / "run.json").write_text("{nope")
    (tmp_path / "not-a-run").mkdir()
    runs, problems = list_runs(tmp_path)
    assert [r.run_dir.name for r in runs] == ["b-run", "a-run"]  # newest name first
    assert len(problems) == 1 and "c-broken" in problems[0] and "not readable JSON" in problems[0]
    a = runs[1]
    assert (a.side, a.task, a.seed, a.population, a.iterations, a.tosses) == ("right", "topspin_velocity", 3, 4, 1, 5)  # 5: the default
    assert a.evaluations == a.planned == 2 + 4 and a.seeds == 2
    assert a.best_reward == max(json.loads(line)["reward"] for line in (tmp_path / "a-run" / "evaluations.jsonl").read_text().splitlines())
    assert a.label().startswith("a-run: 6/6 evaluations, best ")
    only, _ = list_runs(tmp_path, side="right", task="backspin")
    assert [r.run_dir.name for r in only] == ["b-run"]
    assert list_runs(tmp_path / "absent") == ([], [])


def test_resume_without_seeds_keeps_the_runs_own(tmp_path: Path) -> None:
    run(tmp_path, iterations=1)
    recorded = json.loads((tmp_path / "run.json").read_text())["seeds"]
    res = run(tmp_path, iterations=2, seeds=[], resume=True)
    assert json.loads((tmp_path / "run.json").read_text())["seeds"] == recorded  # not overwritten with []
    assert res.evaluations == 2 + 2 * 4 and [r["source"] for r in read_log(tmp_path)][:2] == ["seed:hand0", "seed:hand1"]


# --- worker processes: they die with the driver; a dead worker ends the run with a message ---------

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "serves" / "topspin_right.json"


def _cli(run_dir: Path, iterations: int, *extra: str) -> list[str]:
    import sys

    exe = Path(sys.executable).with_name("serve-studio")
    head = [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from studio.cli import main; sys.exit(main())"]
    return head + ["optimize", str(EXAMPLE), "--side", "right", "--task", "topspin_velocity", "--iterations", str(iterations),
                   "--population", "4", "--workers", "2", "--run-dir", str(run_dir), *extra]  # fmt: skip


def _proc_stat(pid: int) -> tuple[int, str] | None:
    """(parent pid, state) of a process from /proc, None when it no longer exists."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    state, ppid = stat.rsplit(")", 1)[1].split()[:2]
    return int(ppid), state


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _descendants(pid: int) -> dict[int, str]:
    """Living descendants of ``pid``: pid -> command line."""
    parent: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        st = _proc_stat(int(entry.name)) if entry.name.isdigit() else None
        if st is not None and st[1] != "Z":
            parent[int(entry.name)] = st[0]
    found: dict[int, str] = {}
    frontier = [pid]
    while frontier:
        kids = [k for k, pp in parent.items() if pp in frontier and k not in found]
        found.update({k: _cmdline(k) for k in kids})
        frontier = kids
    return found


def _workers(pid: int, timeout: float = 120.0, *, log: Path | None = None, lines: int = 0) -> list[int]:
    """Wait until ``pid`` has 2 spawned evaluation workers (and ``log`` ``lines`` lines)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        workers = [p for p, cmd in _descendants(pid).items() if "spawn_main" in cmd]
        enough = log is None or (log.exists() and log.read_text().count("\n") >= lines)
        if len(workers) == 2 and enough:
            return workers
        assert _alive(pid), "the optimize run ended before the check"
        time.sleep(0.05)
    raise AssertionError(f"no 2 workers (and {lines} logged lines) within {timeout} s")


def _alive(pid: int) -> bool:
    st = _proc_stat(pid)
    return st is not None and st[1] != "Z"  # a zombie has ended (its reaper was killed)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
@pytest.mark.parametrize("when", ["spawned", "evaluating"])
def test_kill_9_of_the_driver_takes_its_workers_along(tmp_path: Path, when: str) -> None:
    import signal
    import subprocess

    run_dir = tmp_path / "run"
    driver = subprocess.Popen(_cli(run_dir, 3 if when == "spawned" else 40), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    family: dict[int, str] = {}
    try:
        workers = _workers(driver.pid, log=run_dir / "evaluations.jsonl" if when == "evaluating" else None, lines=1)
        family = _descendants(driver.pid)  # the workers and multiprocessing's resource tracker
        assert set(workers) <= set(family)
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait(10)
        t0 = time.monotonic()
        while any(_alive(p) for p in family) and time.monotonic() - t0 < 10.0:
            time.sleep(0.02)
        gone_after = time.monotonic() - t0
        assert not any(_alive(p) for p in family), f"still alive {gone_after:.1f} s after kill -9 of the driver: {[p for p in family if _alive(p)]}"
        assert gone_after < 3.0
        print(f"[{when}] {len(family)} child processes gone {gone_after:.2f} s after kill -9 of the driver")
    finally:
        if driver.poll() is None:
            driver.kill()
        for p in family:  # orphans of a failed check (never other processes: same command line)
            if _alive(p) and _cmdline(p) == family[p]:
                os.kill(p, signal.SIGKILL)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_a_killed_worker_ends_the_run_with_a_message_and_resume_completes_it(tmp_path: Path) -> None:
    import signal
    import subprocess

    run_dir = tmp_path / "run"
    log = run_dir / "evaluations.jsonl"
    driver = subprocess.Popen(_cli(run_dir, 12), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        victim = _workers(driver.pid, log=log, lines=5)[0]  # the seed and batch 0 are logged
        os.kill(victim, signal.SIGKILL)
        _out, err = driver.communicate(timeout=60)
    finally:
        if driver.poll() is None:
            driver.kill()
    assert driver.returncode == 2, err
    assert "Traceback" not in err and "BrokenProcessPool" not in err
    message = [line for line in err.splitlines() if line.startswith("serve-studio optimize: error:")]
    assert len(message) == 1, err
    assert f"evaluation worker pid {victim} was killed by SIGKILL" in message[0]
    assert f"continue the run with --resume --run-dir {run_dir}" in message[0]
    before = log.read_bytes()
    n_before = before.count(b"\n")
    assert 5 <= n_before < 1 + 12 * 4
    assert f"the {n_before} evaluations finished before are logged" in message[0]

    resumed = subprocess.run(_cli(run_dir, 12, "--resume"), capture_output=True, text=True, timeout=300)
    assert resumed.returncode in (0, 1), resumed.stderr  # 1: the chosen serve is not legal
    after = log.read_bytes()
    assert after.startswith(before)  # nothing logged before the kill lost or rewritten
    records = read_log(run_dir)
    assert [r["index"] for r in records] == list(range(1 + 12 * 4))  # each evaluation once, the budget complete
    genomes = [tuple(r["genome"]) for r in records]
    assert len(set(genomes)) == len(genomes)
