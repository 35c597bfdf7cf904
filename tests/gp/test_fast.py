"""CachedPsi: the SVGP predictive in closed form against PsiClassifier (gpytorch).

Tolerance: gpytorch evaluates the predictive in float32, and its own result differs from the
same model evaluated in float64 by up to ~3e-5 on these models (K_zz with jitter 1e-4 is
ill-conditioned); CachedPsi reproduces the float32 gpytorch numbers to ~1e-5, so the checks use
2e-5.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.errors import ConfigError, NumericalError
from surrogate.gp import GPSettings, PsiClassifier, fit_psi
from surrogate.gp import fast as fast_module
from surrogate.gp.fast import CachedPsi
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision

TOL = 2e-5
INPUTS = ("m", "L")


def _data(n: int = 1600, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    m = rng.uniform(1.0, 4.0, n)
    L = rng.uniform(0.0, 0.1, n)
    phi = rng.integers(0, 2, n)
    logit = 3.0 * (m - 2.2 - 10.0 * L) + phi
    y = rng.random(n) < 1.0 / (1.0 + np.exp(-logit))
    return pd.DataFrame({"m": m, "L": L, "phi": phi, "phi_next": y.astype(np.int8)})


@pytest.fixture(scope="module", params=["rbf", "matern12", "matern32", "matern52"])
def psi(request) -> PsiClassifier:
    torch.manual_seed(0)
    settings = GPSettings(kernel=request.param, n_inducing=30, epochs=4, batch_size=400)
    return fit_psi(_data(), INPUTS, settings, progress=False)


def _queries(n: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """(phi, z) with z = (m, L) columns, beyond the training box on both sides."""
    gen = torch.Generator().manual_seed(seed)
    m = 0.5 + 5.0 * torch.rand(n, generator=gen)
    L = 0.12 * torch.rand(n, generator=gen)
    phi = torch.randint(0, 2, (n,), generator=gen)
    return phi, torch.stack([m, L], 1)


@pytest.mark.parametrize("split_rows", [1, 10**9], ids=["split", "both"])
def test_matches_the_classifier(psi: PsiClassifier, split_rows: int) -> None:
    phi, z = _queries(3000)
    fast = CachedPsi.from_classifier(psi, split_rows=split_rows)
    assert fast.input_names == INPUTS and fast.domain == psi.domain
    expected = psi(phi, z)
    got = fast(phi, z)
    assert got.dtype == torch.float32 and got.shape == expected.shape
    assert (got - expected).abs().max().item() < TOL
    assert torch.equal(fast.evaluate(phi, z), got)
    assert fast.max_deviation(psi) < TOL


def test_tabulate_matches_the_classifier(
    psi: PsiClassifier, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The many-rows path (lookup tables' grids): each classifier on its own rows, in chunks,
    the kernel in place: the classifier's values to TOL on mixed origins, over several chunks
    (a short last one included) and an empty origin."""
    monkeypatch.setattr(fast_module, "TABULATE_ROWS", 256)
    phi, z = _queries(3000)
    fast = CachedPsi.from_classifier(psi)
    expected = psi(phi, z)
    got = fast.tabulate(phi, z)
    assert got.dtype == torch.float32 and got.shape == expected.shape
    assert (expected.max() - expected.min()).item() > 0.3  # a surface that varies
    assert (got - expected).abs().max().item() < TOL
    ones = torch.ones_like(phi)
    assert (fast.tabulate(ones, z) - psi(ones, z)).abs().max().item() < TOL
    e = -((8.0 * torch.rand(64, 30, generator=torch.Generator().manual_seed(2))) ** 2)
    # the in-place kernel is the same function (float32 rounding in another order)
    torch.testing.assert_close(fast._kernel_(e.clone()), fast._kernel(e), rtol=1e-6, atol=1e-7)


