"""Training: settings validation, bad inputs, numerical guard and recovery of a known surface."""

from __future__ import annotations

import math
import re

import gpytorch
import pytest
import torch
from torch import Tensor

from surrogate.errors import ConfigError, NumericalError
from surrogate.gp import (
    KERNELS,
    GPSettings,
    PsiGP,
    classification_metrics,
    fit_classifier,
)
from surrogate.gp.fitted import FittedClassifier

M_BOX = (1.0, 3.5)
L_BOX = (0.0, 0.1)
W = 0.1  # switch width in m: steep, like the real psi surfaces


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def p_true(x: Tensor) -> Tensor:
    """Logistic switch at the adapted level m0(L) = 2.2 + 10 L."""
    return torch.sigmoid((2.2 + 10.0 * x[:, 1] - x[:, 0]) / W)


def sample(n: int, gen: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """Uniform inputs on the box, labels ~ Bernoulli(p_true)."""
    m = M_BOX[0] + (M_BOX[1] - M_BOX[0]) * torch.rand(n, generator=gen, dtype=torch.float64)
    L = L_BOX[0] + (L_BOX[1] - L_BOX[0]) * torch.rand(n, generator=gen, dtype=torch.float64)
    x = torch.stack([m, L], dim=1)
    p = p_true(x)
    return x, torch.bernoulli(p, generator=gen), p


def grid(n: int = 50) -> Tensor:
    """Regular n x n test grid over the box (float64)."""
    m = torch.linspace(*M_BOX, n, dtype=torch.float64)
    L = torch.linspace(*L_BOX, n, dtype=torch.float64)
    mm, ll = torch.meshgrid(m, L, indexing="ij")
    return torch.stack([mm.reshape(-1), ll.reshape(-1)], dim=1)


SMALL = {"n_inducing": 25, "epochs": 20, "batch_size": 500, "lr": 0.05}


@pytest.fixture(scope="module")
def trained() -> tuple:
    gen = torch.Generator().manual_seed(0)
    x, y, _ = sample(3000, gen)
    fitted = fit_classifier(x, y, GPSettings(**SMALL), progress=False)
    return fitted, gen


# ----------------------------------------------------------------------------------------------
# statistical recovery


def test_recovers_known_surface(trained: tuple) -> None:
    fitted, _ = trained
    xg = grid()
    pg = p_true(xg)
    err = (fitted.predict_proba(xg).double() - pg).abs().mean().item()
    const_err = (pg - pg.mean()).abs().mean().item()  # best constant in mean-square sense: ~0.39
    # Noise floor: a smoother that resolves the switch pools k ~ 50-100 of the 3000 points, so
    # its s.e. is <= 0.5/sqrt(50) ~ 0.07 inside the band |m - m0| < 2w (16% of the box) and ~0
    # where p is near 0 or 1 (binomial variance p(1-p) vanishes): mean |error| ~ 0.16 * 0.8 *
    # 0.07 ~ 0.01. We allow 0.05 (5x) for smoothing bias at the steep switch; a model that did
    # not learn the switch position sits near the constant's 0.39.
    assert err < 0.05, f"mean |p_hat - p_true| = {err:.4f}"
    assert err < 0.15 * const_err


def test_held_out_brier_beats_base_rate(trained: tuple) -> None:
    fitted, gen = trained
    x_test, y_test, p_test = sample(4000, gen)
    met = classification_metrics(fitted.predict_proba(x_test), y_test)
    # The gain over the base-rate predictor must exceed 5 of its own sampling s.e.: a classifier
    # without skill has gain <= 0 in expectation, so this fails by chance with p < 3e-7.
    assert met["brier_gain"] > 5 * met["brier_gain_se"], met
    # Excess Brier over the Bayes-optimal predictor p_true estimates E[(p_hat - p)^2]; with the
    # grid error above (< 0.05 mean, max |err| <= 1) it cannot exceed 0.05.
    oracle = ((p_test - y_test) ** 2).mean().item()
    assert met["brier"] - oracle < 0.05 * 1.0
    # Validation metrics come from the held-out 20% split.
    assert fitted.validation is not None
    assert fitted.validation["n"] == fitted.n_val == 600
    assert fitted.n_train == 2400


def test_history_decreases(trained: tuple) -> None:
    fitted, _ = trained
    assert len(fitted.history) == SMALL["epochs"]
    # Negative ELBO per point starts near log 2 ~ 0.69 (uninformed) and must fall well below:
    # the Bayes-optimal log loss on this surface is ~0.13.
    assert fitted.history[-1] < 0.5 * fitted.history[0]


# ----------------------------------------------------------------------------------------------
# determinism and options


def tiny_data(n: int = 400, seed: int = 1) -> tuple[Tensor, Tensor]:
    x, y, _ = sample(n, torch.Generator().manual_seed(seed))
    return x, y


TINY = {"n_inducing": 8, "epochs": 3, "batch_size": 100}


def test_same_seed_same_model() -> None:
    x, y = tiny_data()
    a = fit_classifier(x, y, GPSettings(**TINY, seed=3), progress=False)
    b = fit_classifier(x, y, GPSettings(**TINY, seed=3), progress=False)
    c = fit_classifier(x, y, GPSettings(**TINY, seed=4), progress=False)
    xg = grid(10)
    assert torch.equal(a.predict_proba(xg), b.predict_proba(xg))
    assert not torch.equal(a.predict_proba(xg), c.predict_proba(xg))


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("ard", [True, False])
def test_kernels_build_and_predict(kernel: str, ard: bool) -> None:
    x, y = tiny_data()
    fitted = fit_classifier(x, y, GPSettings(**TINY, kernel=kernel, ard=ard), progress=False)
    lengthscale = fitted.model.covar_module.base_kernel.lengthscale
    assert lengthscale.shape[-1] == (2 if ard else 1)
    p = fitted.predict_proba(grid(5))
    assert p.shape == (25,)
    assert bool(((p >= 0) & (p <= 1)).all())


@pytest.mark.parametrize("d", [1, 3, 5])
@pytest.mark.parametrize("ard", [True, False])
def test_any_number_of_inputs(d: int, ard: bool) -> None:
    """x of shape (n, d) for any d >= 1: one lengthscale per column with ARD, inducing points
    and normaliser in d dimensions, predictions for (n, d) queries."""
    gen = torch.Generator().manual_seed(d)
    x = torch.rand(600, d, generator=gen, dtype=torch.float64) * torch.arange(1, d + 1)
    p = torch.sigmoid(4.0 * (x[:, 0] - 0.5))  # depends on the first column only
    y = torch.bernoulli(p, generator=gen)
    settings = GPSettings(n_inducing=12, epochs=8, batch_size=200, lr=0.1, ard=ard)
    fitted = fit_classifier(x, y, settings, progress=False)
    lengthscale = fitted.model.covar_module.base_kernel.lengthscale
    assert lengthscale.shape[-1] == (d if ard else 1)
    assert fitted.model.variational_strategy.inducing_points.shape == (12, d)
    assert fitted.normaliser.mean.shape == fitted.normaliser.std.shape == (d,)
    q = torch.rand(50, d, generator=gen) * torch.arange(1, d + 1)
    out = fitted.predict_proba(q)
    assert out.shape == (50,) and bool(((out >= 0) & (out <= 1)).all())
    mean, var = fitted.latent(q)
    assert mean.shape == var.shape == (50,) and bool((var > 0).all())
    # it learned the trend along the first input
    lo, hi = q.clone(), q.clone()
    lo[:, 0], hi[:, 0] = 0.0, 1.0
    assert (fitted.predict_proba(hi) - fitted.predict_proba(lo)).mean() > 0.2
    # its own rows checked along every input (unbinned: at most 2**16 bins in all, not 50**d)
    assert fitted.own_rows is not None and {g["axis"] for g in fitted.own_rows["groups"]} == set(
        range(d))  # fmt: skip


def test_inputs_must_be_a_matrix() -> None:
    with pytest.raises(ValueError, match=r"\(n, d\)"):
        fit_classifier(torch.rand(100), torch.zeros(100), GPSettings(**TINY), progress=False)
    with pytest.raises(ValueError, match=r"\(n, d\)"):
        fit_classifier(torch.rand(100, 0), torch.zeros(100), GPSettings(**TINY), progress=False)


def test_natural_gradient_trains() -> None:
    x, y = tiny_data(800)
    fitted = fit_classifier(
        x, y, GPSettings(**{**TINY, "epochs": 5}, natural_gradient=True), progress=False
    )
    assert isinstance(
        fitted.model.variational_strategy._variational_distribution,
        gpytorch.variational.NaturalVariationalDistribution,
    )
    assert fitted.history[-1] < fitted.history[0]
    assert fitted.validation is not None and fitted.validation["brier_skill"] > 0


def test_fixed_inducing_points_stay_put() -> None:
    x, y = tiny_data()
    fitted = fit_classifier(x, y, GPSettings(**TINY, learn_inducing=False), progress=False)
    z = fitted.model.variational_strategy.inducing_points
    assert not z.requires_grad
    # They are still the initial subset of normalised training inputs (exact distances: the
    # matmul form of cdist loses ~1e-3 to cancellation).
    zx = fitted.normaliser.transform(x.float())
    dist = torch.cdist(z, zx, compute_mode="donot_use_mm_for_euclid_dist")
    assert bool((dist.min(dim=1).values < 1e-6).all())


def test_no_validation_split() -> None:
    x, y = tiny_data()
    fitted = fit_classifier(x, y, GPSettings(**TINY, validation_fraction=0.0), progress=False)
    assert fitted.validation is None
    assert (fitted.n_train, fitted.n_val) == (400, 0)


# ----------------------------------------------------------------------------------------------
# bad settings and inputs


def test_settings_defaults_match_brief() -> None:
    s = GPSettings()
    assert (s.kernel, s.ard, s.n_inducing, s.epochs, s.batch_size) == ("rbf", True, 100, 40, 1000)
    assert GPSettings.from_config(s.to_dict()) == s
    assert GPSettings.from_config({"lr": 1}).lr == 1.0


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("kernel", "linear"),
        ("n_inducing", 0),
        ("n_inducing", -5),
        ("n_inducing", 2.5),
        ("epochs", 0),
        ("batch_size", True),
        ("lr", 0.0),
        ("lr", float("nan")),
        ("natural_lr", -1.0),
        ("validation_fraction", 1.0),
        ("validation_fraction", -0.1),
        ("ard", "yes"),
        ("seed", -1),
    ],
)
def test_bad_setting_names_key(key: str, value: object) -> None:
    with pytest.raises(ConfigError, match=f"gp\\.{key}"):
        GPSettings.from_config({key: value})


