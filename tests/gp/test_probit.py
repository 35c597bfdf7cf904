"""The branch-free log Phi (surrogate.gp.probit) against gpytorch's, which it replaces in the
binned ELBO: equal values and gradients, bit for bit, over each branch and its edges."""

from __future__ import annotations

import gpytorch
import pytest
import torch
from gpytorch.functions import log_normal_cdf as gpytorch_log_normal_cdf

from surrogate.gp.binned import binned_expected_log_likelihood
from surrogate.gp.probit import log_normal_cdf


def _points(dtype: torch.dtype) -> torch.Tensor:
    edges = torch.tensor([-1.0, -0.2, 0.2, 0.0, -0.19999, 0.19999, -1.00001, -0.99999],
                         dtype=dtype)  # fmt: skip
    sweep = torch.linspace(-40.0, 40.0, 20_002, dtype=dtype)
    return torch.cat([edges, sweep, 3.0 * torch.randn(5_000, generator=torch.Generator().
                                                      manual_seed(0), dtype=dtype)])  # fmt: skip


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_and_gradients_equal_gpytorch_bit_for_bit(dtype: torch.dtype) -> None:
    z = _points(dtype).reshape(-1, 2)
    ours, theirs = z.clone().requires_grad_(), z.clone().requires_grad_()
    a, b = log_normal_cdf(ours), gpytorch_log_normal_cdf(theirs)
    assert torch.equal(a, b)
    weights = torch.randn(z.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    (a * weights).sum().backward()
    (b * weights).sum().backward()
    assert ours.grad is not None and theirs.grad is not None
    assert torch.equal(ours.grad, theirs.grad)
    assert bool(torch.isfinite(a).all()) and bool(torch.isfinite(ours.grad).all())


def test_binned_likelihood_is_gpytorchs() -> None:
    """The binned ELBO's data term with it is what gpytorch's function gives (the fit's
    objective is unchanged)."""
    gen = torch.Generator().manual_seed(2)
    mean = torch.randn(3, 50, generator=gen, dtype=torch.float64) * 2
    var = torch.rand(3, 50, generator=gen, dtype=torch.float64) + 0.01
    f = gpytorch.distributions.MultivariateNormal(mean, torch.diag_embed(var))
    n = torch.randint(1, 50, (3, 50), generator=gen).to(torch.float64)
    k = torch.floor(n * torch.rand(3, 50, generator=gen, dtype=torch.float64))
    likelihood = gpytorch.likelihoods.BernoulliLikelihood()
    expected = likelihood.quadrature(
        lambda s: k * gpytorch_log_normal_cdf(s) + (n - k) * gpytorch_log_normal_cdf(-s), f
    )
    assert torch.equal(binned_expected_log_likelihood(likelihood, f, n, k), expected)
