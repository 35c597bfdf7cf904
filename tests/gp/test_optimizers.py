"""Optimisers of the batched binned fit other than Adam (surrogate/gp/optimizers.py), scored
as scripts/bench_fit.py scores them (surrogate/benchmarks/fit.py)."""

from __future__ import annotations

import pytest
import torch

from surrogate.benchmarks.fit import Method, fit_problems, psi_sd, score
from surrogate.gp.optimizers import natural_step
from surrogate.gp.training import GPSettings

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_natural_step_scales_each_gp_by_its_own_data() -> None:
    # the batched loss is per point: GP i's natural step needs lr * n_i times its gradient
    vec = torch.zeros(3, 4, requires_grad=True)
    mat = torch.zeros(3, 4, 4, requires_grad=True)
    vec.grad = torch.ones(3, 4)
    mat.grad = torch.ones(3, 4, 4)
    n = torch.tensor([10.0, 100.0, 1000.0])
    natural_step([vec, mat], n, lr=0.5)
    assert torch.equal(vec.detach(), -0.5 * n.reshape(3, 1).expand(3, 4))
    assert torch.equal(mat.detach(), -0.5 * n.reshape(3, 1, 1).expand(3, 4, 4))


def test_psi_sd_matches_monte_carlo() -> None:
    gen = torch.Generator().manual_seed(0)
    mu = torch.tensor([-2.0, 0.0, 0.7, 3.0], dtype=torch.float64)
    var = torch.tensor([0.5, 0.01, 2.0, 1.0], dtype=torch.float64)
    draws = 200_000
    f = mu + var.sqrt() * torch.randn(draws, 4, generator=gen, dtype=torch.float64)
    psi = torch.special.ndtr(f)
    sd_mc = psi.std(0)
    # the sample sd's standard error, sd sqrt((kurtosis - 1) / 4n) (psi is skewed where mu is
    # far from 0): 5 of them bound it with a false alarm rate of ~1e-6 per entry
    kurtosis = ((psi - psi.mean(0)) ** 4).mean(0) / sd_mc**4
    tol = 5 * sd_mc * ((kurtosis - 1) / (4 * draws)).sqrt()
    assert torch.all((psi_sd(mu, var) - sd_mc).abs() < tol)


def _problems() -> tuple[list[tuple[torch.Tensor, ...]], list[float]]:
    """Three one-input classification problems (probit steps, one with weighted labels)."""
    gen = torch.Generator().manual_seed(0)
    problems = []
    for i in range(3):
        x = 4 * torch.rand(5000, 1, generator=gen)
        p = torch.special.ndtr(x[:, 0] - 2 + 0.3 * i)
        problems.append((x, p, torch.bernoulli(p, generator=gen)))
    return problems, [1.0, 5.0, 1.0]


SMALL = GPSettings(kernel="matern52", n_inducing=16, bins=50)


@pytest.fixture(scope="module")
def reference() -> list:
    problems, weights = _problems()
    return fit_problems(problems, weights, SMALL, Method("adam", 1000))[0]


@pytest.mark.parametrize("method", [Method("lbfgs", 50), Method("ngd", 50, 0.5)])
def test_other_optimizers_match_adam_within_the_posterior_sd(reference, method) -> None:
    # on a small well-posed problem both reach Adam's 1,000 steps within its posterior sd of
    # psi at every occupied bin, with 20x fewer steps
    problems, weights = _problems()
    fitted = fit_problems(problems, weights, SMALL, method)[0]
    result = score(fitted, reference, problems, weights, SMALL)
    assert result["equal"], result


def test_too_few_steps_are_not_equal(reference) -> None:
    # the criterion can fail: two L-BFGS iterations leave psi several sd off
    problems, weights = _problems()
    fitted = fit_problems(problems, weights, SMALL, Method("lbfgs", 2))[0]
    result = score(fitted, reference, problems, weights, SMALL)
    assert not result["equal"] and result["gps_unequal"] >= 1


def test_a_diverging_natural_step_is_a_numerical_error() -> None:
    from surrogate.errors import NumericalError

    problems, weights = _problems()
    heavy = [1000.0, 1000.0, 1000.0]  # a step of lr 1e3 overshoots the positive-definite cone
    with pytest.raises(NumericalError, match="ngd 3 lr=1000 diverged"):
        fit_problems(problems, heavy, SMALL, Method("ngd", 3, 1000.0))
    assert weights  # the problems themselves are fine (the reference fits them)


def test_gp_optimizer_lbfgs_through_the_fit_matches_adam(reference) -> None:
    # gp.optimizer=lbfgs runs the same batched binned fit as train does (fit_classifiers), and
    # lands on Adam's 1,000 steps within its posterior sd, in at most 50 iterations
    from surrogate.gp.training import fit_classifiers

    problems, weights = _problems()
    settings = GPSettings(kernel="matern52", n_inducing=16, bins=50, epochs=50,
                          optimizer="lbfgs")  # fmt: skip
    fitted = fit_classifiers(problems, settings, progress=False, weights=weights)
    assert all(0 < len(f.history) <= 50 * 25 for f in fitted)  # evaluations, line search incl.
    result = score(fitted, reference, problems, weights, SMALL)
    assert result["equal"], result
    # one classifier alone takes the same route (a batch of one; its line search is its own,
    # so it lands near, not on, the batch's fit): equal to Adam's within the sd too
    from surrogate.gp.training import fit_classifier

    x, y, outcomes = problems[1]
    one = fit_classifier(x, y, settings, progress=False, outcomes=outcomes, weight=weights[1])
    alone = score([one], reference[1:2], problems[1:2], weights[1:2], SMALL)
    assert alone["equal"], alone


@pytest.mark.parametrize(
    ("values", "match"),
    [
        ({"optimizer": "sgd"}, "gp.optimizer: unknown optimizer 'sgd'"),
        ({"optimizer": "lbfgs"}, "gp.optimizer=lbfgs fits the batched binned GP only"),
        ({"optimizer": "lbfgs", "bins": 10, "natural_gradient": True}, "takes no natural gradient"),
    ],
)
def test_a_bad_gp_optimizer_is_refused_with_its_fix(values, match) -> None:
    from surrogate.errors import ConfigError

    with pytest.raises(ConfigError, match=match):
        GPSettings.from_config(values)
    # the fix the message names passes
    GPSettings.from_config({**values, "optimizer": "adam"})


def test_the_default_optimizer_keeps_every_fit_identity() -> None:
    # fits made before gp.optimizer keep their bytes and directories; lbfgs is a new identity
    from surrogate.kinds import chain_kind

    assert "optimizer" not in GPSettings().to_dict()
    assert GPSettings(bins=10, optimizer="lbfgs").to_dict()["optimizer"] == "lbfgs"
    kind = chain_kind()  # the two-state chain
    base = {"kernel": "rbf", "bins": 10}
    assert kind.fit_identity({**base, "optimizer": "adam"}) == kind.fit_identity(base)
    assert kind.fit_identity({**base, "optimizer": "lbfgs"}) != kind.fit_identity(base)