def test_unknown_setting_key() -> None:
    with pytest.raises(ConfigError, match=r"unknown gp setting\(s\) \['n_inducing_points'\]"):
        GPSettings.from_config({"n_inducing_points": 10})


def test_unknown_kernel_in_model_lists_allowed() -> None:
    with pytest.raises(ConfigError, match=r"gp\.kernel.*matern52"):
        PsiGP(torch.zeros(4, 2), kernel="periodic")


def test_too_many_inducing_points() -> None:
    x, y = tiny_data(50)
    with pytest.raises(ConfigError, match=r"gp\.n_inducing"):
        fit_classifier(x, y, GPSettings(n_inducing=100), progress=False)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_inputs(bad: float) -> None:
    x, y = tiny_data()
    x[17, 1] = bad
    with pytest.raises(NumericalError, match="NaN or inf"):
        fit_classifier(x, y, GPSettings(**TINY), progress=False)


def test_bad_labels() -> None:
    x, y = tiny_data()
    y[3] = 2.0
    with pytest.raises(NumericalError, match="labels"):
        fit_classifier(x, y, GPSettings(**TINY), progress=False)


def test_divergence_restores_last_good_state(monkeypatch: pytest.MonkeyPatch) -> None:
    x, y = tiny_data()
    settings = GPSettings(**{**TINY, "epochs": 5})
    n_batches = 4  # 320 training points / batch 100
    calls = {"n": 0}
    original = gpytorch.mlls.VariationalELBO.forward

    def nan_in_epoch_3(self: gpytorch.mlls.VariationalELBO, *args: object, **kw: object) -> Tensor:
        calls["n"] += 1
        out = original(self, *args, **kw)
        # Poison the second minibatch of epoch 3: the loss and the gradients become NaN.
        return out * float("nan") if calls["n"] == 2 * n_batches + 2 else out

    monkeypatch.setattr(gpytorch.mlls.VariationalELBO, "forward", nan_in_epoch_3)
    with pytest.raises(NumericalError, match=r"epoch 3/5.*gp\.lr") as info:
        fit_classifier(x, y, settings, progress=False)
    partial = info.value.partial
    assert len(partial.history) == 2
    for p in partial.model.parameters():
        assert bool(torch.isfinite(p).all())
    assert bool(torch.isfinite(partial.predict_proba(grid(5))).all())


