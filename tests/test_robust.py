"""Robustify: local CMA-ES around a serve, spin kept, never worse than the start, exact resume."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from studio.errors import DataFileError, InvalidInputError
from studio.optimize.robust import (
    ILLEGAL_ON_MEAN,
    LOG_NAME,
    RobustifyOptions,
    RobustScore,
    objective,
    robustify_serve,
    spin_keep,
)
from studio.serve.params import GenomeBounds, HandServe, LimitScale, ServeParams, load_serve

BOUNDS = GenomeBounds(tau=(0.65, 1.0))
EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "serves"
START = HandServe(
    name="start", side="right", task="backspin", limit_scale=LimitScale.uniform(1.2),
    params=ServeParams.denormalize(np.full(10, 0.5), BOUNDS),
)  # fmt: skip
GOOD = np.array([0.56, 0.47, 0.5, 0.53, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5])


class Fake:
    """Legal count grows towards GOOD; the backspin at the net fades along gene 0 (beyond
    0.6 the serve keeps less than 90 % of it); illegal on the mean toss far from the start."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, serve: HandServe) -> RobustScore:
        self.calls += 1
        z = serve.params.normalize(BOUNDS)
        d = float(np.linalg.norm(z - GOOD))
        back = -100.0 + max(0.0, z[0] - 0.5) * 150.0
        if float(np.linalg.norm(z - 0.5)) > 0.3:
            return RobustScore(False, 0, 20, -3.0, back, 5.0)
        return RobustScore(True, int(round(20 * math.exp(-((d / 0.08) ** 2)))), 20, -1.0 + 2 * math.exp(-d), back, 5.0)


def test_spin_keep_and_objective() -> None:
    back = RobustScore(True, 5, 20, 0.2, -80.0, 10.0)
    keep = spin_keep(back, 0.9)
    assert keep.components == (("topspin", -1.0, pytest.approx(72.0)),)  # 10 rad/s of side: not worth keeping
    assert keep.describe() == "backspin >= 72 rad/s at the net"
    assert keep.deficit(back) == 0.0 and keep.deficit(RobustScore(True, 5, 20, 0.2, -60.0, 0.0)) == pytest.approx(12.0)
    assert keep.deficit(RobustScore(True, 5, 20, 0.2, None, None)) == math.inf
    assert objective(back, keep) == pytest.approx(-(5 + 0.02))
    assert objective(RobustScore(True, 9, 20, 0.0, -60.0, 0.0), keep) == pytest.approx(-9 + 4.0)  # 12 rad/s short
    assert objective(RobustScore(False, 0, 20, -3.0, -80.0, 0.0), keep) == ILLEGAL_ON_MEAN
    both = spin_keep(RobustScore(True, 5, 20, 0.2, 210.0, -120.0), 0.5)  # topspin with sidespin: both kept
    assert both.components == (("topspin", 1.0, 105.0), ("sidespin", -1.0, 60.0))
    assert both.describe() == "topspin >= 105 and sidespin (-) >= 60 rad/s at the net"
    assert both.deficit(RobustScore(True, 5, 20, 0.2, 200.0, -40.0)) == pytest.approx(20.0)  # the side lost
    assert spin_keep(RobustScore(True, 5, 20, 0.2, 10.0, 5.0), 0.9).describe() == "no spin to keep"


def test_finds_a_more_robust_serve_that_keeps_the_spin(tmp_path: Path) -> None:
    fake = Fake()
    res = robustify_serve(START, RobustifyOptions(bounds=BOUNDS, evaluations=240), score=fake, run_dir=tmp_path)
    assert fake.calls == 240 + 1 and res.evaluations == 240 and not res.stopped
    assert res.improved and res.best.legal > res.start.legal and res.best.legal >= 15
    assert res.keep.deficit(res.best) == 0.0  # the spin floor holds for the chosen serve
    z = res.serve.params.normalize(BOUNDS)
    assert z[0] <= 0.6 + 1e-9
    # the serve's identity is kept, the notes say what was done
    assert (res.serve.name, res.serve.side, res.serve.task, res.serve.limit_scale) == ("start", "right", "backspin", LimitScale.uniform(1.2))
    assert "legal on" in res.serve.notes and f"(was {res.start.legal}/20)" in res.serve.notes
    lines = (tmp_path / LOG_NAME).read_text().splitlines()
    assert len(lines) == 240 and all(math.isfinite(json.loads(line)["objective"]) for line in lines)


def test_never_worse_than_the_start() -> None:
    class Flat(Fake):
        def __call__(self, serve: HandServe) -> RobustScore:
            self.calls += 1
            top = float(serve.params.normalize(BOUNDS)[0])
            return RobustScore(True, 8 if self.calls == 1 else 3, 20, 0.0, -100.0 if self.calls == 1 else -100.0 + top, 0.0)

    res = robustify_serve(START, RobustifyOptions(bounds=BOUNDS, evaluations=24), score=Flat())
    assert not res.improved and res.serve == START and res.best == res.start


