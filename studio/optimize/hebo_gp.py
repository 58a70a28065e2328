"""HEBO's Gaussian-process model (``hebo.models.gp.gp.GP``), re-implemented in plain torch.

The same model, priors, scalers and fit as HEBO 0.3.6's ``GP`` with one numerical
input kind (what :mod:`studio.optimize.hebo_adapter` uses):

- inputs min-max scaled to [-1, 1] per column, targets standardized (HEBO's own scalers);
- constant mean; Matérn-3/2 ARD kernel with an output scale (``ScaleKernel``), length
  scales initialized to each column's median pairwise distance (at least 0.02), output
  scale to the variance of the scaled targets; Gaussian noise ``softplus(raw) + noise_lb``
  initialized to ``max(0.01, noise_lb)``;
- priors: output scale Gamma(0.5, 0.5), noise LogNormal(log 0.01, 0.5); the loss is
  gpytorch's ``ExactMarginalLogLikelihood`` (negative log marginal likelihood plus the
  log priors, divided by the number of points);
- fit: HEBO's ``pSGLD`` (RMSprop plus Langevin noise after the first tenth of the
  epochs) over the raw parameters in gpytorch's order (noise, mean, output scale, length
  scales), so a seeded fit draws the same noise as HEBO's (and the same numpy draws).

What differs, and why: gpytorch spends most of a fit in per-call overhead (lazy tensors,
settings, memoization; figures: ``docs/optimization.md#the-hebo-adapter-and-its-gp``). Here one
epoch is a kernel matrix, one Cholesky factorization and an analytic gradient of the
Gaussian log-likelihood with respect to the kernel matrix, ``(K^-1 - a a^T) / 2`` with
``a = K^-1 r`` (one ``cholesky_inverse`` instead of autograd through the factorization).
Predictions use the exact posterior variance from the cached factor (HEBO asks gpytorch
for LOVE's approximation, ``fast_pred_var``), without the likelihood noise as the adapter
configures HEBO (``pred_likeli=False``). ``tests/test_hebo_gp.py`` checks the loss, its
gradient and the predictions against gpytorch's model with the same parameters, and a
seeded fit against HEBO's.

Beyond HEBO: a fit can start from where an earlier one ended (``fit(..., start=state())``,
:class:`FitState`), which :class:`studio.optimize.hebo_adapter.HeboAdapter` uses to fit
each batch's GP in a few epochs from the previous batch's (``tests/test_hebo_warm.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

_SQRT3 = math.sqrt(3.0)
_LOG_2PI = math.log(2.0 * math.pi)


def _softplus_inv(x: Tensor) -> Tensor:
    """gpytorch's inverse softplus (``x + log(-expm1(-x))``)."""
    return x + torch.log(-torch.expm1(-x))


def _cholesky(K: Tensor, jitters: tuple[float, ...], used: list[float]) -> Tensor:
    """Lower Cholesky factor of K + jitter I with the first jitter that works (appended to ``used``)."""
    for jitter in jitters:
        L, info = torch.linalg.cholesky_ex(K if jitter == 0.0 else K + jitter * torch.eye(len(K), dtype=K.dtype))
        if int(info) == 0:
            used.append(jitter)
            return L
    raise torch.linalg.LinAlgError("GP kernel matrix is not positive definite at any jitter")


class _GaussNLL(torch.autograd.Function):
    """``0.5 r^T K^-1 r + 0.5 log det K`` of a symmetric positive-definite K (n, n) and a
    residual r (n,), with the analytic gradient ``dK = (K^-1 - a a^T) / 2``, ``dr = a``."""

    @staticmethod
    def forward(ctx: Any, K: Tensor, r: Tensor, jitters: tuple[float, ...], used: list[float]) -> Tensor:  # type: ignore[override]
        L = _cholesky(K, jitters, used)
        a = torch.cholesky_solve(r.unsqueeze(-1), L).squeeze(-1)
        ctx.save_for_backward(L, a)
        return 0.5 * torch.dot(r, a) + torch.log(torch.diagonal(L)).sum()

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor, Tensor, None, None]:  # type: ignore[override]
        L, a = ctx.saved_tensors
        Kinv = torch.cholesky_inverse(L)
        return 0.5 * g * (Kinv - torch.outer(a, a)), g * a, None, None


