"""The sparse variational GP classifier that approximates one psi surface.

The model sees NORMALISED inputs -- see :class:`surrogate.gp.fitted.Normalizer` -- so kernel
lengthscales start at a sensible scale for every column (the ligand L spans only 0.1 mM).
"""

from __future__ import annotations

import gpytorch
import torch
from torch import Tensor

from surrogate.errors import ConfigError

KERNELS = ("rbf", "matern12", "matern32", "matern52")
#: the GP's prior mean of the latent f: a constant, or linear in the (normalised) inputs, which
#: carries the trend into sparsely trained inputs instead of reverting to one constant there
MEANS = ("constant", "linear")
#: gp.mean's default: a fit with it keeps the identity it had before the key existed
DEFAULT_MEAN = MEANS[0]

_MATERN_NU = {"matern12": 0.5, "matern32": 1.5, "matern52": 2.5}
_NO_BATCH = torch.Size()


def make_kernel(
    kernel: str, ard: bool, n_dims: int = 2, batch_shape: torch.Size = _NO_BATCH
) -> gpytorch.kernels.ScaleKernel:
    """``ScaleKernel`` over an RBF or Matern base kernel (one lengthscale per input if ``ard``),
    with independent hyperparameters per ``batch_shape`` entry."""
    if kernel not in KERNELS:
        raise ConfigError(f"gp.kernel: unknown kernel {kernel!r}; allowed values are {KERNELS}")
    ard_num_dims = n_dims if ard else None
    if kernel == "rbf":
        base = gpytorch.kernels.RBFKernel(ard_num_dims=ard_num_dims, batch_shape=batch_shape)
    else:
        base = gpytorch.kernels.MaternKernel(
            nu=_MATERN_NU[kernel], ard_num_dims=ard_num_dims, batch_shape=batch_shape
        )
    return gpytorch.kernels.ScaleKernel(base, batch_shape=batch_shape)


class PsiGP(gpytorch.models.ApproximateGP):
    """Sparse variational GP for the latent function f of a probit classifier p = Phi(f).

    Args:
        inducing_points: ``M x d`` initial inducing locations in normalised input space, or
            ``b x M x d`` for ``b`` independent GPs trained side by side (a batch; see
            :func:`surrogate.gp.training.fit_classifiers`).
        kernel: one of :data:`KERNELS`.
        ard: one lengthscale per input column (m and L vary on different scales).
        learn_inducing: optimise the inducing locations together with the hyperparameters.
        natural: use a ``NaturalVariationalDistribution`` (to be trained with
            ``gpytorch.optim.NGD``) instead of a ``CholeskyVariationalDistribution``.
        mean: one of :data:`MEANS`, the prior mean of f.
    """

    def __init__(
        self,
        inducing_points: Tensor,
        kernel: str = "rbf",
        ard: bool = True,
        learn_inducing: bool = True,
        natural: bool = False,
        mean: str = DEFAULT_MEAN,
    ) -> None:
        if inducing_points.dim() not in (2, 3) or inducing_points.shape[-2] < 1:
            raise ConfigError(
                f"gp.n_inducing: inducing points must be a non-empty (M, d) tensor, "
                f"got shape {tuple(inducing_points.shape)}"
            )
        if mean not in MEANS:
            raise ConfigError(f"gp.mean: unknown mean {mean!r}; allowed values are {MEANS}")
        batch = inducing_points.shape[:-2]
        # Validate before building anything so the error names the setting, not a gpytorch class.
        covar_module = make_kernel(kernel, ard, n_dims=inducing_points.shape[-1], batch_shape=batch)
        n_inducing = inducing_points.shape[-2]
        if natural:
            variational_distribution = gpytorch.variational.NaturalVariationalDistribution(
                n_inducing, batch_shape=batch
            )
        else:
            variational_distribution = gpytorch.variational.CholeskyVariationalDistribution(
                n_inducing, batch_shape=batch
            )
        strategy = gpytorch.variational.VariationalStrategy(
            self,
            inducing_points,
            variational_distribution,
            learn_inducing_locations=learn_inducing,
        )
        super().__init__(strategy)
        self.kernel_name = kernel
        self.ard = ard
        self.natural = natural
        self.mean_name = mean
        self.mean_module: gpytorch.means.Mean = (
            gpytorch.means.ConstantMean(batch_shape=batch)
            if mean == DEFAULT_MEAN
            else gpytorch.means.LinearMean(inducing_points.shape[-1], batch_shape=batch)
        )
        self.covar_module = covar_module

    def forward(self, x: Tensor) -> gpytorch.distributions.MultivariateNormal:
        """The GP prior over f at ``x`` (normalised inputs)."""
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))
