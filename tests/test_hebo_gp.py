"""FastGP against HEBO's gpytorch GP: same loss, gradient, seeded fit, predictions and suggestions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from studio.optimize.hebo_adapter import HeboAdapter, HeboConfig
from studio.optimize.hebo_gp import FastGP

CONF = {"lr": 0.01, "noise_lb": 8e-4, "pred_likeli": False, "verbose": False}


def _data(n: int = 120, d: int = 5, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    X = rng.random((n, d))
    y = ((X - 0.3) ** 2).sum(1, keepdims=True) + 0.05 * rng.standard_normal((n, 1))
    y[: n // 6] = 3.0  # a block of identical penalty targets, as failed plans give
    return torch.tensor(X, dtype=torch.float32), torch.tensor(y, dtype=torch.float32)


def _hebo_gp(X: torch.Tensor, y: torch.Tensor, epochs: int, seed: int) -> object:
    from hebo.models.model_factory import get_model

    torch.manual_seed(seed)
    np.random.seed(seed)
    g = get_model("gp", X.shape[1], 0, 1, num_epochs=epochs, **CONF)
    g.fit(X, torch.zeros(len(X), 0, dtype=torch.long), y)
    return g


def _fast_gp(X: torch.Tensor, y: torch.Tensor, epochs: int, seed: int) -> FastGP:
    torch.manual_seed(seed)
    np.random.seed(seed)
    f = FastGP(X.shape[1], 0, 1, num_epochs=epochs, **CONF)
    f.fit(X, torch.zeros(len(X), 0, dtype=torch.long), y)
    return f


def _raw(f: FastGP) -> list[torch.Tensor]:
    return [f.raw_noise, f.raw_constant, f.raw_outputscale, f.raw_lengthscale]


def test_loss_and_gradient_equal_gpytorch_marginal_likelihood() -> None:
    import gpytorch

    X, y = _data()
    g, f = _hebo_gp(X, y, 0, 1), _fast_gp(X, y, 0, 1)
    params = list(g.gp.parameters())  # noise, mean, output scale, length scales: the same order
    gen = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for a, b in zip(_raw(f), params, strict=True):
            assert torch.equal(a.detach().reshape(-1), b.detach().reshape(-1))  # same initialization
            step = 0.4 * torch.randn(a.shape, generator=gen)
            a.add_(step)
            b.add_(step.reshape(b.shape))
    g.gp.train()
    g.lik.train()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(g.lik, g.gp)
    lg = -mll(g.gp(g.Xc, g.Xe), g.y.squeeze())
    lg.backward()
    lf = f.loss()
    lf.backward()
    assert float(lf) == pytest.approx(float(lg), rel=1e-5)
    for a, b in zip(_raw(f), params, strict=True):
        np.testing.assert_allclose(a.grad.reshape(-1).numpy(), b.grad.reshape(-1).numpy(), rtol=2e-3, atol=2e-6)


def test_seeded_fit_and_predictions_match_hebo() -> None:
    X, y = _data(n=150, d=6, seed=2)
    g, f = _hebo_gp(X, y, 30, 5), _fast_gp(X, y, 30, 5)
    for a, b in zip(_raw(f), g.gp.parameters(), strict=True):
        np.testing.assert_allclose(a.detach().reshape(-1).numpy(), b.detach().reshape(-1).numpy(), atol=2e-4)
    Xs = torch.rand(40, 6, generator=torch.Generator().manual_seed(3))
    mg, vg = g.predict(Xs, torch.zeros(40, 0, dtype=torch.long))
    mf, vf = f.predict(Xs, torch.zeros(40, 0, dtype=torch.long))
    np.testing.assert_allclose(mf.numpy(), mg.detach().numpy(), atol=1e-4)
    np.testing.assert_allclose(vf.numpy(), vg.detach().numpy(), rtol=1e-3, atol=1e-6)
    np.testing.assert_allclose(f.noise.numpy(), g.noise.numpy(), rtol=1e-4)
    # the posterior interpolates: small variance at a training point, prior-sized far away
    _, v_train = f.predict(X[:1], None)
    _, v_far = f.predict(torch.full((1, 6), 5.0), None)
    assert float(v_train) < 0.1 * float(v_far)


def test_adapter_suggestions_identical_with_either_gp() -> None:
    rng = np.random.default_rng(4)
    X = rng.random((60, 4))
    y = ((X - 0.6) ** 2).sum(1)
    y[rng.random(60) < 0.2] = 10.0
    out = []
    for fast in (False, True):
        a = HeboAdapter(4, seed=3, config=HeboConfig(fast_gp=fast, gp_epochs=15, es_pop=16, es_iters=5, refit_every=None))  # cold fits, as HEBO
        a.observe(X, y)
        out.append(a.suggest(6))
    np.testing.assert_allclose(out[0], out[1], atol=1e-6)


def test_bad_input_rejected() -> None:
    with pytest.raises(ValueError, match="numerical inputs"):
        FastGP(3, 1, 1)
    X, y = _data(n=20, d=3)
    y[3] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        FastGP(3, 0, 1).fit(X, torch.zeros(20, 0, dtype=torch.long), y)


def test_pending_points_keep_the_mean_and_shrink_the_variance() -> None:
    X, y = _data(n=80, d=4, seed=5)
    f = _fast_gp(X, y, 20, 1)
    P = torch.rand(5, 4, generator=torch.Generator().manual_seed(9))
    Xs = torch.rand(30, 4, generator=torch.Generator().manual_seed(10))
    m0, v0 = f.predict(Xs, None)
    _, vp0 = f.predict(P, None)
    f.condition_on(P)
    m1, v1 = f.predict(Xs, None)
    _, vp1 = f.predict(P, None)
    np.testing.assert_allclose(m1.numpy(), m0.numpy(), atol=1e-4)  # kriging believer: same mean
    assert torch.all(v1 <= v0 + 1e-6)
    assert torch.all(vp1 < 0.2 * vp0)  # the pending points are now (almost) known


def test_adapter_never_suggests_pending_points_and_needs_fast_gp_to_fantasize() -> None:
    from studio.errors import InvalidInputError

    rng = np.random.default_rng(6)
    X = rng.random((40, 3))
    cfg = HeboConfig(gp_epochs=10, es_pop=16, es_iters=4)
    a = HeboAdapter(3, seed=2, config=cfg)
    a.observe(X, ((X - 0.5) ** 2).sum(1))
    first = a.suggest(5)
    again = a.suggest(5, pending=first)
    assert not {tuple(r) for r in first} & {tuple(r) for r in again}
    np.testing.assert_array_equal(a.suggest(5, pending=first[::-1]), again)  # order-free
    with pytest.raises(InvalidInputError, match="pending points must be finite"):
        a.suggest(5, pending=np.array([[0.1, np.nan, 0.2]]))
    slow = HeboAdapter(3, seed=2, config=HeboConfig(gp_epochs=10, es_pop=16, es_iters=4, fast_gp=False))
    slow.observe(X, ((X - 0.5) ** 2).sum(1))
    with pytest.raises(InvalidInputError, match="fantasize needs fast_gp"):
        slow.suggest(5, pending=first)


def test_identical_targets_still_give_suggestions() -> None:
    """Only failed plans so far: every target equals the penalty (HEBO's GP survives this too)."""
    X, y = _data(n=30, d=3, seed=7)
    f = _fast_gp(X, torch.full_like(y, 10.0), 20, 0)
    mu, var = f.predict(X[:4], None)
    assert torch.all(torch.isfinite(mu)) and torch.all(torch.isfinite(var))
    a = HeboAdapter(3, seed=1, config=HeboConfig(gp_epochs=10, es_pop=16, es_iters=4))
    a.observe(np.random.default_rng(0).random((30, 3)), np.full(30, 10.0))
    Z = a.suggest(6)
    assert Z.shape == (6, 3) and np.all(np.isfinite(Z))
