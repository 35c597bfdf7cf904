"""Binned training data: points aggregated into equal-width bins of the normalised inputs
(:func:`bin_inputs`), the binned likelihood (:func:`binned_expected_log_likelihood`,
:func:`binned_loss`) and the weight of an expected label (:func:`label_weight`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import gpytorch
import torch
from torch import Tensor

from surrogate.errors import ConfigError, NumericalError
from surrogate.gp.model import PsiGP
from surrogate.gp.probit import log_normal_cdf


def weighted_bins(
    binned: tuple[Tensor, Tensor, Tensor], weight: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Bins whose rows count ``weight`` draws each (``weight == 1``: the same tensors)."""
    if weight == 1.0:
        return binned
    z_b, n_b, k_b = binned
    return z_b, n_b * weight, k_b * weight


def padded_bins(binned: Sequence[tuple[Tensor, Tensor, Tensor]]) -> tuple[Tensor, Tensor, Tensor]:
    """Stack several classifiers' bins (``b x L x d``, ``b x L``, ``b x L``), padding with
    empty bins (no points: they add nothing to the ELBO) at the first bin's input."""
    size = max(z.shape[0] for z, _, _ in binned)

    def pad(t: Tensor, like: Tensor) -> Tensor:
        extra = size - t.shape[0]
        return torch.cat([t, like.expand(extra, *t.shape[1:])]) if extra else t

    z = torch.stack([pad(z, z[:1]) for z, _, _ in binned])
    n = torch.stack([pad(n, n.new_zeros(1)) for _, n, _ in binned])
    k = torch.stack([pad(k, k.new_zeros(1)) for _, _, k in binned])
    return z, n, k


def _bin_index(z: Tensor, bins: int | Sequence[int]) -> tuple[Tensor, int]:
    """Each point's equal-width bin (``bins`` per column, or ``bins[j]`` for column ``j``)
    and the number of bins."""
    d = z.shape[1]
    per_axis = [bins] * d if isinstance(bins, int) else list(bins)
    if len(per_axis) != d:
        raise ConfigError(f"gp.bins has {len(per_axis)} counts for {d} input(s): give one or {d}")
    index = torch.zeros(z.shape[0], dtype=torch.int64, device=z.device)
    for j, n in enumerate(per_axis):
        col = z[:, j].contiguous()  # bucketize copies (and warns) otherwise
        edges = torch.linspace(float(col.min()), float(col.max()), n + 1, device=z.device)
        index = index * n + torch.bucketize(col, edges[1:-1])
    return index, math.prod(per_axis)


