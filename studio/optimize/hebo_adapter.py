"""HEBO over a normalized box [0, 1]^d, with every quirk of ``hebo`` 0.3.6 handled here.

The quirks (found in ``hebo`` 0.3.6 with pymoo 0.6.2) and what this adapter does:

- ``HEBO.suggest`` refits its GP from scratch on *all* observations and runs NSGA-II with
  hard-coded 100 individuals x 100 generations, so a call costs seconds and grows with the
  observations (figures: ``docs/optimization.md#the-hebo-adapter-and-its-gp``). The adapter
  re-implements ``suggest`` with the same algorithm (power transform, GP, MACE
  acquisition, NSGA-II, the same candidate selection) but a capped
  training set, GP fits warm-started from the previous batch's fit with a cold refit
  every few batches, and a configurable acquisition effort run on plain arrays
  (:class:`HeboConfig`, :func:`lean_nsga2`).
- pymoo 0.6.2 draws from its own unseeded generator unless ``minimize(..., seed=...)`` is
  given; ``get_init_pop`` draws a Sobol sequence from torch's global generator and the
  final pick uses ``np.random.choice``. Every suggestion here runs with numpy, torch and
  pymoo seeded from ``(seed, number of observations, batch size)`` inside a forked torch
  generator and a saved numpy state, so the process's global RNGs are left untouched and
  a suggestion depends only on the seed and the observations (which is what makes a
  resumed run reproducible).
- HEBO's own Sobol engine is stateful (each draw advances it); the initial random points
  here come from a scrambled Sobol engine seeded with ``seed`` and fast-forwarded by the
  number of observations (same property as above).
- The GP prints ``jitter = ...`` retries with ``print``: stdout is captured during every
  HEBO call and forwarded line by line to the ``studio.hebo`` logger (warnings too).
- ``observe_new_data`` silently drops non-finite targets: the adapter replaces NaN/inf by
  a fixed penalty before HEBO sees them (and refuses non-finite genomes).
- ``import hebo`` sets torch to one thread for the whole process: the adapter imports it
  lazily, restores the previous thread count right after, and runs each suggestion with
  :attr:`HeboConfig.torch_threads` threads, restoring the count afterwards.
"""

from __future__ import annotations

import contextlib
import functools
import io
import logging
import math
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from studio.errors import InvalidInputError

LOG = logging.getLogger("studio.hebo")