def test_stop_then_resume_equals_the_uninterrupted_search(tmp_path: Path) -> None:
    opts = RobustifyOptions(bounds=BOUNDS, evaluations=96)
    whole = robustify_serve(START, opts, score=Fake(), run_dir=tmp_path / "whole")
    stop = threading.Event()

    def progress(done: int, total: int, best: RobustScore) -> None:
        if done >= 36:
            stop.set()

    part = robustify_serve(START, opts, score=Fake(), run_dir=tmp_path / "part", progress=progress, stop=stop)
    assert part.stopped and part.evaluations == 36
    # a torn last line (killed while writing) is cut off and that candidate scored again
    log = tmp_path / "part" / LOG_NAME
    log.write_bytes(log.read_bytes() + b'{"index": 36, "genome": [0.5')
    fake = Fake()
    resumed = robustify_serve(START, opts, score=fake, run_dir=tmp_path / "part", resume=True)
    assert fake.calls == 1 + (96 - 36)  # the start, then only what was not logged
    assert resumed.serve == whole.serve and resumed.best == whole.best
    assert (tmp_path / "part" / LOG_NAME).read_text() == (tmp_path / "whole" / LOG_NAME).read_text()
    # another search's settings or log are refused by field / line
    with pytest.raises(DataFileError, match="field 'sigma'"):
        robustify_serve(START, replace(opts, sigma=0.05), score=Fake(), run_dir=tmp_path / "part", resume=True)
    lines = log.read_text().splitlines()
    doc = json.loads(lines[3])
    doc["genome"][0] += 0.01
    lines[3] = json.dumps(doc)
    log.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFileError, match="line 4: the logged candidate differs"):
        robustify_serve(START, opts, score=Fake(), run_dir=tmp_path / "part", resume=True)
    with pytest.raises(InvalidInputError, match="already holds a search"):
        robustify_serve(START, opts, score=Fake(), run_dir=tmp_path / "part")


@pytest.mark.parametrize(
    "kw,name",
    [
        ({"keep_spin": 1.5}, "keep_spin"), ({"sigma": 0.0}, "sigma"), ({"sigma": math.nan}, "sigma"), ({"evaluations": 0}, "evaluations"),
        ({"evaluations": True}, "evaluations"), ({"population": 2}, "population"), ({"population": 6.5}, "population"), ({"seed": -1}, "seed"),
        ({"seed": 2**40}, "seed"),
    ],
)
def test_bad_settings_are_rejected_by_name(kw: dict, name: str) -> None:
    # refused when the options are built, before any search starts
    with pytest.raises(InvalidInputError, match=f"robustify: {name} out of range"):
        RobustifyOptions(bounds=BOUNDS, **kw)


def test_resume_without_run_dir_is_rejected() -> None:
    with pytest.raises(InvalidInputError, match="run_dir"):
        robustify_serve(START, RobustifyOptions(bounds=BOUNDS), score=Fake(), resume=True)


def test_real_search_on_an_example_keeps_its_spin_and_legality() -> None:
    from studio.serve.evaluate import EvaluationContext

    serve = load_serve(EXAMPLES / "backspin_right.json")
    res = robustify_serve(serve, RobustifyOptions(evaluations=24, sigma=0.05), context=EvaluationContext.default())
    assert res.start.mean_legal and res.start.tosses == 20
    assert res.best.legal >= res.start.legal and res.best.mean_legal
    assert res.keep.components[0][:2] == ("topspin", -1.0)  # a backspin serve stays one
    assert res.keep.deficit(res.best) == 0.0


def test_unknown_task_fails_before_anything_is_loaded(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match="task"):
        robustify_serve(START, RobustifyOptions(task="no-such-task", bounds=BOUNDS), run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_numpy_global_random_state_is_left_alone() -> None:
    np.random.seed(123)
    expected = np.random.rand(3)
    np.random.seed(123)
    a = robustify_serve(START, RobustifyOptions(bounds=BOUNDS, evaluations=36), score=Fake())
    np.testing.assert_array_equal(np.random.rand(3), expected)
    np.random.seed(999)  # and the search does not depend on it
    b = robustify_serve(START, RobustifyOptions(bounds=BOUNDS, evaluations=36), score=Fake())
    assert a.serve == b.serve and a.best == b.best


def test_spin_turned_round_costs_less_than_illegal_on_the_mean_toss() -> None:
    keep = spin_keep(RobustScore(True, 5, 20, 0.0, -300.0, 0.0), 0.9)
    reversed_spin = RobustScore(True, 0, 20, -2.0, +300.0, 0.0)
    assert objective(reversed_spin, keep) < ILLEGAL_ON_MEAN
    assert objective(RobustScore(True, 0, 20, -2.0, None, None), keep) < ILLEGAL_ON_MEAN


def test_resume_under_other_models_is_refused(tmp_path: Path) -> None:
    robustify_serve(START, RobustifyOptions(bounds=BOUNDS, evaluations=12), score=Fake(), run_dir=tmp_path)

    class Other(Fake):  # e.g. other toss recordings: the start scores differently
        def __call__(self, serve: HandServe) -> RobustScore:
            sc = super().__call__(serve)
            return RobustScore(sc.mean_legal, max(0, sc.legal - 1), sc.tosses, sc.mean_reward, sc.net_topspin, sc.net_sidespin)

    with pytest.raises(DataFileError, match="field 'start'"):
        robustify_serve(START, RobustifyOptions(bounds=BOUNDS, evaluations=24), score=Other(), run_dir=tmp_path, resume=True)


def test_options_refuse_an_unknown_task_and_wrong_bounds_on_construction() -> None:
    with pytest.raises(InvalidInputError, match="unknown task 'nope'"):
        RobustifyOptions(task="nope")
    with pytest.raises(InvalidInputError, match="bounds must be a GenomeBounds, got dict"):
        RobustifyOptions(bounds={"offset": 0.07})  # type: ignore[arg-type]
