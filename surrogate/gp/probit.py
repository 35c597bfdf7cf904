"""log Phi(z), the probit likelihood's log, as gpytorch computes it, without its masks.

Hand-written, and why: the binned ELBO (:func:`~surrogate.gp.binned.binned_loss`) evaluates
log Phi at every quadrature node of every bin of every GP each step, and gpytorch's
``LogNormalCDF`` selects its three branches with ``masked_select``/``masked_scatter_`` (and
their ``nonzero`` syncs) forward and indexed writes backward: half of a K-lumps training
step's time (E. coli, 45 GPs x 100 bins x 20 nodes: 39 ms a step, 20 of them there; measured by
``scripts/bench_fit.py``). :func:`log_normal_cdf` computes every branch on every element and
picks with ``torch.where``: the same formulas in the same order, so the same values bit for bit
(tests/gp/test_probit.py checks it against gpytorch's over the branches and their edges) and
the same objective, hence the same fits. Not ``torch.special.log_ndtr``: closer to the exact
integral, but another objective (binned.py says what it changed).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.autograd import Function

# gpytorch.functions._log_normal_cdf's constants (gpytorch 1.11-1.15), in its order
_NEAR_ZERO = (0.00048204, -0.00142906, 0.0013200243174, 0.0009461589032, -0.0045563339802,
              0.00556964649138, 0.00125993961762116, -0.01621575378835404, 0.02629651521057465,
              -0.001829764677455021, 2 * (1 - math.pi / 3), (4 - math.pi) / 3, 1, 1)  # fmt: skip
_SMALL_NUMERATOR = (1.2753666447299659525, 5.019049726784267463450, 6.1602098531096305441,
                    7.409740605964741794425, 2.9788656263939928886)  # fmt: skip
_SMALL_DENOMINATOR = (2.260528520767326969592, 9.3960340162350541504, 12.048951927855129036034,
                      17.081440747466004316, 9.608965327192787870698, 3.3690752069827527677)  # fmt: skip


def _small_terms(z: Tensor) -> tuple[Tensor, Tensor]:
    """The rational approximation's numerator and denominator for z < -1 (at every element)."""
    # gpytorch adds each constant as a 0-d tensor of z's dtype: the same roundings here
    numerator = torch.full_like(z, 0.5641895835477550741)
    denominator = torch.ones_like(z)
    for r in torch.tensor(_SMALL_NUMERATOR, dtype=z.dtype, device=z.device):
        numerator = -z.mul(numerator.div(math.sqrt(2))) + r
    for q in torch.tensor(_SMALL_DENOMINATOR, dtype=z.dtype, device=z.device):
        denominator = -z.mul(denominator.div(math.sqrt(2))) + q
    return numerator, denominator


class _LogNormalCDF(Function):
    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, z: Tensor) -> Tensor:
        near_zero = z.pow(2).lt(0.04)
        small = z.lt(-1)
        first = -z.div(math.sqrt(2 * math.pi))
        f: Tensor | float = 0
        # gpytorch's constants pass through a tensor of z's dtype, then Python floats
        for c in torch.tensor(_NEAR_ZERO, dtype=z.dtype).tolist():
            f = first.mul(c + f)
        assert isinstance(f, Tensor)
        at_zero = f.mul(-2).sub(math.log(2))
        numerator, denominator = _small_terms(z)
        at_small = torch.log(numerator.div(denominator) / 2) - z.pow(2).div(2)
        ordinary = torch.log(torch.distributions.Normal(0.0, 1.0).cdf(z))
        out = torch.where(near_zero, at_zero, torch.where(small, at_small, ordinary))
        ctx.save_for_backward(z, out, numerator, denominator)
        return out

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad_output: Tensor) -> Tensor:
        z, out, numerator, denominator = ctx.saved_tensors  # type: ignore[attr-defined]
        small = torch.abs(denominator.div(numerator)).mul(math.sqrt(2 / math.pi))
        other = torch.exp(z.pow(2).div(-2).sub(out).add(math.log(0.5))).mul(math.sqrt(2 / math.pi))
        return torch.where(z.lt(-1), small, other).mul(grad_output)


def log_normal_cdf(z: Tensor) -> Tensor:
    """log Phi(z), elementwise, equal to ``gpytorch.functions.log_normal_cdf`` (values and
    gradients), in one branch-free pass.

    Args:
        z: any shape.

    Example:
        >>> log_normal_cdf(torch.tensor([-3.0, 0.0, 2.0]))
        tensor([-6.6077, -0.6931, -0.0230])
    """
    return _LogNormalCDF.apply(z)


__all__ = ["log_normal_cdf"]