def bin_inputs(
    z: Tensor, y: Tensor, bins: int | Sequence[int], rows: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Aggregate points into equal-width bins of every (normalised) input column: ``bins`` per
    column, or ``bins[j]`` for column ``j``.

    Returns the occupied bins' mean inputs ``b x d``, point counts ``n_b`` and counts of y = 1
    ``k_b``; with ``rows`` (``n``), each point counts as that many (the windows a row of a
    collection that keeps every switch stands for), in the counts and the means alike. With
    one input and hundreds of bins the bins are far narrower than any lengthscale psi varies
    on, so placing a bin's points at their mean changes the fit negligibly, while a
    full-batch step on ~``bins`` rows is cheap enough to converge (minibatch training on the
    points left the fit measurably off; see docs/fidelity.md).
    """
    d = z.shape[1]
    index, size = _bin_index(z, bins)
    # the labels and inputs summed per bin as one stack of columns, weighted once where rows are
    columns = torch.cat([y.to(z.dtype).reshape(-1, 1), z], 1)
    if rows is None:
        n_b = torch.bincount(index, minlength=size).to(z.dtype)
    else:
        w = rows.to(z.dtype).reshape(-1)
        n_b = torch.bincount(index, weights=w, minlength=size)
        columns = columns * w.unsqueeze(1)
    sums = torch.stack(
        [torch.bincount(index, weights=columns[:, j], minlength=size) for j in range(d + 1)], 1
    )
    k_b = sums[:, 0]
    sums = sums[:, 1:]
    keep = n_b > 0
    return sums[keep] / n_b[keep].unsqueeze(1), n_b[keep], k_b[keep]


def label_weight(z: Tensor, y: Tensor, bins: int | Sequence[int], cap: float) -> float:
    """How many Bernoulli draws one expected label is worth: the inverse of the quasi-binomial
    dispersion, Pearson's pooled estimate within equal-width bins of ``z`` (``n x d``),
    ``sum_b (n_b - 1) p_b (1 - p_b) / sum_i (y_i - p_b(i))^2`` over bins with two rows or more
    (``p_b`` the bin's mean label; ``n_b - 1``: the bin's mean uses up one degree of freedom),
    clipped to ``[1, cap]``.

    A 0/1 outcome has the binomial variance p (1 - p); an expected label, the window's law given
    the internal state, varies only as much as that state does among cells at the same input
    (not at all where the class pins the state). The binned likelihood counts a row as one draw,
    so without this weight a GP trusts noise-free labels as little as coin flips and bends
    where they are sparse (E. coli, run with 2 CCW motors leaving at the top of the occupied
    band: +28 % at 90 rows; docs/fidelity.md, "Memory"). Weighting the likelihood by it is the
    quasi-likelihood fit of a GLM with estimated dispersion. The bins span ``z``'s own range,
    as the training's bins span its (normalised) training split's: the same equal-width bins up
    to the held-out rows.

    One weight for all of a GP's rows, pooled over the bins: a per-bin estimate would be noise
    where rows are sparse (90 rows in 100 bins), which is where the weight matters. Pooling is
    right when the rows share one dispersion: labels of one kind from one collection (collect
    writes expected labels for every row or for none, so each GP of the pipeline gets one
    kind). Where it varies, rows with dispersions ``1/w_k`` in shares ``f_k`` get the inverse
    of the mean dispersion, ``1 / sum_k f_k / w_k``: the noisier rows are over-weighted and the
    quieter under-weighted. E.g. a table mixing noise-free expected labels with 0/1 outcomes
    copied into the expected column, half each, gets ~2: the outcomes count ~2x what they are
    worth. So do not mix label sources in one table; within one source the dispersion still
    varies with ``z`` where the class pins the internal state in places and not in others
    (E. coli's hidden S/C split), and the weight is then that average.
    """
    if not cap >= 1.0:
        raise ValueError(f"label_weight: cap must be >= 1, got {cap!r}")
    if not (bool(torch.isfinite(z).all()) and bool(torch.isfinite(y).all())):
        raise NumericalError("label_weight: inputs and labels must be finite")
    index, size = _bin_index(z, bins)
    y = y.to(torch.float64)
    n_b = torch.bincount(index, minlength=size).to(torch.float64)
    p_b = torch.bincount(index, weights=y, minlength=size) / n_b.clamp(min=1)
    pooled = n_b >= 2  # a bin of one row says nothing about the spread around its mean
    binomial = float(((n_b - 1) * p_b * (1 - p_b))[pooled].sum())
    residual = float(((y - p_b[index]) ** 2)[pooled[index]].sum())
    if binomial <= 0.0:  # every pooled bin all 0 or all 1: nothing to weigh
        return 1.0
    return float(min(cap, max(1.0, binomial / residual))) if residual > 0 else float(cap)


def binned_expected_log_likelihood(
    likelihood: gpytorch.likelihoods.BernoulliLikelihood,
    f: gpytorch.distributions.MultivariateNormal,
    n_b: Tensor,
    k_b: Tensor,
) -> Tensor:
    """Each bin's expected log-likelihood under q(f) (``... x L``): ``k`` successes and
    ``n - k`` failures of the probit likelihood, E_q[k log Phi(f) + (n - k) log Phi(-f)], in
    one pass of the likelihood's Gauss-Hermite quadrature.

    What ``BernoulliLikelihood.expected_log_prob`` computes for each label (with its
    ``log_normal_cdf``), summed, in one quadrature instead of two (a training step at the
    paper's size ~25 % cheaper), with :func:`~surrogate.gp.probit.log_normal_cdf`: gpytorch's
    values bit for bit, without its masks (a K-lumps step ~2x cheaper). Not ``torch.special.log_ndtr``, though it is closer to the
    exact integral: the objective would change, and the fitted psi with it (measured: up to
    2 % more bias where cells live after the default 1,000 steps on the same data).
    """
    return likelihood.quadrature(
        lambda s: k_b * log_normal_cdf(s) + (n_b - k_b) * log_normal_cdf(-s), f
    )


def binned_loss(
    model: PsiGP,
    likelihood: gpytorch.likelihoods.BernoulliLikelihood,
    z_b: Tensor,
    n_b: Tensor,
    k_b: Tensor,
) -> Tensor:
    """Negative ELBO per point on binned data (``...``: one per GP of a batch): the expected
    log-likelihood of k_b successes and n_b - k_b failures at each bin's mean input, minus the
    KL term."""
    ell = binned_expected_log_likelihood(likelihood, model(z_b), n_b, k_b)
    return -(ell.sum(-1) - model.variational_strategy.kl_divergence()) / n_b.sum(-1)


__all__ = [
    "bin_inputs",
    "binned_expected_log_likelihood",
    "binned_loss",
    "label_weight",
    "padded_bins",
    "weighted_bins",
]
