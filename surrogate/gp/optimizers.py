"""Optimisers other than Adam for the batched binned GP fit, measured against it by
``scripts/bench_fit.py`` (:mod:`surrogate.benchmarks.fit`; docs/performance.md, "Faster fits:
measured"). ``gp.optimizer=lbfgs`` selects :func:`fit_lbfgs` for the batched binned fit
(opt-in: none matched Adam's 1,000 steps within the posterior sd where data live, a bar
Adam's 1,000 steps miss against its own 2,000); ``ngd`` is measured only.

:func:`~surrogate.gp.training.fit_classifiers` trains several classifiers as one batched GP
whose loss is the sum of their negative ELBOs per point (``loss_fn() -> (b,)``). Each optimiser
here is given such a batched model and a closure evaluating the loss:

* ``ngd``: natural-gradient steps on the variational parameters (a
  ``NaturalVariationalDistribution``) and Adam on the hyperparameters, one step of each per
  iteration. The natural step of GP ``i`` is ``lr`` times the gradient of its own negative ELBO
  (not per point): :class:`gpytorch.optim.NGD` with a ``num_data`` per batch entry.
* ``lbfgs``: :class:`torch.optim.LBFGS` over every parameter with a strong-Wolfe line search;
  one step size for the whole batch (the line search sees the sum).

Both record each GP's loss at every evaluation (``histories``) and raise
:class:`FloatingPointError` when a loss is not finite (gpytorch's ``NotPSDError`` where a
covariance breaks down).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import gpytorch
import torch
from torch import Tensor

LossFn = Callable[[], Tensor]


def _record(losses: Tensor, histories: Sequence[list[float]]) -> None:
    values = losses.detach().cpu().tolist()
    if not all(math.isfinite(v) for v in values):
        raise FloatingPointError(f"loss became {values}")
    for h, v in zip(histories, values, strict=True):
        h.append(v)


def natural_step(parameters: Sequence[Tensor], n_data: Tensor, lr: float) -> None:
    """One natural-gradient step on the batched natural parameters ``parameters`` (each
    ``b x ...``) whose ``.grad`` holds the gradient of the sum of per-point losses:
    ``theta_i -= lr * n_data[i] * grad_i`` (``n_data``: ``b``, each GP's data count), the
    step :class:`gpytorch.optim.NGD` takes with its ``num_data`` per batch entry."""
    with torch.no_grad():
        for p in parameters:
            if p.grad is not None:
                scale = n_data.reshape(-1, *([1] * (p.dim() - 1))).to(p.dtype)
                p.sub_(lr * scale * p.grad)


def fit_ngd(
    model: gpytorch.models.ApproximateGP,
    likelihood: gpytorch.likelihoods.Likelihood,
    loss_fn: LossFn,
    n_data: Tensor,
    steps: int,
    lr: float,
    natural_lr: float,
    histories: Sequence[list[float]],
) -> None:
    """``steps`` iterations of NGD (variational parameters, ``natural_lr``) and Adam
    (hyperparameters, ``lr``) on ``loss_fn`` (``() -> (b,)``, per-point losses).

    Args:
        model: a batched GP with a natural variational distribution.
        likelihood: its likelihood (its parameters, if any, are hyperparameters).
        loss_fn: the batch's negative ELBO per point, ``b``.
        n_data: ``b``, each GP's data count (the per-point loss's divisor).
        steps: iterations.
        lr: Adam's learning rate.
        natural_lr: the natural step's size (1: the exact update of a conjugate model).
        histories: ``b`` lists, each GP's loss appended at every iteration.
    """
    natural = list(model.variational_parameters())
    hyper = torch.optim.Adam([*model.hyperparameters(), *likelihood.parameters()], lr=lr)
    for _ in range(steps):
        for p in natural:
            p.grad = None
        hyper.zero_grad(set_to_none=True)
        losses = loss_fn()
        losses.sum().backward()
        _record(losses, histories)
        natural_step(natural, n_data, natural_lr)
        hyper.step()


def fit_lbfgs(
    parameters: Sequence[Tensor],
    loss_fn: LossFn,
    steps: int,
    histories: Sequence[list[float]],
) -> int:
    """At most ``steps`` L-BFGS iterations (strong-Wolfe line search) on the sum of
    ``loss_fn``'s per-point losses over ``parameters``; returns the loss evaluations made
    (each appended to ``histories``)."""
    optimizer = torch.optim.LBFGS(list(parameters), lr=1.0, max_iter=steps,
                                  history_size=20, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-7, tolerance_change=1e-10)  # fmt: skip
    evaluations = 0

    def closure() -> Tensor:
        nonlocal evaluations
        optimizer.zero_grad(set_to_none=True)
        losses = loss_fn()
        _record(losses, histories)
        evaluations += 1
        total = losses.sum()
        total.backward()
        return total

    optimizer.step(closure)
    return evaluations


__all__ = ["fit_lbfgs", "fit_ngd", "natural_step"]
