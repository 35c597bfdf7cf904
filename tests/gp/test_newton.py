"""The binned fit with q(u) solved by Newton's method (surrogate/gp/newton.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from surrogate.errors import ConfigError
from surrogate.gp.newton import _Q, _elbo, _Prior, _whitened_prior, expected_log_lik, solve_q
from surrogate.gp.training import GPSettings, fit_classifier, fit_classifiers

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_expected_log_lik_derivatives_match_autograd() -> None:
    # g = dE/dm and lam = -d2E/dm2 (the Newton step's), and Price's theorem dE/dv = -lam / 2
    mean = torch.tensor([-3.0, -0.5, 0.0, 1.2, 4.0], dtype=F64, requires_grad=True)
    var = torch.tensor([0.3, 2.0, 1e-6, 0.7, 1.5], dtype=F64, requires_grad=True)
    n = torch.tensor([10.0, 3.0, 1000.0, 1.0, 50.0], dtype=F64)
    k = torch.tensor([0.5, 2.0, 400.0, 1.0, 49.9], dtype=F64)
    value, g, lam = expected_log_lik(mean, var, n, k, derivatives=True)
    d_mean, d_var = torch.autograd.grad(value.sum(), (mean, var), create_graph=True)
    (d2_mean,) = torch.autograd.grad(d_mean.sum(), mean)
    torch.testing.assert_close(g, d_mean.detach(), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(lam, -d2_mean, rtol=1e-9, atol=1e-9)
    # quadrature of the same integrand: Price holds to the quadrature's error
    torch.testing.assert_close(d_var.detach(), -lam / 2, rtol=1e-4, atol=1e-6)
    assert bool((lam > 0).all())  # log-concave: the Newton step's curvature is positive


def _tiny_problem() -> tuple[_Prior, tuple[torch.Tensor, torch.Tensor]]:
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(1, 3, 12, generator=gen, dtype=F64) * 0.8
    prior = _Prior(a, torch.randn(1, 12, generator=gen, dtype=F64) * 0.3,
                   torch.full((1, 12), 0.05, dtype=F64))  # fmt: skip
    n = torch.randint(1, 40, (1, 12), generator=gen).to(F64)
    k = torch.floor(n * torch.rand(1, 12, generator=gen, dtype=F64))
    return prior, (n, k)


def test_solve_q_reaches_the_elbo_optimum_found_by_scipy() -> None:
    # an independent optimiser (BFGS over the mean and a Cholesky factor of S) on the same
    # ELBO reaches what the damped Newton solve reaches, from the prior
    from surrogate.gp.newton import _Bins

    prior, (n, k) = _tiny_problem()
    bins = _Bins(n, k, n.sum(-1))
    q, elbo, steps = solve_q(prior, bins)
    assert steps < 30

    def negative(theta: np.ndarray) -> float:
        t = torch.tensor(theta, dtype=F64)
        lower = torch.zeros(3, 3, dtype=F64)
        lower[tuple(torch.tril_indices(3, 3))] = t[3:]
        covariance = lower @ lower.T + 1e-12 * torch.eye(3, dtype=F64)
        precision_chol = torch.linalg.cholesky(torch.linalg.inv(covariance))
        return -float(_elbo(prior, _Q(t[:3].unsqueeze(0), precision_chol.unsqueeze(0)), bins))

    start = np.concatenate([np.zeros(3), np.eye(3)[np.tril_indices(3)]])
    best = minimize(negative, start, method="BFGS", options={"gtol": 1e-10, "maxiter": 2000})
    assert float(elbo) == pytest.approx(-best.fun, abs=1e-7)
    lower = np.zeros((3, 3))
    lower[np.tril_indices(3)] = best.x[3:]
    torch.testing.assert_close(q.mean[0], torch.tensor(best.x[:3], dtype=F64), atol=1e-4, rtol=0)
    covariance = torch.cholesky_inverse(q.chol[0])
    torch.testing.assert_close(covariance, torch.tensor(lower @ lower.T), atol=1e-4, rtol=0)


def _problems() -> tuple[list[tuple[torch.Tensor, ...]], list[float]]:
    gen = torch.Generator().manual_seed(0)
    problems = []
    for i in range(3):
        x = 4 * torch.rand(5000, 1, generator=gen)
        p = torch.special.ndtr(torch.sin(2 * x[:, 0] + i) - 0.5)
        problems.append((x, p, torch.bernoulli(p, generator=gen)))
    return problems, [1.0, 20.0, 1.0]  # expected labels, one weighted as many draws


SETTINGS = GPSettings(kernel="matern52", n_inducing=16, bins=50, optimizer="newton", epochs=200)


def _exact_elbo(fitted, problem, weight) -> float:
    """A fitted classifier's binned ELBO per draw, by the exact objective the Newton fit
    maximises (its q as stored, float64)."""
    from surrogate.gp.binned import bin_inputs, weighted_bins
    from surrogate.gp.newton import _Bins
    from surrogate.gp.training import _prepare

    prep = _prepare(problem[0], problem[1], SETTINGS, torch.device("cpu"), problem[2])
    z, n, k = weighted_bins(bin_inputs(prep.z_train, prep.y_train, SETTINGS.bins), weight)
    model = fitted.model
    with torch.no_grad():
        a, mean, var = _whitened_prior(model, z)
        prior = _Prior(a, mean, var - (a * a).sum(-2))
        dist = model.variational_strategy._variational_distribution
        covariance = (dist.chol_variational_covar @ dist.chol_variational_covar.mT).double()
        precision_chol = torch.linalg.cholesky(torch.linalg.inv(covariance))
        q = _Q(dist.variational_mean.double().unsqueeze(0), precision_chol.unsqueeze(0))
        bins = _Bins(n.double().unsqueeze(0), k.double().unsqueeze(0), n.double().sum())
        return float(_elbo(_Prior(prior.a.unsqueeze(0), prior.mean.unsqueeze(0),
                                  prior.var.unsqueeze(0)), q, bins)) / float(n.sum())  # fmt: skip


def test_newton_fit_is_stable_in_its_steps_and_beats_adam_on_its_objective() -> None:
    from surrogate.benchmarks.fit import psi_sd

    problems, weights = _problems()
    newton = fit_classifiers(problems, SETTINGS, progress=False, weights=weights)
    # twice the hyperparameter steps moves psi where the data live by less than its own
    # posterior sd (Adam alone: up to 32 sd between 1,000 and 2,000 steps on the quick
    # start's problems, docs/performance.md), because q is exact at whatever they reach
    longer = fit_classifiers(problems, GPSettings(**{**SETTINGS.to_dict(), "epochs": 400}),
                             progress=False, weights=weights)  # fmt: skip
    adam = fit_classifiers(problems, GPSettings(**{**SETTINGS.to_dict(), "optimizer": "adam",
                                                   "epochs": 1000}),
                           progress=False, weights=weights)  # fmt: skip
    x = torch.linspace(0.1, 3.9, 50).unsqueeze(1)
    for i, (problem, w) in enumerate(zip(problems, weights, strict=True)):
        assert len(newton[i].history) == 201  # a loss per step and q*'s at the end
        mu, var = longer[i].latent(x)
        delta = (newton[i].predict_proba(x) - longer[i].predict_proba(x)).abs().double()
        assert bool((delta < psi_sd(mu, var)).all()), (i, float((delta / psi_sd(mu, var)).max()))
        ours, theirs = _exact_elbo(newton[i], problem, w), _exact_elbo(adam[i], problem, w)
        assert ours >= theirs - 1e-7, (i, ours, theirs)
        assert newton[i].validation is not None  # held-out metrics, as every fit


def test_one_classifier_alone_takes_the_batched_newton_route() -> None:
    problems, weights = _problems()
    x, y, outcomes = problems[1]
    one = fit_classifier(x, y, SETTINGS, progress=False, outcomes=outcomes, weight=weights[1])
    batch = fit_classifiers(problems, SETTINGS, progress=False, weights=weights)[1]
    grid = torch.linspace(0.1, 3.9, 50).unsqueeze(1)
    # Adam steps each GP of a batch as it would alone, and q* is exact per GP
    torch.testing.assert_close(one.predict_proba(grid), batch.predict_proba(grid),
                               atol=1e-4, rtol=0)  # fmt: skip


@pytest.mark.parametrize(
    ("values", "match"),
    [
        ({"optimizer": "newton"}, "gp.optimizer=newton fits the batched binned GP only"),
    ],
)
def test_newton_without_bins_is_refused_with_its_fix(values, match) -> None:
    with pytest.raises(ConfigError, match=match):
        GPSettings.from_config(values)
    GPSettings.from_config({**values, "optimizer": "adam"})


def test_newton_overrides_a_recipes_natural_gradient() -> None:
    # the clock's recipe asks for natural gradients; gp.optimizer=newton solves q(u) exactly
    # instead and stores it in a Cholesky q (what predictions read)
    from surrogate.gp.settings import psi_gp

    settings = GPSettings(bins=10, natural_gradient=True, optimizer="newton", epochs=20)
    assert not psi_gp(torch.zeros(4, 1), settings).natural
    problems, weights = _problems()
    fitted = fit_classifiers(problems[:2], settings, progress=False, weights=weights[:2])
    assert len(fitted[0].history) == 21


def test_a_failing_newton_fit_is_a_numerical_error_naming_its_fix(monkeypatch) -> None:
    # a Cholesky that breaks (here forced) is the fit's NumericalError with the restored
    # model attached and the setting to lower, not a bare torch error
    import surrogate.gp.newton as newton
    from surrogate.errors import NumericalError

    def broken(*args, **kwargs):
        raise torch.linalg.LinAlgError("linalg.cholesky: not positive-definite")

    monkeypatch.setattr(newton, "solve_q", broken)
    problems, weights = _problems()
    with pytest.raises(NumericalError, match="Try a smaller gp.lr") as info:
        fit_classifiers(problems[:2], SETTINGS, progress=False, weights=weights[:2])
    assert info.value.partial is not None


def test_newton_is_its_own_fit_identity() -> None:
    from surrogate.kinds import chain_kind

    assert GPSettings(bins=10, optimizer="newton").to_dict()["optimizer"] == "newton"
    base = {"kernel": "rbf", "bins": 10}
    kind = chain_kind()
    assert kind.fit_identity({**base, "optimizer": "newton"}) != kind.fit_identity(base)