def _state(fitted) -> dict[str, Tensor]:
    return {
        **{f"model.{k}": v for k, v in fitted.model.state_dict().items()},
        **{f"likelihood.{k}": v for k, v in fitted.likelihood.state_dict().items()},
    }


def _same_state(a: dict[str, Tensor], b: dict[str, Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("bad_epoch", [1, 2, 3, 4])
def test_divergence_message_names_the_restored_state(
    monkeypatch: pytest.MonkeyPatch, bad_epoch: int
) -> None:
    """The epoch the message says the model was restored to is the state actually restored.

    The loss of the second minibatch of ``bad_epoch`` is made NaN. The last epoch whose losses
    were all finite is ``bad_epoch - 1``; its start is the state after ``bad_epoch - 2`` full
    epochs, which a clean fit with that many epochs reproduces bit for bit (same seed, same
    split and minibatches). The state *after* the named epoch (what the old message claimed)
    must not be what was restored.
    """
    x, y = tiny_data()
    epochs = 5
    n_batches = 4  # 320 training points / batch 100
    original = gpytorch.mlls.VariationalELBO.forward
    calls = {"n": 0}

    def poisoned(self: gpytorch.mlls.VariationalELBO, *args: object, **kw: object) -> Tensor:
        calls["n"] += 1
        out = original(self, *args, **kw)
        return out * float("nan") if calls["n"] == (bad_epoch - 1) * n_batches + 2 else out

    with monkeypatch.context() as patch:
        patch.setattr(gpytorch.mlls.VariationalELBO, "forward", poisoned)
        with pytest.raises(NumericalError, match=f"diverged in epoch {bad_epoch}/{epochs}") as info:
            fit_classifier(x, y, GPSettings(**{**TINY, "epochs": epochs}), progress=False)
    message = str(info.value)
    partial = info.value.partial
    restored = _state(partial)
    assert len(partial.history) == bad_epoch - 1

    named = re.search(r"restored to the start of epoch (\d+) ", message)
    if named is None:
        assert "restored to its initial state" in message
        start_of = 1  # the initial state is the start of epoch 1
    else:
        start_of = int(named.group(1))
    # the last epoch whose losses were all finite (the initial state when the first failed)
    assert start_of == max(bad_epoch - 1, 1)
    assert "end of epoch" not in message

    def after(n_epochs: int) -> dict[str, Tensor]:
        fitted = fit_classifier(x, y, GPSettings(**{**TINY, "epochs": n_epochs}), progress=False)
        return _state(fitted)

    done = start_of - 1  # full epochs before the start of epoch `start_of`
    if done >= 1:
        assert _same_state(restored, after(done))
    else:
        # Nothing trained yet: gpytorch's untouched initial values (variational distribution
        # not yet initialised from the prior, q(u) = N(0, I)), inducing points still exactly
        # rows of the normalised training inputs, every hyperparameter as freshly built.
        strategy = partial.model.variational_strategy
        assert int(strategy.variational_params_initialized) == 0
        q = strategy._variational_distribution
        assert torch.equal(q.variational_mean, torch.zeros_like(q.variational_mean))
        eye = torch.eye(TINY["n_inducing"])
        assert torch.equal(q.chol_variational_covar, eye)
        z = strategy.inducing_points
        zx = partial.normaliser.transform(x.float())
        dist = torch.cdist(z, zx, compute_mode="donot_use_mm_for_euclid_dist")
        assert bool((dist.min(dim=1).values == 0).all())
        fresh = PsiGP(z.detach().clone())
        fresh_state = {f"model.{k}": v for k, v in fresh.state_dict().items()}
        fresh_state.update({
            f"likelihood.{k}": v
            for k, v in gpytorch.likelihoods.BernoulliLikelihood().state_dict().items()
        })  # fmt: skip
        assert _same_state(restored, fresh_state)
    # not the state after the named epoch (what the old message said)
    assert not _same_state(restored, after(start_of))


def _two_surfaces(n: int = 3000) -> list[tuple[Tensor, Tensor]]:
    g = torch.Generator().manual_seed(7)
    out = []
    for shift in (0.0, 1.5):
        x = torch.randn(n, 1, generator=g) * 2
        y = (torch.rand(n, generator=g) < torch.sigmoid(2 * x[:, 0] - shift)).float()
        out.append((x, y))
    return out


def test_classifiers_fitted_side_by_side_take_their_separate_steps() -> None:
    """The batched fit is each classifier's own fit (same split, inducing points, initial
    noise and Adam steps): equal first losses to float rounding; converged, the same psi up to
    rounding carried through the optimiser (Adam's early steps are nearly sign steps, so
    last-bit gradient differences move parameters), 1e-3 at most: an order of magnitude below
    the fit's own sampling error (the binomial s.e. of ~2,400 labels per surface, spread over
    the switch, is >= 0.01 there)."""
    from surrogate.gp.training import fit_classifiers

    data = _two_surfaces()
    s = GPSettings(kernel="matern52", n_inducing=30, epochs=300, lr=0.05, bins=100, seed=4)
    separate = [fit_classifier(x, y, s, progress=False) for x, y in data]
    together = fit_classifiers(data, s, progress=False)
    q = torch.linspace(-5, 5, 401)[:, None]
    for a, b in zip(separate, together, strict=True):
        assert a.history[0] == pytest.approx(b.history[0], rel=1e-6)
        assert b.history[-1] == pytest.approx(a.history[-1], rel=1e-3)
        assert (a.predict_proba(q) - b.predict_proba(q)).abs().max() < 1e-3
        assert (a.n_train, a.n_val) == (b.n_train, b.n_val)
        assert b.validation["brier"] == pytest.approx(a.validation["brier"], rel=1e-3)
        # a classifier of the batch saves and loads as a separately fitted one
        again = FittedClassifier.from_state(b.to_state())
        assert torch.equal(again.predict_proba(q), b.predict_proba(q))
    assert together[0].predict_proba(q).sub(together[1].predict_proba(q)).abs().max() > 0.1


@pytest.mark.parametrize("bins", [0, 50], ids=["minibatch", "over_the_batch_limit"])
def test_classifiers_are_fitted_one_by_one_where_batching_does_not_pay(
    bins: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    from surrogate.gp import training
    from surrogate.gp.training import fit_classifiers

    monkeypatch.setattr(training, "BATCH_MAX_BINS", 20)  # 50 bins exceed it
    data = _two_surfaces(600)
    s = GPSettings(n_inducing=10, epochs=3, bins=bins, seed=1)
    separate = [fit_classifier(x, y, s, progress=False) for x, y in data]
    together = fit_classifiers(data, s, progress=False)
    q = torch.linspace(-3, 3, 50)[:, None]
    for a, b in zip(separate, together, strict=True):
        assert torch.equal(a.predict_proba(q), b.predict_proba(q))


def test_binned_likelihood_is_gpytorchs_per_label_expected_log_prob() -> None:
    """One quadrature of k log Phi(f) + (n - k) log Phi(-f) equals k E[log p(1|f)] +
    (n - k) E[log p(0|f)] from BernoulliLikelihood.expected_log_prob (the same objective, float
    rounding apart), also in both tails (|mean| up to 40 latent s.d.), and both are the
    integral done in double with 200 Gauss-Hermite nodes to 1e-2 (gpytorch's log_normal_cdf is
    a piecewise approximation)."""
    import numpy as np

    from surrogate.gp.binned import binned_expected_log_likelihood

    g = torch.Generator().manual_seed(0)
    likelihood = gpytorch.likelihoods.BernoulliLikelihood()
    mean = torch.cat([torch.randn(2, 300, generator=g) * 3, torch.tensor([[-40.0, 40.0]] * 2)], 1)
    var = torch.rand(mean.shape, generator=g) * 2 + 1e-3
    f = gpytorch.distributions.MultivariateNormal(mean, torch.diag_embed(var))
    n = torch.randint(1, 100, mean.shape, generator=g).float()
    k = torch.floor(n * torch.rand(mean.shape, generator=g))
    ours = binned_expected_log_likelihood(likelihood, f, n, k)
    ones = torch.ones_like(n)
    per_label = k * likelihood.expected_log_prob(ones, f) + (n - k) * likelihood.expected_log_prob(
        ones - 1, f
    )
    assert ours.shape == per_label.shape == (2, 302)
    torch.testing.assert_close(ours, per_label, rtol=1e-5, atol=1e-3)
    nodes, weights = (torch.from_numpy(a) for a in np.polynomial.hermite.hermgauss(200))
    s = mean.double()[..., None] + (2 * var.double()[..., None]).sqrt() * nodes
    log_p = k.double()[..., None] * torch.special.log_ndtr(s) + (n - k).double()[
        ..., None
    ] * torch.special.log_ndtr(-s)
    truth = (log_p * weights).sum(-1) / math.sqrt(math.pi)
    torch.testing.assert_close(ours.double(), truth, rtol=1e-2, atol=0.1)


# ----------------------------------------------------------------------------------------------
# expected (fractional) labels


def _hidden_state_data(n: int, seed: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """1-D inputs, a hidden state that scales each row's switching probability by 0.5 or 1.5
    (so its expected label q has mean p_true(x) given x), and outcomes y ~ Bernoulli(q)."""
    gen = torch.Generator().manual_seed(seed)
    x = M_BOX[0] + (M_BOX[1] - M_BOX[0]) * torch.rand(n, 1, generator=gen)
    p = 0.6 * torch.sigmoid((2.2 - x[:, 0]) / 0.3)
    q = p * (0.5 + (torch.rand(n, generator=gen) < 0.5).float())
    return x, q, torch.bernoulli(q, generator=gen), p


def test_expected_labels_recover_the_surface_better_than_outcomes() -> None:
    """Same inputs, binned training: on the expected labels (variance ~p^2/4 per row instead of
    p(1 - p)) the fit is closer to p_true than on the 0/1 outcomes; held-out metrics score the
    outcomes either way."""
    x, q, y, _ = _hidden_state_data(4000, seed=3)
    settings = GPSettings(n_inducing=20, epochs=150, bins=100, lr=0.05)
    on_q = fit_classifier(x, q, settings, progress=False, outcomes=y)
    on_y = fit_classifier(x, y, settings, progress=False)
    xg = torch.linspace(*M_BOX, 200)[:, None]
    truth = 0.6 * torch.sigmoid((2.2 - xg[:, 0]) / 0.3)
    err_q = (on_q.predict_proba(xg) - truth).abs().mean().item()
    err_y = (on_y.predict_proba(xg) - truth).abs().mean().item()
    assert err_q < 0.7 * err_y, (err_q, err_y)
    assert err_q < 0.01, err_q
    assert on_q.validation is not None and on_q.validation["n"] == on_y.validation["n"] == 800
    assert on_q.validation["base_rate"] == on_y.validation["base_rate"]  # the same outcomes


def test_expected_labels_need_bins_and_outcomes() -> None:
    x, q, y, _ = _hidden_state_data(400, seed=4)
    with pytest.raises(ConfigError, match="binned"):
        fit_classifier(x, q, GPSettings(**TINY), progress=False, outcomes=y)
    with pytest.raises(NumericalError, match="0/1 outcomes"):
        fit_classifier(x, q, GPSettings(**TINY, bins=20), progress=False)


def test_classifiers_fitted_in_processes_are_those_fitted_here() -> None:
    """One by one (natural gradients), in two spawned processes of this process's one thread:
    each classifier is the fit made here bit for bit (its state, history and held-out scores),
    returned in the data's order."""
    from surrogate.gp.training import fit_classifiers

    data = _two_surfaces(600)
    s = GPSettings(n_inducing=10, epochs=30, bins=50, seed=1, natural_gradient=True)
    here = fit_classifiers(data, s, progress=False)
    spawned = fit_classifiers(data, s, progress=False, processes=2)
    for a, b in zip(here, spawned, strict=True):
        assert _same_state(_state(a), _state(b))
        assert a.history == b.history and a.validation == b.validation
    assert not _same_state(_state(spawned[0]), _state(spawned[1]))


def test_a_fit_that_fails_in_a_process_raises_here_with_its_restored_model() -> None:
    """A classifier whose fit fails numerically in a worker raises the fit's own error here,
    with the restored model attached as ``exc.partial``, as one by one would."""
    from surrogate.gp.training import fit_classifiers

    data = _two_surfaces(600)
    s = GPSettings(n_inducing=10, epochs=30, bins=50, seed=1, natural_gradient=True,
                   natural_lr=1e6)  # fmt: skip
    with pytest.raises(NumericalError) as here:
        fit_classifiers(data, s, progress=False)
    with pytest.raises(NumericalError) as spawned:
        fit_classifiers(data, s, progress=False, processes=2)
    assert str(spawned.value) == str(here.value)
    assert _same_state(_state(spawned.value.partial), _state(here.value.partial))
