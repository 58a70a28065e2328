"""Cheaper HEBO suggestions: warm-started GP fits, the refit schedule, the lean NSGA-II."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from studio.errors import InvalidInputError
from studio.optimize.hebo_adapter import HeboAdapter, HeboConfig, lean_nsga2
from studio.optimize.hebo_gp import FastGP

CONF = {"lr": 0.01, "noise_lb": 8e-4, "pred_likeli": False, "verbose": False}
# cheap adapter settings: GP from the 5th observation, 3 warm epochs, a cold fit every 3 batches
CHAIN = HeboConfig(rand_sample=5, es_pop=16, es_iters=4, gp_epochs=10, warm_epochs=3, refit_every=3, refit_tolerance=math.inf, max_train=32, keep_best=8)


def _data(n: int, d: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    X = rng.random((n, d))
    y = ((X - 0.3) ** 2 * np.arange(1, d + 1)).sum(1, keepdims=True) + 0.05 * rng.standard_normal((n, 1))
    return torch.tensor(X, dtype=torch.float32), torch.tensor(y, dtype=torch.float32)


def _fit(X: torch.Tensor, y: torch.Tensor, epochs: int, seed: int, start: object = None) -> FastGP:
    torch.manual_seed(seed)
    np.random.seed(seed)
    f = FastGP(X.shape[1], 0, 1, num_epochs=epochs, **CONF)
    f.fit(X, None, y, start=start, epochs=epochs if start is not None else None)  # type: ignore[arg-type]
    return f


def _observed(n: int = 40, d: int = 4, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.random((n, d))
    return X, ((X - 0.6) ** 2).sum(1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_warm_started_fit_reaches_the_cold_fits_marginal_likelihood(seed: int) -> None:
    """20 points arrive after a fit on 140: 10 warm epochs from that fit end at a loss
    (negative log marginal likelihood per point) no worse than a 60-epoch cold fit's on
    the same 160 points, and far below 10 cold epochs (the start is what helps)."""
    X, y = _data(160, seed=seed)
    before = _fit(X[:140], y[:140], 60, 1)
    cold = _fit(X, y, 60, 2).state()
    warm = _fit(X, y, 10, 2, start=before.state()).state()
    short = _fit(X, y, 10, 2).state()
    assert warm.points == cold.points == 160
    assert warm.loss <= cold.loss + 0.02  # measured: 0.04 vs 0.19, 0.00 vs 0.15, -0.06 vs 0.10
    assert short.loss - warm.loss > 0.3  # measured: ~0.7


def test_state_round_trip_and_a_warm_start_of_the_wrong_width_is_refused() -> None:
    X, y = _data(60, d=4)
    f = _fit(X, y, 20, 0)
    st = f.state()
    with torch.no_grad():
        assert st.loss == pytest.approx(float(f.loss()), abs=1e-6)
    again = _fit(X, y, 1, 0, start=st)  # one more epoch from the fitted parameters: no worse
    assert again.state().loss <= st.loss + 0.01
    assert _fit(X, y, 1, 0).state().loss > st.loss + 0.2  # one epoch from HEBO's initial values
    X5, y5 = _data(60, d=5)
    with pytest.raises(ValueError, match="length scales"):
        _fit(X5, y5, 3, 0, start=st)


def test_a_cold_refit_happens_every_k_batches() -> None:
    X, y = _observed()
    a = HeboAdapter(4, seed=1, config=CHAIN)
    a.observe(X, y)
    for m in range(8, 41, 4):  # batches of 4 from 8, 12, ..., 40 observations
        a.suggest(4, upto=m)
    kinds = [(f.observations, f.kind) for f in a.fits]
    # the first GP fit is cold; then cold whenever m crosses a multiple of 3 x 4
    assert kinds == [(8, "first"), (12, "scheduled"), (16, "warm"), (20, "warm"), (24, "scheduled"), (28, "warm"), (32, "warm"), (36, "scheduled"), (40, "warm")]
    assert all(f.batch == 4 for f in a.fits)


def test_the_chain_of_fits_depends_on_the_observations_only() -> None:
    """A fresh adapter (a resumed run) suggesting at 32 observations re-creates the chain
    (24 cold, 28 and 32 warm) and suggests what the adapter that went through every batch did."""
    X, y = _observed()
    a = HeboAdapter(4, seed=1, config=CHAIN)
    a.observe(X, y)
    last = None
    for m in range(8, 33, 4):
        last = a.suggest(4, upto=m)
    b = HeboAdapter(4, seed=1, config=CHAIN)
    b.observe(X, y)
    np.testing.assert_array_equal(b.suggest(4, upto=32), last)
    assert [(f.observations, f.kind) for f in b.fits] == [(24, "scheduled"), (28, "warm"), (32, "warm")]


def test_a_degraded_warm_fit_is_redone_cold() -> None:
    """Outliers arrive: the warm fit's loss per point rises above the fit it started from
    by more than the tolerance and the fit is redone cold; with a huge tolerance it is kept."""
    X, y = _observed(n=28)
    y[24:] += np.array([25.0, -30.0, 40.0, -35.0])  # wild targets in the newest batch
    out = {}
    for tol in (0.05, 1e9):
        a = HeboAdapter(4, seed=2, config=HeboConfig(**{**CHAIN.to_json(), "refit_every": 10, "refit_tolerance": tol}))
        a.observe(X, y)
        a.suggest(4, upto=24)
        out[tol] = a.suggest(4, upto=28)
        assert [f.kind for f in a.fits][-1] == ("degraded" if tol < 1 else "warm")
    assert not np.array_equal(out[0.05], out[1e9])


def test_default_suggestions_stay_in_the_box_and_repeat_for_a_seed() -> None:
    X, y = _observed(n=60, d=5)
    cfg = HeboConfig(es_pop=16, es_iters=5)  # defaults otherwise: warm starts, lean NSGA-II
    runs = []
    for _ in range(2):
        a = HeboAdapter(5, seed=7, config=cfg)
        a.observe(X, y)
        runs.append([a.suggest(6, upto=m, pending=X[m : m + 6]) for m in (36, 42, 48, 54)])
    for Z, Z2 in zip(*runs, strict=True):
        np.testing.assert_array_equal(Z, Z2)
        assert Z.shape == (6, 5) and np.all((Z >= 0.0) & (Z <= 1.0))
        assert len({tuple(r) for r in Z}) == 6 and not {tuple(r) for r in Z} & {tuple(r) for r in X}
    other = HeboAdapter(5, seed=8, config=cfg)
    other.observe(X, y)
    assert not np.array_equal(other.suggest(6, upto=54, pending=X[54:60]), runs[0][-1])


def test_full_refit_is_the_old_path_and_bad_settings_are_refused() -> None:
    cfg = HeboConfig.full_refit()
    assert cfg.refit_every is None and not cfg.lean_nsga and (cfg.es_pop, cfg.es_iters) == (48, 25)
    X, y = _observed()
    a = HeboAdapter(4, seed=1, config=HeboConfig(**{**cfg.to_json(), "es_pop": 16, "es_iters": 3, "gp_epochs": 5}))
    a.observe(X, y)
    for m in (20, 24, 28):
        a.suggest(4, upto=m)
    assert [f.kind for f in a.fits] == ["cold"] * 3
    for bad in ({"refit_every": 0}, {"warm_epochs": 0}, {"refit_tolerance": -0.1}):
        with pytest.raises(InvalidInputError):
            HeboConfig(**bad)  # type: ignore[arg-type]


def _zdt1(X: np.ndarray) -> np.ndarray:
    f1 = X[:, 0]
    g = 1 + 9 * X[:, 1:].mean(1)
    return np.c_[f1, g * (1 - np.sqrt(f1 / g))]


def test_lean_nsga2_searches_as_well_as_pymoos() -> None:
    """ZDT1 in 6-D, population 24, 20 generations, 8 seeds: the lean NSGA-II's final front
    has the hypervolume of pymoo's (measured 5.88 +- 0.05 against 5.88 +- 0.15; the
    initial population's is 3.2), its points are mutually non-dominated and in the box,
    and a seed repeats its result."""
    from pymoo.algorithms.moo.nsga2 import NSGA2
    from pymoo.core.problem import Problem
    from pymoo.indicators.hv import HV
    from pymoo.optimize import minimize

    class Zdt1(Problem):  # type: ignore[misc]
        def __init__(self) -> None:
            super().__init__(n_var=6, n_obj=2, xl=0.0, xu=1.0)

        def _evaluate(self, X: np.ndarray, out: dict, *args: object, **kwargs: object) -> None:
            out["F"] = _zdt1(X)

    hv = HV(ref_point=np.array([1.1, 6.0]))
    lean, ref = [], []
    for seed in range(8):
        init = np.random.default_rng(seed).random((24, 6))
        X = lean_nsga2(_zdt1, init, 24, 20, np.random.default_rng(seed))
        F = _zdt1(X)
        assert np.all((X >= 0) & (X <= 1))
        assert not any(np.all(F[i] <= F[j]) and np.any(F[i] < F[j]) for i in range(len(F)) for j in range(len(F)))
        lean.append(hv(F))
        ref.append(hv(_zdt1(minimize(Zdt1(), NSGA2(pop_size=24, sampling=init, eliminate_duplicates=True), ("n_gen", 20), seed=seed).X)))
    assert np.mean(lean) >= np.mean(ref) - 0.1
    assert np.mean(lean) > hv(_zdt1(np.random.default_rng(0).random((24, 6)))) + 2.0
    again = lean_nsga2(_zdt1, np.random.default_rng(0).random((24, 6)), 24, 20, np.random.default_rng(0))
    np.testing.assert_array_equal(again, lean_nsga2(_zdt1, np.random.default_rng(0).random((24, 6)), 24, 20, np.random.default_rng(0)))