@dataclass(frozen=True, slots=True)
class HeboConfig:
    """Cost knobs of one HEBO suggestion.

    Defaults: the CPU cost of a suggestion stays flat in the number of observations once
    the training cap is reached, several times below cold fits with pymoo's NSGA-II
    (:meth:`full_refit`, the defaults before warm starts) and far below HEBO's own
    settings, whose cost grows with the observations; the warm starts and the lean
    NSGA-II each take a share of the saving. The cap keeps the GP a local model around the
    best points (the ones the acquisition cares about) plus the newest batch information.
    Over five seeds of 2000 evaluations the defaults lost no reward beyond the
    seed-to-seed spread, and the 48 x 25 NSGA-II (1200 acquisition evaluations instead of
    HEBO's 10 000) did as well as HEBO's defaults on the serve task (one task and seed:
    not a tuning study). Figures: ``docs/optimization.md#training-time`` and
    ``docs/optimization.md#optimizers-at-equal-evaluations``.
    """

    max_train: int | None = 256
    """Cap on the points the GP is fitted on (``None``: all of them, HEBO's behaviour). When
    exceeded, the :attr:`keep_best` best points plus the most recent ones are kept."""
    keep_best: int = 128
    """How many of the best observations always stay in the capped training set."""
    es_pop: int = 48
    """NSGA-II population of the acquisition optimizer (HEBO: 100)."""
    es_iters: int = 25
    """NSGA-II generations of the acquisition optimizer (HEBO: 100)."""
    gp_epochs: int = 60
    """Adam epochs of the GP hyper-parameter fit (HEBO: 100)."""
    gp_lr: float = 0.01
    """Adam learning rate of the GP fit (HEBO: 0.01)."""
    noise_lb: float = 8e-4
    """Lower bound of the GP's noise variance on the power-transformed targets (HEBO: 8e-4)."""
    rand_sample: int | None = None
    """Observations before the GP is used (``None``: dimension + 1, HEBO's default); the
    first suggestions are scrambled Sobol points."""
    torch_threads: int = 1
    """Torch threads during a suggestion (HEBO forces 1 at import); restored afterwards.
    Alone, two threads make a suggestion somewhat cheaper, but the optimizer suggests while
    its workers evaluate (``overlap``): there two threads oversubscribe the cores and a run
    takes markedly longer (figures: ``docs/optimization.md#the-hebo-adapter-and-its-gp``)."""
    fast_gp: bool = True
    """Fit and query HEBO's GP through :class:`studio.optimize.hebo_gp.FastGP` (the same model, priors,
    fit and random draws in plain torch, exact posterior variance) instead of gpytorch:
    a fit takes about half the time and an acquisition call a fraction of it (figures:
    ``docs/optimization.md#the-hebo-adapter-and-its-gp``)."""
    fantasize: bool = True
    """With suggestions made while a batch is still being evaluated (``pending`` points of
    :meth:`HeboAdapter.suggest`), enter the pending points into the GP at their posterior
    mean (kriging believer, hyper-parameters unchanged) so the acquisition steers away from
    them; needs :attr:`fast_gp`. ``False``: pending points are only kept out of the result."""
    vector_nsga: bool = True
    """Run NSGA-II on plain float vectors (pymoo's SBX/PM operators, numpy duplicate
    elimination) instead of HEBO's mixed-variable setup (the same real-valued operators
    behind per-individual dicts and an O(n^2) Python duplicate check): the same search,
    several times cheaper for an all-continuous genome (``docs/optimization.md#the-hebo-adapter-and-its-gp``)."""
    lean_nsga: bool = True
    """With :attr:`vector_nsga`: run NSGA-II on plain arrays (:func:`lean_nsga2`: pymoo's SBX,
    polynomial mutation, non-dominated sorting and crowding-distance functions, the same
    tournament, duplicate elimination and survival) instead of through pymoo's algorithm
    objects, whose per-individual bookkeeping dominated a generation's cost
    (``docs/optimization.md#training-time``).
    ``False``: pymoo's ``NSGA2`` (its own random stream: other suggestions)."""
    refit_every: int | None = 10
    """Batches between cold GP fits (:attr:`gp_epochs` epochs from HEBO's initial values).
    ``None``: every suggestion fits cold, in its own random stream (HEBO's way; the
    behaviour before warm starts). A number k: the fit for a batch of ``n`` from ``m``
    observations starts from the fit for ``n`` from ``m - n`` (the previous batch's) and
    runs :attr:`warm_epochs` epochs; it is cold when ``m`` crosses a multiple of
    ``k * n`` observations, when no GP was fitted on ``m - n`` observations, or when the
    warm fit degrades (:attr:`refit_tolerance`). Each fit of the chain is seeded from
    (seed, m, n), so the chain depends on the observations alone and a resumed run
    re-creates it. Needs :attr:`fast_gp` (HEBO's gpytorch GP is always fitted cold)."""
    warm_epochs: int = 10
    """pSGLD epochs of a warm-started GP fit (the learning rate is :attr:`gp_lr`). On the
    warm fits of a recorded serve run 10 warm epochs typically ended at a loss slightly
    *below* a 60-epoch cold fit's on the same data (HEBO's 60 epochs do not converge), at
    a fraction of its cost; the worst ones (new data far from the old model) are caught by
    :attr:`refit_tolerance` (figures: ``docs/optimization.md#training-time``)."""
    refit_tolerance: float = 0.3
    """A warm fit whose loss (negative log marginal likelihood with the priors, per
    training point) ends more than this above the loss of the fit it started from (on
    that fit's data) is redone cold [nats per point]. Replayed on that run's chain it
    flagged only warm fits well above a cold fit, and the few such fits it let through came
    right after a flagged one (which, redone cold, restarts the chain); a 2000-evaluation
    run redoes only a few of its fits (figures: ``docs/optimization.md#training-time``)."""

    def __post_init__(self) -> None:
        if self.max_train is not None and self.max_train < 8:
            raise InvalidInputError(f"HeboConfig.max_train must be >= 8 or None, got {self.max_train}")
        if self.max_train is not None and not (0 <= self.keep_best <= self.max_train):
            raise InvalidInputError(f"HeboConfig.keep_best must be in [0, max_train], got {self.keep_best}")
        for name in ("es_pop", "es_iters", "gp_epochs", "torch_threads", "warm_epochs"):
            if int(getattr(self, name)) < 1:
                raise InvalidInputError(f"HeboConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.refit_every is not None and int(self.refit_every) < 1:
            raise InvalidInputError(f"HeboConfig.refit_every must be >= 1 or None, got {self.refit_every}")
        if not (self.gp_lr > 0 and self.noise_lb > 0 and self.refit_tolerance >= 0):
            raise InvalidInputError("HeboConfig.gp_lr and noise_lb must be positive, refit_tolerance >= 0")

    @classmethod
    def hebo_defaults(cls) -> HeboConfig:
        """HEBO 0.3.6's own settings (no cap, NSGA-II 100 x 100 on mixed variables, 100 GP epochs, one torch thread)."""
        return cls(
            max_train=None,
            es_pop=100,
            es_iters=100,
            gp_epochs=100,
            vector_nsga=False,
            fast_gp=False,
            fantasize=False,
            torch_threads=1,
            refit_every=None,
            lean_nsga=False,
        )

    @classmethod
    def full_refit(cls) -> HeboConfig:
        """The defaults before warm starts: a cold GP fit for every suggestion and NSGA-II
        48 x 25 (what runs logged before these options used)."""
        return cls(refit_every=None, es_pop=48, es_iters=25, lean_nsga=False)

    def to_json(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.__slots__}  # type: ignore[attr-defined]


def _import_hebo() -> dict[str, Any]:
    """Import hebo's pieces without letting it change torch's thread count."""
    import torch

    threads = torch.get_num_threads()
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from hebo.acq_optimizers.evolution_optimizer import BOProblem, get_init_pop
            from hebo.acquisitions.acq import MACE, Mean, Sigma
            from hebo.design_space.design_space import DesignSpace
            from hebo.models.model_factory import get_model
            from hebo.optimizers.hebo import HEBO
            from pymoo.algorithms.moo.nsga2 import NSGA2
            from pymoo.core.mixed import MixedVariableDuplicateElimination, MixedVariableMating
            from pymoo.optimize import minimize
    finally:
        torch.set_num_threads(threads)
    return dict(
        BOProblem=BOProblem, get_init_pop=get_init_pop, MACE=MACE, Mean=Mean, Sigma=Sigma,
        DesignSpace=DesignSpace, get_model=get_model, HEBO=HEBO, NSGA2=NSGA2,
        MixedVariableDuplicateElimination=MixedVariableDuplicateElimination,
        MixedVariableMating=MixedVariableMating, minimize=minimize,
    )  # fmt: skip


def _acq_values(acq: Any, X: npt.NDArray[np.float64]) -> npt.NDArray[np.float32]:
    """HEBO acquisition values at the points X (n, d) of [0, 1]^d (no gradients): the
    objectives, then the constraints (n, num_obj + num_constr)."""
    import torch

    with torch.no_grad():
        v = acq(torch.from_numpy(np.asarray(X, dtype=np.float32)), torch.zeros((len(X), 0), dtype=torch.long))
    return v.numpy()


def _acq_objectives(acq: Any, X: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """HEBO acquisition objectives (n, k) at the points X (n, d) of [0, 1]^d (no gradients)."""
    return _acq_values(acq, X)[:, : acq.num_obj].astype(float)


@functools.cache
def _vector_acq_problem_class() -> type:
    from pymoo.core.problem import Problem

    class VectorAcqProblem(Problem):  # type: ignore[misc]
        """HEBO's acquisition (e.g. MACE, several objectives) over [0, 1]^dim as a
        vectorized pymoo problem (rows of X are points)."""

        def __init__(self, acq: Any, dim: int) -> None:
            self.acq = acq
            super().__init__(n_var=dim, n_obj=acq.num_obj, n_ieq_constr=acq.num_constr, xl=0.0, xu=1.0)

        def _evaluate(self, X: npt.NDArray[np.float64], out: dict[str, Any], *args: Any, **kwargs: Any) -> None:
            v = _acq_values(self.acq, X)
            out["F"] = v[:, : self.acq.num_obj]
            if self.acq.num_constr:
                out["G"] = v[:, self.acq.num_obj :]

    return VectorAcqProblem


SBX_ETA, SBX_PROB, SBX_PROB_VAR = 15.0, 0.9, 0.5
"""pymoo 0.6's NSGA-II crossover: SBX with distribution index 15, applied to a mating with
probability 0.9 and to each variable with probability 0.5 (children swapped with 0.5)."""
PM_ETA = 20.0
"""pymoo 0.6's NSGA-II mutation: polynomial mutation with distribution index 20, each
variable with probability min(0.5, 1 / dim)."""
DUPLICATE_DISTANCE = 1e-16
"""Offspring within this Euclidean distance of a population member or of an earlier
offspring are dropped (pymoo's default duplicate elimination)."""


def _dominates(Fa: npt.NDArray[np.float64], Fb: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
    """Row-wise Pareto dominance (minimizing): Fa[i] dominates Fb[i]."""
    return np.all(Fa <= Fb, axis=1) & np.any(Fa < Fb, axis=1)


def _rank_and_crowding(
    F: npt.NDArray[np.float64], keep: int, rng: np.random.Generator
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """NSGA-II survival (pymoo's ``RankAndCrowding``): whole fronts while they fit, then the
    most crowding-distant points of the next front (ties in random order). Returns the
    survivors' indices into F, their front ranks and crowding distances."""
    from pymoo.operators.survival.rank_and_crowding.metrics import (
        calc_crowding_distance,
    )
    from pymoo.util.nds.non_dominated_sorting import NonDominatedSorting

    idx: list[npt.NDArray[np.int64]] = []
    ranks: list[npt.NDArray[np.float64]] = []
    crowd: list[npt.NDArray[np.float64]] = []
    taken = 0
    for r, front in enumerate(NonDominatedSorting().do(F, n_stop_if_ranked=keep)):
        cd = np.full(len(front), np.inf) if len(front) <= 2 else calc_crowding_distance(F[front])
        order = np.arange(len(front))
        if taken + len(front) > keep:
            perm = rng.permutation(len(front))
            order = perm[np.argsort(-cd[perm], kind="stable")][: keep - taken]
        idx.append(front[order])
        ranks.append(np.full(len(order), float(r)))
        crowd.append(cd[order])
        taken += len(order)
        if taken >= keep:
            break
    return np.concatenate(idx), np.concatenate(ranks), np.concatenate(crowd)


def _tournament(
    F: npt.NDArray[np.float64], crowd: npt.NDArray[np.float64], n: int, rng: np.random.Generator
) -> npt.NDArray[np.int64]:
    """``n`` winners of binary tournaments (pymoo's NSGA-II: the dominating one, else the
    larger crowding distance, else at random); contestants from concatenated permutations."""
    size = len(F)
    P = np.concatenate([rng.permutation(size) for _ in range(-(-2 * n // size))])[: 2 * n].reshape(n, 2)
    a, b = P[:, 0], P[:, 1]
    coin = rng.random(n) < 0.5
    by_crowd = np.where(crowd[a] > crowd[b], a, np.where(crowd[b] > crowd[a], b, np.where(coin, a, b)))
    return np.where(_dominates(F[a], F[b]), a, np.where(_dominates(F[b], F[a]), b, by_crowd))


def _offspring(
    X: npt.NDArray[np.float64],
    F: npt.NDArray[np.float64],
    crowd: npt.NDArray[np.float64],
    n: int,
    rng: np.random.Generator,
) -> npt.NDArray[np.float64]:
    """``n`` new points from the population X (pymoo 0.6's NSGA-II mating: tournament,
    SBX, polynomial mutation; duplicates of the population or of each other dropped and
    mated again, at most 100 rounds)."""
    from pymoo.operators.crossover.sbx import cross_sbx
    from pymoo.operators.mutation.pm import mut_pm

    dim = X.shape[1]
    xl, xu = np.zeros(dim), np.ones(dim)
    off = np.empty((0, dim))
    for _ in range(100):
        m = -(-(n - len(off)) // 2)  # matings, two children each
        parents = _tournament(F, crowd, 2 * m, rng).reshape(m, 2)
        Xp = np.stack([X[parents[:, 0]], X[parents[:, 1]]])  # (2, m, dim)
        cross = rng.random(m) < SBX_PROB
        if cross.any():
            eta, prob_var, prob_bin = (np.full((m, 1), v) for v in (SBX_ETA, SBX_PROB_VAR, 0.5))
            Q = cross_sbx(Xp, xl, xu, eta, prob_var, prob_bin, random_state=rng)
            Xp[:, cross] = Q[:, cross]
        kids = Xp.reshape(-1, dim)
        kids = mut_pm(
            kids,
            xl,
            xu,
            np.full(len(kids), PM_ETA),
            np.full(len(kids), min(0.5, 1.0 / dim)),
            at_least_once=False,
            random_state=rng,
        )
        kids = _drop_duplicates(kids, np.vstack([X, off]))
        off = np.vstack([off, kids[: n - len(off)]])
        if len(off) >= n:
            break
    return off


def _drop_duplicates(new: npt.NDArray[np.float64], old: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Rows of ``new`` farther than :data:`DUPLICATE_DISTANCE` from every row of ``old`` and
    from every earlier row of ``new``."""
    from scipy.spatial.distance import cdist

    keep = np.all(cdist(new, old) > DUPLICATE_DISTANCE, axis=1) if len(old) else np.ones(len(new), dtype=bool)
    within = cdist(new, new) <= DUPLICATE_DISTANCE
    keep &= ~np.any(np.triu(within, k=1), axis=0)  # a later copy of an earlier row
    return new[keep]


def lean_nsga2(
    evaluate: Any, init: npt.NDArray[np.float64], pop_size: int, generations: int, rng: np.random.Generator
) -> npt.NDArray[np.float64]:
    """NSGA-II on the box [0, 1]^d minimizing ``evaluate(X (n, d)) -> F (n, k)``, with
    pymoo 0.6's operators and survival on plain arrays (no per-individual objects).

    ``init`` (duplicates dropped) is the first population, counted as generation 1 as
    pymoo counts it; ``generations - 1`` rounds of ``pop_size`` offspring follow. Returns
    the non-dominated points of the final population (pymoo's ``res.X``), (k, d).
    """
    X = _drop_duplicates(np.asarray(init, dtype=float), np.empty((0, init.shape[1])))
    F = np.asarray(evaluate(X), dtype=float)
    keep, rank, crowd = _rank_and_crowding(F, pop_size, rng)
    X, F = X[keep], F[keep]
    for _ in range(generations - 1):
        off = _offspring(X, F, crowd, pop_size, rng)
        if not len(off):
            break
        X, F = np.vstack([X, off]), np.vstack([F, np.asarray(evaluate(off), dtype=float)])
        keep, rank, crowd = _rank_and_crowding(F, pop_size, rng)
        X, F = X[keep], F[keep]
    return X[rank == 0]


@dataclass(frozen=True, slots=True)
class GPFit:
    """One GP fit of :class:`HeboAdapter` (for tests and benchmarks)."""

    observations: int
    """Observations the fit used (``m``; the capped training set is drawn from them)."""
    batch: int
    """Size of the batch it was made for (``n``)."""
    kind: str
    """``cold`` (:attr:`HeboConfig.refit_every` ``None``), ``first`` (the chain's first fit),
    ``scheduled`` (cold, every ``refit_every`` batches), ``warm`` or ``degraded`` (a warm
    fit redone cold)."""


class HeboAdapter:
    """Minimizes y over the box [0, 1]^dim with HEBO (MACE acquisition, batch suggestions).

    ``observe`` takes targets to *minimize*; non-finite targets become ``penalty``.
    Observations are kept in full (:attr:`X`, :attr:`y`); only the GP fit is capped.
    """

    def __init__(self, dim: int, *, seed: int = 0, config: HeboConfig = HeboConfig(), penalty: float = 10.0) -> None:
        if dim < 1:
            raise InvalidInputError(f"HeboAdapter dim must be >= 1, got {dim}")
        if not np.isfinite(penalty):
            raise InvalidInputError(f"HeboAdapter penalty must be finite, got {penalty}")
        self.dim = int(dim)
        self.seed = int(seed)
        self.config = config
        self.penalty = float(penalty)
        self._h = _import_hebo()
        self.fits: list[GPFit] = []
        """Every GP fit made, in order (see :class:`GPFit`)."""
        self._fit_states: dict[tuple[int, int], Any] = {}
        self.names = [f"g{i}" for i in range(self.dim)]
        self.space = self._h["DesignSpace"]().parse(
            [{"name": n, "type": "num", "lb": 0.0, "ub": 1.0} for n in self.names]
        )
        with self._quiet():
            self.hebo = self._h["HEBO"](
                self.space, model_name="gp", rand_sample=config.rand_sample, scramble_seed=self.seed
            )
        self.hebo._model_config = {
            "lr": config.gp_lr,
            "num_epochs": config.gp_epochs,
            "verbose": False,
            "noise_lb": config.noise_lb,
            "pred_likeli": False,
        }

    # -- observations ------------------------------------------------------------------

    @property
    def X(self) -> npt.NDArray[np.float64]:
        """Observed points (n, dim) in [0, 1], in observation order (what HEBO holds)."""
        return self.hebo.X[self.names].to_numpy(dtype=float).reshape(-1, self.dim)

    @property
    def y(self) -> npt.NDArray[np.float64]:
        """Observed targets (n,) (penalty where the objective was not finite)."""
        return np.asarray(self.hebo.y, dtype=float).reshape(-1)

    @property
    def n_observed(self) -> int:
        return int(self.hebo.y.shape[0])

    def observe(self, Z: npt.ArrayLike, y: npt.ArrayLike) -> None:
        """Add points Z (n, dim) with targets y (n,) to minimize; NaN/inf -> :attr:`penalty`."""
        import pandas as pd

        Z = np.atleast_2d(np.asarray(Z, dtype=float))
        y = np.asarray(y, dtype=float).reshape(-1)
        if Z.shape != (len(y), self.dim):
            raise InvalidInputError(f"observe: Z must be (n, {self.dim}) with n = len(y) = {len(y)}, got {Z.shape}")
        if not np.all(np.isfinite(Z)):
            raise InvalidInputError("observe: genomes must be finite")
        y = np.where(np.isfinite(y), y, self.penalty)
        self.hebo.observe_new_data(pd.DataFrame(Z, columns=self.names), y.reshape(-1, 1))

    # -- suggestions -------------------------------------------------------------------

    @contextlib.contextmanager
    def _quiet(self) -> Iterator[None]:
        """Capture HEBO's prints and warnings into the ``studio.hebo`` logger."""
        buf = io.StringIO()
        with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(buf):
            warnings.simplefilter("always")
            yield
        for line in buf.getvalue().splitlines():
            if line.strip():
                LOG.debug("hebo: %s", line.strip())
        for w in caught:
            LOG.debug("hebo warning: %s", w.message)

    @contextlib.contextmanager
    def _seeded(self, n: int, n_used: int, skip: int) -> Iterator[int]:
        """Seed numpy/torch for one suggestion from (seed, observations used, batch size,
        points suggested before); restore global RNG states and threads afterwards."""
        import torch

        key = np.random.SeedSequence([self.seed, n_used, n, skip]).generate_state(1)[0]
        np_state = np.random.get_state()
        threads = torch.get_num_threads()
        try:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(int(key))
                np.random.seed(int(key))
                torch.set_num_threads(self.config.torch_threads)
                yield int(key)
        finally:
            np.random.set_state(np_state)
            torch.set_num_threads(threads)

    def _sobol(self, n: int, skip: int, seed: int | None = None) -> npt.NDArray[np.float64]:
        """``n`` scrambled Sobol points after the first ``skip`` (scrambled with ``seed``,
        default the adapter's seed)."""
        from torch.quasirandom import SobolEngine

        eng = SobolEngine(self.dim, scramble=True, seed=self.seed if seed is None else seed)
        if skip:
            eng.fast_forward(skip)
        return eng.draw(n).double().numpy()

    def _training_set(self, upto: int | None = None) -> tuple[Any, npt.NDArray[np.float64]]:
        """The capped (X DataFrame, y (m, 1)) the GP is fitted on (first ``upto`` observations)."""
        m = self.n_observed if upto is None else upto
        X, y = self.hebo.X.iloc[:m], self.hebo.y[:m]
        cap = self.config.max_train
        if cap is None or len(y) <= cap:
            return X, y
        n = len(y)
        best = np.argsort(y.reshape(-1), kind="stable")[: self.config.keep_best]
        keep = set(best.tolist())
        for i in range(n - 1, -1, -1):
            if len(keep) >= cap:
                break
            keep.add(i)
        idx = np.array(sorted(keep))
        return X.iloc[idx].reset_index(drop=True), y[idx]

    def suggest(
        self, n: int, *, upto: int | None = None, skip: int | None = None, pending: npt.ArrayLike | None = None
    ) -> npt.NDArray[np.float64]:
        """``n`` new points (n, dim) in [0, 1] from the first ``upto`` observations (default:
        all), deterministic given the seed and those observations.

        ``upto`` lets a caller suggest the next batch while the current one is still being
        evaluated, from the observations it had before (and reproduce that on resume);
        ``skip`` (default ``upto``) is how many points were suggested before this call, so
        that the initial Sobol points of overlapping calls do not repeat. ``pending`` (p, dim):
        points suggested earlier whose targets are not among those observations yet (a batch
        in flight): never suggested again and, with :attr:`HeboConfig.fantasize`, entered
        into the GP at its posterior mean. They are used in a canonical (sorted) order, so
        the result does not depend on the order they are given in.
        """
        if n < 1:
            raise InvalidInputError(f"suggest: n must be >= 1, got {n}")
        m = self.n_observed if upto is None else int(upto)
        if not 0 <= m <= self.n_observed:
            raise InvalidInputError(f"suggest: upto must be in [0, {self.n_observed}], got {upto}")
        k = m if skip is None else int(skip)
        P = np.zeros((0, self.dim)) if pending is None else np.asarray(pending, dtype=float).reshape(-1, self.dim)
        if not np.all(np.isfinite(P)):
            raise InvalidInputError("suggest: pending points must be finite")
        if len(P):
            P = np.unique(P, axis=0)  # canonical order (lexicographic rows), duplicates dropped
        with self._seeded(n, m, k) as key, self._quiet():
            if m < self.hebo.rand_sample:
                return self._sobol(n, k)
            return self._suggest_model(n, key, m, P)

    def _suggest_model(self, n: int, key: int, m: int, pending: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """HEBO's suggestion step from the GP: fit, pending points, MACE, NSGA-II, selection."""
        import pandas as pd

        cfg = self.config
        Xdf, yy = self._training_set(m)
        model = self._model(Xdf, yy, m, n)
        if len(pending) and cfg.fantasize:
            if not cfg.fast_gp:
                raise InvalidInputError(
                    "HeboConfig.fantasize needs fast_gp (HEBO's gpytorch GP cannot add pending points)"
                )
            model.condition_on(self.space.transform(pd.DataFrame(pending, columns=self.names))[0])
        best_x = Xdf.iloc[[int(np.argmin(yy.reshape(-1)))]]
        py_best, _ = model.predict(*self.space.transform(best_x))
        it = max(1, m // n)
        kappa = np.sqrt(0.5 * 2 * ((2.0 + self.dim / 2.0) * np.log(it) + np.log(3 * np.pi**2 / (3 * 0.01))))
        acq = self._h["MACE"](model, best_y=py_best.detach().numpy().squeeze(), kappa=kappa)
        rec = self._search(acq, best_x, key)
        rec = self._unseen(rec, n, key, m, pending)
        return self._select(rec, n, key, model)

    # -- the GP fit ----------------------------------------------------------------------

    def _fit(self, Xdf: Any, yy: npt.NDArray[np.float64], *, start: Any = None, epochs: int | None = None) -> Any:
        """HEBO's GP fitted on (Xdf, yy (m, 1)) after HEBO's target warping (a power
        transform; on failure HEBO's fallback, the raw targets). ``start``/``epochs``: a
        warm start of :class:`~studio.optimize.hebo_gp.FastGP` (:meth:`FastGP.fit`)."""
        import torch
        from sklearn.preprocessing import power_transform

        cfg, space = self.config, self.space
        X, Xe = space.transform(Xdf)

        def fit(y_t: Any) -> Any:
            if cfg.fast_gp:
                from studio.optimize.hebo_gp import FastGP

                model = FastGP(space.num_numeric, space.num_categorical, 1, **self.hebo.model_config)
                model.fit(X, Xe, y_t, start=start, epochs=epochs)
                if model.failed_steps or any(model.jitters_used):
                    LOG.debug(
                        "hebo: GP fit needed jitter up to %g (%d epochs skipped)",
                        max(model.jitters_used, default=0.0),
                        model.failed_steps,
                    )
            else:
                model = self._h["get_model"](
                    "gp", space.num_numeric, space.num_categorical, 1, **self.hebo.model_config
                )
                model.fit(X, Xe, y_t)
            return model

        try:  # HEBO's target warping, then its fallback on the raw targets
            std = yy.std() if yy.std() > 0 else 1.0
            method = "yeo-johnson" if yy.min() <= 0 else "box-cox"
            y_t: torch.Tensor = torch.FloatTensor(power_transform(yy / std, method=method))
            if method == "box-cox" and y_t.std() < 0.5:
                y_t = torch.FloatTensor(power_transform(yy / std, method="yeo-johnson"))
            if y_t.std() < 0.5:
                raise RuntimeError("power transformation failed")
            return fit(y_t)
        except Exception:  # noqa: BLE001 - HEBO's own fallback (bare except in hebo)
            return fit(torch.FloatTensor(yy).clone())

    def _model(self, Xdf: Any, yy: npt.NDArray[np.float64], m: int, n: int) -> Any:
        """The GP for a batch of ``n`` from the first ``m`` observations (training set Xdf, yy):
        cold in the suggestion's random stream (:attr:`HeboConfig.refit_every` ``None`` or
        HEBO's gpytorch GP), else from the chain of fits (:meth:`_chain_fit`)."""
        if self.config.refit_every is None or not self.config.fast_gp:
            self.fits.append(GPFit(m, n, "cold"))
            return self._fit(Xdf, yy)
        return self._chain_fit(m, n, (Xdf, yy))[0]

    @contextlib.contextmanager
    def _fit_rng(self, m: int, n: int) -> Iterator[None]:
        """numpy and torch seeded from (seed, m, n) alone for one fit of the chain (a stream
        of its own: spawn key 1), global states restored afterwards."""
        import torch

        key = int(np.random.SeedSequence([self.seed, m, n], spawn_key=(1,)).generate_state(1)[0])
        np_state = np.random.get_state()
        try:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(key)
                np.random.seed(key)
                yield
        finally:
            np.random.set_state(np_state)

    def _chain_fit(self, m: int, n: int, data: tuple[Any, npt.NDArray[np.float64]] | None = None) -> tuple[Any, Any]:
        """(model, :class:`~studio.optimize.hebo_gp.FitState`) of the fit at ``m`` observations in
        the chain of batches of ``n`` (:attr:`HeboConfig.refit_every`); the fit at ``m - n`` it
        starts from is taken from the cache or made first (so it depends on the seed and
        the observations only). ``data``: the training set at ``m`` when known."""
        cfg = self.config
        k = int(cfg.refit_every)  # type: ignore[arg-type]
        prev = m - n
        if prev < self.hebo.rand_sample:
            kind = "first"
        elif m // (k * n) != prev // (k * n):
            kind = "scheduled"
        else:
            kind = "warm"
        start = self._fit_states.get((prev, n)) if kind == "warm" else None
        if kind == "warm" and start is None:
            start = self._chain_fit(prev, n)[1]
        Xdf, yy = data if data is not None else self._training_set(m)
        with self._fit_rng(m, n):
            model = self._fit(Xdf, yy, start=start, epochs=cfg.warm_epochs if start is not None else None)
            state = model.state()
            if start is not None and not (math.isfinite(state.loss) and state.loss <= start.loss + cfg.refit_tolerance):
                LOG.debug(
                    "hebo: warm GP fit at %d observations degraded (loss %.3f, was %.3f): cold refit",
                    m,
                    state.loss,
                    start.loss,
                )
                kind = "degraded"
                model = self._fit(Xdf, yy)
                state = model.state()
        self.fits.append(GPFit(m, n, kind))
        self._fit_states[(m, n)] = state
        for old in sorted(self._fit_states)[: max(0, len(self._fit_states) - 4)]:
            del self._fit_states[old]
        return model, state

    # -- the acquisition search ----------------------------------------------------------

    def _search(self, acq: Any, best_x: Any, key: int) -> npt.NDArray[np.float64]:
        """NSGA-II on the MACE objectives (:attr:`HeboConfig.es_pop` x :attr:`HeboConfig.es_iters`),
        started from the best observation and random points: the final front (k, dim)."""
        import pandas as pd

        h, space, cfg = self._h, self.space, self.config
        if cfg.vector_nsga:
            init = (
                pd.concat([best_x, space.sample(cfg.es_pop)], axis=0).head(cfg.es_pop)[self.names].to_numpy(dtype=float)
            )
            if cfg.lean_nsga and acq.num_constr == 0:
                return lean_nsga2(
                    functools.partial(_acq_objectives, acq), init, cfg.es_pop, cfg.es_iters, np.random.default_rng(key)
                )
            prob: Any = _vector_acq_problem_class()(acq, self.dim)
            algo = h["NSGA2"](pop_size=cfg.es_pop, sampling=init, eliminate_duplicates=True)
        else:  # HEBO's own mixed-variable setup
            prob = h["BOProblem"](acq, space, None)
            algo = h["NSGA2"](
                pop_size=cfg.es_pop,
                sampling=h["get_init_pop"](space, cfg.es_pop, best_x, True),
                mating=h["MixedVariableMating"](eliminate_duplicates=h["MixedVariableDuplicateElimination"]()),
                eliminate_duplicates=h["MixedVariableDuplicateElimination"](),
            )
        x = h["minimize"](prob, algo, ("n_gen", cfg.es_iters), verbose=False, seed=key % (2**31)).X
        if x is None:
            return np.empty((0, self.dim))
        if cfg.vector_nsga:
            return np.atleast_2d(np.asarray(x, dtype=float))
        x = [x] if isinstance(x, dict) else list(x)
        return pd.DataFrame(x)[self.names].to_numpy(dtype=float)

    def _unseen(
        self, rec: npt.NDArray[np.float64], n: int, key: int, m: int, pending: npt.NDArray[np.float64]
    ) -> npt.NDArray[np.float64]:
        """The candidates clipped to the box, without duplicates, observed or pending points;
        filled up to ``n`` with Sobol points when too few (as HEBO does)."""
        rec = np.unique(np.clip(rec, 0.0, 1.0), axis=0)
        seen = {tuple(r) for r in self.X[:m]} | {tuple(r) for r in pending}
        rec = np.array([r for r in rec if tuple(r) not in seen]).reshape(-1, self.dim)
        if len(rec) < n:  # too few Pareto points: fill with Sobol points from a sequence scrambled
            # with this call's key, so that a resumed batch does not redraw the fill points of
            # the interrupted one
            fill = self._sobol(n - len(rec) + len(pending), 0, seed=int(key % (2**31)))
            fill = np.array([r for r in fill if tuple(r) not in seen]).reshape(-1, self.dim)  # pending ones stay out
            rec = np.vstack([rec, fill[: n - len(rec)]])
        return rec

    def _select(self, rec: npt.NDArray[np.float64], n: int, key: int, model: Any) -> npt.NDArray[np.float64]:
        """HEBO's pick of ``n`` of the candidates: at random, but always with the one of
        lowest predicted mean and the one of highest predicted uncertainty."""
        import torch

        mu, sig = self._h["Mean"](model), self._h["Sigma"](model, linear_a=-1.0)
        select = np.random.default_rng(key).choice(len(rec), n, replace=False).tolist()
        with torch.no_grad():
            t = torch.from_numpy(rec).float()
            e = torch.zeros((len(rec), 0), dtype=torch.long)
            py_all = mu(t, e).squeeze(-1).numpy().reshape(-1)
            ps_all = (-1 * sig(t, e)).squeeze(-1).numpy().reshape(-1)
        best_pred, best_unc = int(np.argmin(py_all)), int(np.argmax(ps_all))
        if best_unc not in select and n > 2:
            select[0] = best_unc
        if best_pred not in select and n > 2:
            select[1] = best_pred
        return rec[select].astype(float)
