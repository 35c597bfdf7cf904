"""The binned SVGP fit with q(u) solved exactly (``gp.optimizer=newton``).

For fixed hyperparameters the binned ELBO is concave in q(u) (the probit likelihood is
log-concave), so its optimum can be found by Newton's method instead of being chased by
first-order steps alongside the hyperparameters. In whitened coordinates (q(v) = N(m, S),
f(x_b) = mu_b + a_b^T v, a_b = L^{-1} k_Z(x_b), K_ZZ + jitter I = L L^T) and with E_b(m_b, s_b)
the expected log-likelihood of bin b's ``k_b`` successes in ``n_b`` draws at the marginal
mean m_b and variance s_b of f(x_b):

    S^{-1} = I + A diag(lam) A^T,   lam_b = -d^2 E_b / d m_b^2 (= -2 dE_b/ds_b, Price)
    m      = m + S (A g - m),        g_b   =  d E_b / d m_b

is one Newton step on m with the exact Hessian and the fixed point for S (the variational
conjugate-computation update at step 1, Khan & Lin 2017). Each step is damped (natural
parameters interpolated) until the ELBO does not fall, and iterated to convergence.

The hyperparameters (kernel scales, the prior mean, the inducing locations if learned) then
see the collapsed objective ELBO(theta, q*(theta)): by the envelope theorem its gradient is
the partial one at q* held fixed (the KL term of a whitened q does not depend on theta), and
Adam steps on it, each after one Newton step on q from the last (which tracks q* as theta
moves: Adam needs no exact gradient), with q* solved to convergence at the end. Not L-BFGS: where data
are dense the collapsed objective is nearly flat in the hyperparameters and badly scaled
(q* absorbs what they would change), and L-BFGS's steps crawled (the toggle switch's 8M
rows: kernel scales moved by 1e-5 in 250 evaluations, then a NaN step). What the fit
returns is q* exactly at the hyperparameters the last step reached, so psi where data are
dense does not depend on how far the optimiser went (measured on the toggle switch:
``docs/performance.md``, "Faster fits: measured"): the fit-to-fit spread left is the data's.

Hand-written, and why: gpytorch's NGD at step 1 is this update for q(u) alone, but through its
natural-parameter parametrisation in float32 it broke positive definiteness in its second step
on the quick start's problems (measured, docs/performance.md); here the update is solved in
float64 by Cholesky factors of S^{-1}, which stay positive definite for any lam >= 0. The
expected log-likelihood uses the exact log Phi (``torch.special.log_ndtr``) and 20-node
Gauss-Hermite quadrature in float64, so this is the exact binned ELBO, not the float32
approximation the Adam fit optimises (``surrogate.gp.probit``): the two optima differ by that
approximation. The kernel matrices come from the model's own modules, jitter and float64
Cholesky (as gpytorch's ``VariationalStrategy`` in eval mode builds them), so the predictive
the fitted model gives is the one optimised.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from surrogate.gp.model import PsiGP
from surrogate.gp.optimizers import _record

#: Gauss-Hermite nodes of the expected log-likelihood (gpytorch's quadrature uses 20)
GH_NODES = 20
#: the inner Newton solve stops when no GP's ELBO per draw rises by more than this
INNER_TOLERANCE = 1e-12
#: at most this many Newton steps per inner solve (a warm start needs a few)
INNER_STEPS = 100
#: damping halvings tried before a Newton step is given up as converged
MAX_HALVINGS = 30


@dataclass
class _Bins:
    """One batch's binned data in float64 (``b x L``)."""

    n: Tensor
    k: Tensor
    total: Tensor  # b: draws per GP (the ELBO's per-point divisor)


@dataclass
class _Prior:
    """The GP prior at the bins, whitened (float64): a_b columns, prior mean, prior variance."""

    a: Tensor  # b x M x L
    mean: Tensor  # b x L
    var: Tensor  # b x L: k(x, x) + jitter - a^T a


@dataclass
class _Q:
    """q(v) by its mean and the Cholesky factor of its precision S^{-1} = chol chol^T."""

    mean: Tensor  # b x M
    chol: Tensor  # b x M x M