def test_split_rows_run_eagerly_under_torch_compile(monkeypatch: pytest.MonkeyPatch) -> None:
    """Inside torch.compile the row split still runs eagerly (a graph break: data-dependent
    row counts), through the wrapper made at first use, and gives the eager numbers."""
    torch.manual_seed(0)
    settings = GPSettings(n_inducing=8, epochs=1, batch_size=200)
    psi = fit_psi(_data(400), INPUTS, settings, progress=False)
    fast = CachedPsi.from_classifier(psi, split_rows=1)
    fast.check_finite = False
    compiling: list[bool] = []
    impl = CachedPsi._split_rows_impl

    def spy(self: CachedPsi, phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        compiling.append(torch.compiler.is_compiling())
        return impl(self, phi, x)

    monkeypatch.setattr(CachedPsi, "_split_rows_impl", spy)
    fast_module._eager_split_rows.cache_clear()  # wrap the spy
    try:
        phi, z = _queries(300)
        eager = fast.evaluate(phi, z)
        compiled = torch.compile(lambda p, q: fast.evaluate(p, q) * 1.0, backend="eager")
        got = compiled(phi, z)
    finally:
        fast_module._eager_split_rows.cache_clear()
    assert compiling == [False, False]  # the eager call and the compiled one
    assert (got - eager).abs().max().item() < 1e-6


def test_latent_matches_gpytorch(psi: PsiClassifier) -> None:
    _, z = _queries(500)
    fast = CachedPsi.from_classifier(psi)
    mean, var = fast.latent(z)
    assert mean.shape == var.shape == (2, 500)
    for c, fitted in enumerate((psi.psi_0, psi.psi_1)):
        mu_ref, var_ref = fitted.latent(z)
        assert (mean[c] - mu_ref).abs().max().item() < 1e-4
        assert (var[c] - var_ref).abs().max().item() < 1e-4


def test_phi_as_bool_int_or_float_and_checks(psi: PsiClassifier) -> None:
    phi, z = _queries(200)
    fast = CachedPsi.from_classifier(psi)
    a = fast(phi, z)
    assert torch.equal(a, fast(phi.bool(), z))
    assert torch.equal(a, fast(phi.float(), z))
    bad = z.clone()
    bad[3, 0] = float("nan")
    with pytest.raises(NumericalError, match="NaN"):
        fast(phi, bad)
    assert torch.isnan(fast.evaluate(phi, bad)[3])  # the unchecked form lets NaN through
    fast.check_finite = False
    assert torch.isnan(fast(phi, bad)[3])
    with pytest.raises(ValueError, match="rows"):
        fast(phi[:5], z)


def test_natural_gradient_model() -> None:
    torch.manual_seed(1)
    settings = GPSettings(n_inducing=20, epochs=3, batch_size=400, natural_gradient=True)
    psi = fit_psi(_data(800, seed=2), INPUTS, settings, progress=False)
    phi, z = _queries(1000)
    fast = CachedPsi.from_classifier(psi)
    assert (fast(phi, z) - psi(phi, z)).abs().max().item() < TOL


def test_simulation_leaves_the_per_call_check_on(psi: PsiClassifier) -> None:
    """The decision layer calls the unchecked ``evaluate`` (the simulator checks its state at
    record times); the caller's CachedPsi is left as it was, still checking direct calls."""
    from surrogate.fields import GaussianField
    from surrogate.simulate import Simulator

    fast = CachedPsi.from_classifier(psi)
    model = EcoliModel()
    decision = AbstractDecision(fast, model.internal, model.featurizer(INPUTS))
    sim = Simulator(model, decision, GaussianField(), 0.05)
    assert fast.check_finite is True
    phi, z = _queries(50)
    bad = z.clone()
    bad[7, 1] = float("nan")
    with pytest.raises(NumericalError, match="NaN"):
        fast(phi, bad)
    # the layer's path: no check, NaN flows through to be caught at record time
    p = decision.probability(phi, bad)
    assert torch.isnan(p[7]) and bool(torch.isfinite(p[:7]).all())
    assert torch.equal(decision.probability(phi, z), fast(phi, z))
    state = sim.initial_state(20, (2.0, 0.0))
    sim.step(state)
    assert state.step == 1 and fast.check_finite is True


# ----------------------------------------------------------------------------------------------
# any number of inputs


def _data_d(d: int, n: int = 1200, seed: int = 4) -> tuple[pd.DataFrame, tuple[str, ...]]:
    """A synthetic transitions table over ``d`` inputs x0..x{d-1} with different scales."""
    rng = np.random.default_rng(seed)
    names = tuple(f"x{i}" for i in range(d))
    scales = 10.0 ** np.arange(d)  # 1, 10, 100: the normaliser and the lengthscales must cope
    x = rng.uniform(-1.0, 1.0, (n, d)) * scales
    phi = rng.integers(0, 2, n)
    logit = 3.0 * (x / scales).sum(1) - 1.0 + 2.0 * phi
    y = rng.random(n) < 1.0 / (1.0 + np.exp(-logit))
    frame = pd.DataFrame(x, columns=list(names))
    return frame.assign(phi=phi, phi_next=y.astype(np.int8)), names


@pytest.mark.parametrize("d", [1, 3])
@pytest.mark.parametrize("ard", [True, False])
def test_any_number_of_inputs(d: int, ard: bool) -> None:
    data, names = _data_d(d)
    torch.manual_seed(0)
    settings = GPSettings(n_inducing=15, epochs=3, batch_size=300, ard=ard)
    psi = fit_psi(data, names, settings, progress=False)
    fast = CachedPsi.from_classifier(psi)
    assert fast.input_names == names
    gen = torch.Generator().manual_seed(5)
    scales = 10.0 ** torch.arange(d, dtype=torch.float32)
    z = (2.4 * torch.rand(3000, d, generator=gen) - 1.2) * scales  # 20 % beyond the data
    phi = torch.randint(0, 2, (3000,), generator=gen)
    expected = psi(phi, z)
    # the surface really varies here, so agreement is not trivial
    assert (expected.max() - expected.min()).item() > 0.3
    for split_rows in (1, 10**9):
        fast.split_rows = split_rows
        assert (fast(phi, z) - expected).abs().max().item() < TOL
    mean, var = fast.latent(z)
    assert mean.shape == (2, 3000)
    for c, fitted in enumerate(psi.classifiers):
        mu_ref, var_ref = fitted.latent(z)
        assert (mean[c] - mu_ref).abs().max().item() < 1e-4
        assert (var[c] - var_ref).abs().max().item() < 1e-4
    assert fast.max_deviation(psi, n_check=2000, seed=3) < TOL


def test_max_deviation_samples_each_inputs_domain() -> None:
    """Points are drawn per input name from ``domain[name]`` (widened 10 %), not from a box
    shared by all inputs: record what psi is asked."""
    data, names = _data_d(3, n=600)
    psi = fit_psi(data, names, GPSettings(n_inducing=8, epochs=2, batch_size=300), progress=False)
    fast = CachedPsi.from_classifier(psi)
    seen: list[torch.Tensor] = []

    def recording(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        seen.append(z.clone())
        return psi(phi, z)

    recording.device = psi.device  # type: ignore[attr-defined]
    assert fast.max_deviation(recording, n_check=4000, seed=0) < TOL
    z = seen[0]
    assert z.shape == (4000, 3)
    for i, name in enumerate(names):
        lo, hi = psi.domain[name]
        pad = 0.1 * (hi - lo)
        assert z[:, i].min().item() >= lo - pad - 1e-3 * (hi - lo)
        assert z[:, i].max().item() <= hi + pad + 1e-3 * (hi - lo)
        # and they cover it: beyond the data on both sides
        assert z[:, i].min().item() < lo and z[:, i].max().item() > hi


def test_empty_batch(psi: PsiClassifier) -> None:
    phi, z = _queries(10)
    fast = CachedPsi.from_classifier(psi)
    assert fast(phi[:0], z[:0]).shape == (0,)


@pytest.mark.parametrize("d", [1, 3])
def test_linear_prior_mean(d: int) -> None:
    """gp.mean=linear: the cached form carries the slope, on both query paths and in latent."""
    data, names = _data_d(d)
    torch.manual_seed(0)
    settings = GPSettings(n_inducing=15, epochs=3, batch_size=300, mean="linear")
    psi = fit_psi(data, names, settings, progress=False)
    assert all(c.model.mean_name == "linear" for c in psi.classifiers)
    fast = CachedPsi.from_classifier(psi)
    assert fast.mean_slope is not None and fast.mean_slope.shape == (2, d)
    gen = torch.Generator().manual_seed(5)
    scales = 10.0 ** torch.arange(d, dtype=torch.float32)
    z = (4.0 * torch.rand(3000, d, generator=gen) - 2.0) * scales  # well beyond the data
    phi = torch.randint(0, 2, (3000,), generator=gen)
    expected = psi(phi, z)
    for split_rows in (1, 10**9):
        fast.split_rows = split_rows
        assert (fast(phi, z) - expected).abs().max().item() < TOL
    mean, _ = fast.latent(z)
    for c, fitted in enumerate(psi.classifiers):
        assert (mean[c] - fitted.latent(z)[0]).abs().max().item() < 1e-4
    # a constant mean has no slope term at all (the hot path gains no op)
    const = fit_psi(
        data, names, GPSettings(n_inducing=15, epochs=1, batch_size=300), progress=False
    )
    assert CachedPsi.from_classifier(const).mean_slope is None


def test_unknown_mean_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"gp.mean: unknown mean 'quadratic'"):
        GPSettings(mean="quadratic")