def _matern32(Z1: Tensor, Z2: Tensor) -> Tensor:
    """Matérn-3/2 correlation of length-scaled points Z1 (n, d), Z2 (m, d) -> (n, m)."""
    sq = (Z1 * Z1).sum(-1, keepdim=True) - 2.0 * Z1 @ Z2.T + (Z2 * Z2).sum(-1)
    r = _SQRT3 * sq.clamp_min(1e-30).sqrt()
    return (1.0 + r) * torch.exp(-r)


@dataclass(frozen=True)
class FitState:
    """Where a :class:`FastGP` fit ended: what a warm-started fit on more data starts from."""

    raw: tuple[Tensor, Tensor, Tensor, Tensor]
    """Raw (unconstrained) noise, mean, output scale and length scales (1, d), in gpytorch's order."""
    loss: float
    """:meth:`FastGP.loss` at the end of the fit: negative log marginal likelihood plus
    negative log priors, per training point [nats per point] (``inf``: not factorizable)."""
    points: int
    """Training points of the fit."""


class FastGP:
    """Drop-in for HEBO's ``GP`` (numerical inputs only): ``fit``, ``predict``, ``noise``."""

    support_grad = False
    num_out = 1

    JITTERS: tuple[float, ...] = (0.0, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)
    """Diagonal jitters tried in turn when a Cholesky factorization fails (gpytorch's float32
    schedule starts at 1e-6 and HEBO's retry loop raises it tenfold up to 10)."""

    def __init__(self, num_cont: int, num_enum: int, num_out: int, **conf: Any) -> None:
        if num_enum != 0 or num_out != 1:
            raise ValueError("FastGP supports numerical inputs and one output only")
        self.num_cont = int(num_cont)
        self.lr = float(conf.get("lr", 3e-2))
        self.num_epochs = int(conf.get("num_epochs", 100))
        self.noise_lb = float(conf.get("noise_lb", 1e-5))
        self.noise_guess = float(conf.get("noise_guess", 0.01))
        self.pred_likeli = bool(conf.get("pred_likeli", True))
        self.failed_steps = 0
        """Epochs skipped because no jitter made the kernel matrix positive definite."""
        self.jitters_used: list[float] = []
        """Diagonal jitter of every factorization (0 when none was needed)."""

    # -- parameters --------------------------------------------------------------------

    def _constrained(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(noise, mean, output scale, length scales (d,)) from the raw parameters."""
        sp = torch.nn.functional.softplus
        return (
            sp(self.raw_noise) + self.noise_lb,
            self.raw_constant,
            sp(self.raw_outputscale),
            sp(self.raw_lengthscale).reshape(-1),
        )

    def loss(self) -> Tensor:
        """gpytorch's ``-ExactMarginalLogLikelihood`` (priors included) at the current parameters."""
        noise, c, os_, ls = self._constrained()
        Z = (self.Xc - self._centre) / ls  # centred as gpytorch does (smaller float32 rounding in the distances)
        n = len(Z)
        K = os_ * _matern32(Z, Z) + torch.diag_embed(noise.expand(n))
        nll = _GaussNLL.apply(K, self.y - c, self.JITTERS, self.jitters_used) + 0.5 * n * _LOG_2PI
        # priors (log densities of the constrained values, as gpytorch adds them)
        conc = rate = 0.5
        log_gamma = conc * math.log(rate) + (conc - 1.0) * torch.log(os_) - rate * os_ - math.lgamma(conc)
        log_noise = torch.log(noise)
        mu, s = math.log(self.noise_guess), 0.5
        log_lognormal = (-0.5 * ((log_noise - mu) / s) ** 2 - math.log(s) - 0.5 * _LOG_2PI - log_noise).sum()
        return (nll - log_gamma - log_lognormal) / n

    # -- HEBO's model interface --------------------------------------------------------

    def fit(
        self, Xc: Tensor, Xe: Tensor, y: Tensor, *, start: FitState | None = None, epochs: int | None = None
    ) -> None:
        """Fit the hyper-parameters to (Xc (n, d), y (n, 1)) with HEBO's pSGLD.

        ``start=None`` (HEBO's cold fit): parameters initialized as HEBO does, ``num_epochs``
        epochs. ``start``: a warm start from the raw parameters where an earlier fit ended
        (:meth:`state`), ``epochs`` (default ``num_epochs``) epochs of the same pSGLD (a
        fresh RMSprop: on the serve task's GP fits its first, larger steps reached a lower
        loss than continuing the earlier fit's step sizes). Scalers and data are those of
        this call in both cases.
        """
        self._set_data(Xc, y)
        if start is None:
            params = self._initial_params()
        else:
            if start.raw[3].shape != (1, self.Xc.shape[1]):
                raise ValueError(
                    f"FastGP.fit: the warm start has {start.raw[3].shape[-1]} length scales, the inputs {self.Xc.shape[1]} columns"
                )
            params = [p.detach().clone().requires_grad_(True) for p in start.raw]
        self.raw_noise, self.raw_constant, self.raw_outputscale, self.raw_lengthscale = params
        self._train(params, self.num_epochs if epochs is None else int(epochs))
        self._cache()

    def _set_data(self, Xc: Tensor, y: Tensor) -> None:
        """Scalers (HEBO's: inputs to [-1, 1], targets standardized) and the scaled data."""
        from hebo.models.scalers import TorchMinMaxScaler, TorchStandardScaler

        Xc, y = Xc.float(), y.float()
        if not (torch.isfinite(Xc).all() and torch.isfinite(y).all()):
            raise ValueError("FastGP.fit: inputs and targets must be finite")
        self.xscaler = TorchMinMaxScaler((-1, 1)).fit(Xc)
        self.yscaler = TorchStandardScaler().fit(y)
        self.Xc = self.xscaler.transform(Xc)
        self._centre = self.Xc.mean(0)
        self.y = self.yscaler.transform(y).reshape(-1)

    def _initial_params(self) -> list[Tensor]:
        """HEBO's initial raw parameters (noise, mean, output scale, length scales (1, d))."""
        d = self.Xc.shape[1]
        for _ in range(d):  # HEBO's kernel set-up draws a permutation per column from numpy's global
            # generator (the median is order-free); draw the same so later draws match HEBO's
            np.random.choice(len(self.Xc), min(len(self.Xc), 1000), replace=False)
        ls0 = torch.stack([torch.pdist(self.Xc[:, i : i + 1]).median().clamp(min=0.02) for i in range(d)])
        raw_noise = _softplus_inv(torch.tensor([max(1e-2, self.noise_lb) - self.noise_lb]))
        # HEBO starts the output scale at the targets' variance; floored so that identical
        # targets (e.g. only failed plans so far) do not start it at 0 (softplus^-1(0) = -inf)
        raw_outputscale = _softplus_inv(self.y.var().clamp_min(1e-4))
        return [
            p.requires_grad_(True)
            for p in (raw_noise, torch.zeros(()), raw_outputscale, _softplus_inv(ls0).reshape(1, d))
        ]

    def _train(self, params: list[Tensor], epochs: int) -> None:
        """``epochs`` pSGLD epochs on ``params``; a diverged fit falls back to its start."""
        from hebo.models.nn.sgld import pSGLD

        start = [p.detach().clone() for p in params]
        opt = pSGLD(params, lr=self.lr, factor=1.0 / len(self.y), pretrain_step=epochs // 10)
        for _ in range(epochs):
            opt.zero_grad()
            try:
                self.loss().backward()
            except torch.linalg.LinAlgError:
                self.failed_steps += 1  # HEBO: "jitter is too large, give up fitting GP" (for this epoch)
                continue
            opt.step()
        if not self._usable():  # a diverged fit (e.g. on identical targets): keep the start
            self.failed_steps += 1
            with torch.no_grad():
                for p, p0 in zip(params, start, strict=True):
                    p.copy_(p0)

    def _usable(self) -> bool:
        """The parameters are finite and give a factorizable kernel matrix with a finite loss."""
        params = (self.raw_noise, self.raw_constant, self.raw_outputscale, self.raw_lengthscale)
        if not all(bool(torch.isfinite(p).all()) for p in params):
            return False
        with torch.no_grad():
            try:
                return bool(torch.isfinite(self.loss()))
            except torch.linalg.LinAlgError:
                return False

    def state(self) -> FitState:
        """Where the last fit ended (to warm-start a later fit on more data); its loss is
        evaluated here at the fitted parameters (one factorization)."""
        with torch.no_grad():
            try:
                loss = float(self.loss())
            except torch.linalg.LinAlgError:
                loss = math.inf
        raw = tuple(
            p.detach().clone() for p in (self.raw_noise, self.raw_constant, self.raw_outputscale, self.raw_lengthscale)
        )
        return FitState(raw=raw, loss=loss, points=len(self.y))  # type: ignore[arg-type]

    def _cache(self) -> None:
        """Factor of the training covariance and the weights of the posterior mean."""
        with torch.no_grad():
            noise, c, os_, ls = self._constrained()
            self._ls, self._os, self._c, self._noise = ls.clone(), os_.clone(), c.clone(), noise.clone()
            Z = (self.Xc - self._centre) / ls
            n = len(Z)
            K = os_ * _matern32(Z, Z) + noise * torch.eye(n)
            self._Z, self._L = Z, _cholesky(K, self.JITTERS, self.jitters_used)
            self._alpha = torch.cholesky_solve((self.y - c).unsqueeze(-1), self._L)

    def predict(self, Xc: Tensor, Xe: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and variance (n, 1) at Xc (n, d) in the caller's units."""
        with torch.no_grad():
            Zs = (self.xscaler.transform(Xc.float()) - self._centre) / self._ls
            Ks = self._os * _matern32(Zs, self._Z)  # (n, m)
            mu = self._c + Ks @ self._alpha
            v = torch.linalg.solve_triangular(self._L, Ks.T, upper=False)
            var = (self._os - (v * v).sum(0)).reshape(-1, 1)
            if self.pred_likeli:
                var = var + self._noise
            mu = self.yscaler.inverse_transform(mu.reshape(-1, 1))
            var = var * self.yscaler.std**2
            return mu, var.clamp(min=torch.finfo(var.dtype).eps)

    def condition_on(self, Xc: Tensor) -> None:
        """Add pending points Xc (m, d) as observations at the posterior mean (the "kriging
        believer" for a batch still being evaluated), hyper-parameters unchanged: the
        posterior mean stays the same everywhere and the variance shrinks around them."""
        if len(Xc) == 0:
            return
        with torch.no_grad():
            Xs = self.xscaler.transform(Xc.float())
            Ks = self._os * _matern32((Xs - self._centre) / self._ls, self._Z)
            mu = self._c + (Ks @ self._alpha).reshape(-1)
            self.Xc = torch.cat([self.Xc, Xs])
            self.y = torch.cat([self.y, mu])
        self._cache()

    @property
    def noise(self) -> Tensor:
        """Noise variance in the caller's target units, shape (1,)."""
        return (self._noise * self.yscaler.std**2).reshape(1).detach()

    def hyperparameters(self) -> dict[str, Any]:
        """Fitted values (scaled units): noise, mean, output scale, length scales."""
        return {
            "noise": float(self._noise),
            "mean": float(self._c),
            "outputscale": float(self._os),
            "lengthscale": np.asarray(self._ls, dtype=float).tolist(),
        }