def _gauss_hermite(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    x, w = np.polynomial.hermite.hermgauss(GH_NODES)
    nodes = torch.tensor(x * math.sqrt(2.0), dtype=dtype, device=device)
    weights = torch.tensor(w / math.sqrt(math.pi), dtype=dtype, device=device)
    return nodes, weights


def expected_log_lik(
    mean: Tensor, var: Tensor, n: Tensor, k: Tensor, derivatives: bool = False
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """E_{f ~ N(mean, var)}[k log Phi(f) + (n - k) log Phi(-f)] per bin by Gauss-Hermite
    quadrature, and (``derivatives``) its gradient g in ``mean`` and its curvature
    ``lam = -d^2 E / d mean^2 >= 0``.

    Args:
        mean, var, n, k: ``... x L`` (``var > 0``).

    Example:
        >>> e, g, lam = expected_log_lik(*(torch.tensor([x], dtype=torch.float64)
        ...                                for x in (0.0, 1e-12, 2.0, 1.0)), derivatives=True)
        >>> round(float(e), 6), round(float(g), 6), round(float(lam), 6)
        (-1.386294, 0.0, 1.27324)
    """
    nodes, weights = _gauss_hermite(mean.dtype, mean.device)
    f = mean.unsqueeze(-1) + var.clamp(min=0).sqrt().unsqueeze(-1) * nodes  # ... x L x Q
    n_, k_ = n.unsqueeze(-1), k.unsqueeze(-1)
    log_pos, log_neg = torch.special.log_ndtr(f), torch.special.log_ndtr(-f)
    value = ((k_ * log_pos + (n_ - k_) * log_neg) * weights).sum(-1)
    if not derivatives:
        return value, None, None
    with torch.no_grad():
        log_phi = -0.5 * f * f - 0.5 * math.log(2 * math.pi)
        r_pos = torch.exp(log_phi - log_pos)  # phi(f) / Phi(f)
        r_neg = torch.exp(log_phi - log_neg)  # phi(f) / Phi(-f)
        first = k_ * r_pos - (n_ - k_) * r_neg
        second = -k_ * r_pos * (f + r_pos) - (n_ - k_) * r_neg * (r_neg - f)
        return value, (first * weights).sum(-1), -(second * weights).sum(-1)


def _marginals(prior: _Prior, q: _Q) -> tuple[Tensor, Tensor]:
    """q(f)'s mean and variance at the bins (``b x L``)."""
    mean = prior.mean + (prior.a * q.mean.unsqueeze(-1)).sum(-2)
    s_a = torch.cholesky_solve(prior.a, q.chol)  # S a_b
    var = prior.var + (prior.a * s_a).sum(-2)
    return mean, var


def _kl(q: _Q) -> Tensor:
    """KL(N(m, S) || N(0, I)) per GP, with S^{-1} = chol chol^T."""
    eye = torch.eye(q.chol.shape[-1], dtype=q.chol.dtype, device=q.chol.device)
    inverse = torch.cholesky_solve(eye.expand_as(q.chol), q.chol)
    trace = inverse.diagonal(dim1=-2, dim2=-1).sum(-1)
    log_det_precision = 2 * q.chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    m = q.chol.shape[-1]
    return 0.5 * (trace + (q.mean * q.mean).sum(-1) - m + log_det_precision)


def _elbo(prior: _Prior, q: _Q, bins: _Bins) -> Tensor:
    mean, var = _marginals(prior, q)
    return expected_log_lik(mean, var, bins.n, bins.k)[0].sum(-1) - _kl(q)


def solve_q(
    prior: _Prior, bins: _Bins, start: _Q | None = None, max_steps: int = INNER_STEPS
) -> tuple[_Q, Tensor, int]:
    """q*(v) for fixed hyperparameters by at most ``max_steps`` damped Newton steps from
    ``start`` (default the prior, N(0, I)); returns q*, its ELBO per GP (``b``) and the steps
    taken."""
    b, m_dim, _ = prior.a.shape
    eye = torch.eye(m_dim, dtype=prior.a.dtype, device=prior.a.device).expand(b, m_dim, m_dim)
    zeros = torch.zeros(b, m_dim, dtype=prior.a.dtype, device=prior.a.device)
    q = _Q(zeros, eye.clone()) if start is None else start
    mean, var = _marginals(prior, q)
    value, g, lam = expected_log_lik(mean, var, bins.n, bins.k, derivatives=True)
    elbo = value.sum(-1) - _kl(q)
    for step in range(1, max_steps + 1):
        if step > 1:  # the derivatives at the q the last step reached
            mean, var = _marginals(prior, q)
            _, g, lam = expected_log_lik(mean, var, bins.n, bins.k, derivatives=True)
        assert g is not None and lam is not None
        precision = eye + (prior.a * lam.unsqueeze(-2)) @ prior.a.mT
        target_chol = torch.linalg.cholesky(precision)
        gradient = (prior.a @ g.unsqueeze(-1)).squeeze(-1) - q.mean
        target_mean = q.mean + torch.cholesky_solve(gradient.unsqueeze(-1), target_chol).squeeze(-1)
        # natural parameters of the current and the target q: interpolate until the ELBO holds
        old_precision = q.chol @ q.chol.mT
        old_eta = (old_precision @ q.mean.unsqueeze(-1)).squeeze(-1)
        target_eta = (precision @ target_mean.unsqueeze(-1)).squeeze(-1)
        rho = torch.ones(b, dtype=prior.a.dtype, device=prior.a.device)
        accepted = torch.zeros(b, dtype=torch.bool, device=prior.a.device)
        new_q, new_elbo = q, elbo
        for _ in range(MAX_HALVINGS):
            r = rho.reshape(b, 1, 1)
            p_rho = (1 - r) * old_precision + r * precision
            chol_rho = torch.linalg.cholesky(p_rho)
            eta_rho = (1 - rho.unsqueeze(-1)) * old_eta + rho.unsqueeze(-1) * target_eta
            mean_rho = torch.cholesky_solve(eta_rho.unsqueeze(-1), chol_rho).squeeze(-1)
            trial = _Q(mean_rho, chol_rho)
            trial_elbo = _elbo(prior, trial, bins)
            ok = trial_elbo >= elbo - 1e-13 * elbo.abs()
            take = ok & ~accepted
            if bool(take.any()):
                w = take.reshape(b, 1)
                new_q = _Q(torch.where(w, trial.mean, new_q.mean),
                           torch.where(w.unsqueeze(-1), trial.chol, new_q.chol))  # fmt: skip
                new_elbo = torch.where(take, trial_elbo, new_elbo)
            accepted |= ok
            if bool(accepted.all()):
                break
            rho = torch.where(accepted, rho, rho / 2)
        gain = (new_elbo - elbo) / bins.total
        q, elbo = new_q, new_elbo
        if bool((gain <= INNER_TOLERANCE).all()):
            return q, elbo, step
    return q, elbo, max_steps


def _whitened_prior(model: PsiGP, z_b: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """a (``b x M x L``, float64), the prior mean and k(x, x) + jitter at the bins (``b x L``),
    differentiable in the model's hyperparameters, built as gpytorch's eval-mode
    ``VariationalStrategy`` builds them (jitter of the model's dtype, float64 Cholesky)."""
    strategy = model.variational_strategy
    inducing = strategy.inducing_points
    jitter = strategy.jitter_val
    k_zz = model.covar_module(inducing).to_dense()
    k_zz = k_zz + jitter * torch.eye(k_zz.shape[-1], dtype=k_zz.dtype, device=k_zz.device)
    k_zx = model.covar_module(inducing, z_b).to_dense()
    k_xx = model.covar_module(z_b, diag=True) + jitter
    chol = torch.linalg.cholesky(k_zz.double())
    a = torch.linalg.solve_triangular(chol, k_zx.double(), upper=False)
    return a, model.mean_module(z_b).double(), k_xx.double()


def fit_newton(
    model: PsiGP,
    z_b: Tensor,
    n_b: Tensor,
    k_b: Tensor,
    steps: int,
    lr: float,
    histories: Sequence[list[float]],
) -> None:
    """Fit the batched ``model`` (a Cholesky variational distribution) to binned data: q(u)
    by Newton's method at every hyperparameter setting, the hyperparameters by ``steps`` Adam
    steps of ``lr`` on the collapsed ELBO; writes q* at the final hyperparameters into the
    model's variational distribution (each GP's negative ELBO per draw appended to
    ``histories`` at every step).

    Args:
        model: a batched :class:`PsiGP` (``b`` GPs) with ``natural=False``.
        z_b: ``b x L x d`` bins' mean inputs (normalised).
        n_b, k_b: ``b x L`` draws and successes per bin (padded bins: 0 and 0).
        steps: Adam steps on the hyperparameters (0: q* at the initial ones).
        lr: Adam's learning rate.
        histories: ``b`` lists.
    """
    bins = _Bins(n_b.double(), k_b.double(), n_b.double().sum(-1))
    hyper = [p for name, p in model.named_parameters()
             if "variational_distribution" not in name and p.requires_grad]  # fmt: skip
    q: _Q | None = None  # warm start: the last step's q* (whitened: valid at any theta)
    optimizer = torch.optim.Adam(hyper, lr=lr)
    for _ in range(steps):
        optimizer.zero_grad(set_to_none=True)
        prior = _prior(model, z_b)  # built once: the Newton step reads it detached
        fixed = _Prior(prior.a.detach(), prior.mean.detach(), prior.var.detach())
        with torch.no_grad():  # one Newton step tracks q* as theta moves; solved at the end
            q = solve_q(fixed, bins, q, max_steps=1)[0]
        losses = -_elbo(prior, q, bins) / bins.total
        _record(losses, histories)
        losses.sum().backward()
        optimizer.step()
    with torch.no_grad():
        q, elbo, _ = solve_q(_prior(model, z_b), bins, q)
        _record(-elbo / bins.total, histories)
        _write_q(model, q)


def _prior(model: PsiGP, z_b: Tensor) -> _Prior:
    a, mean, var = _whitened_prior(model, z_b)
    return _Prior(a, mean, var - (a * a).sum(-2))


def _write_q(model: PsiGP, q: _Q) -> None:
    """Store q(v) = N(m, S) in the model's Cholesky variational distribution (float32):
    S's lower Cholesky factor from the precision's (S = chol^{-T} chol^{-1})."""
    dist = model.variational_strategy._variational_distribution
    eye = torch.eye(q.chol.shape[-1], dtype=q.chol.dtype, device=q.chol.device)
    covariance = torch.cholesky_solve(eye.expand_as(q.chol), q.chol)
    covariance = 0.5 * (covariance + covariance.mT)
    lower = torch.linalg.cholesky(covariance)
    dist.variational_mean.copy_(q.mean.to(dist.variational_mean.dtype))
    dist.chol_variational_covar.copy_(lower.to(dist.chol_variational_covar.dtype))
    model.variational_strategy.variational_params_initialized.fill_(1)


__all__ = ["expected_log_lik", "fit_newton", "solve_q"]
