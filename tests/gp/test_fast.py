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

from surrogate.errors import NumericalError
from surrogate.gp import GPSettings, fit_psi
from surrogate.gp.fast import CachedPsi
from surrogate.models.ecoli import EcoliParameters
from surrogate.simulate import AbstractDecision

TOL = 2e-5


def _data(n: int = 1600, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    m = rng.uniform(1.0, 4.0, n)
    L = rng.uniform(0.0, 0.1, n)
    phi = rng.integers(0, 2, n)
    logit = 3.0 * (m - 2.2 - 10.0 * L) + phi
    y = rng.random(n) < 1.0 / (1.0 + np.exp(-logit))
    return pd.DataFrame({"m": m, "L": L, "phi": phi, "phi_next": y.astype(np.int8)})


@pytest.fixture(scope="module", params=["rbf", "matern12", "matern32", "matern52"])
def psi(request):
    torch.manual_seed(0)
    settings = GPSettings(kernel=request.param, n_inducing=30, epochs=4, batch_size=400)
    return fit_psi(_data(), settings, progress=False)


def _queries(n: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    m = 0.5 + 5.0 * torch.rand(n, generator=gen)  # beyond the training box on both sides
    L = 0.12 * torch.rand(n, generator=gen)
    phi = torch.randint(0, 2, (n,), generator=gen)
    return phi, m, L


@pytest.mark.parametrize("split_rows", [1, 10**9], ids=["split", "both"])
def test_matches_the_classifier(psi, split_rows: int) -> None:
    phi, m, L = _queries(3000)
    fast = CachedPsi.from_classifier(psi, split_rows=split_rows)
    expected = psi(phi, m, L)
    got = fast(phi, m, L)
    assert got.dtype == torch.float32 and got.shape == expected.shape
    assert (got - expected).abs().max().item() < TOL
    assert fast.max_deviation(psi) < TOL


def test_latent_matches_gpytorch(psi) -> None:
    _, m, L = _queries(500)
    fast = CachedPsi.from_classifier(psi)
    mean, var = fast.latent(m, L)
    x = torch.stack([m, L], 1)
    for c, fitted in enumerate((psi.psi_tumble, psi.psi_run)):
        mu_ref, var_ref = fitted.latent(x)
        assert (mean[c] - mu_ref).abs().max().item() < 1e-4
        assert (var[c] - var_ref).abs().max().item() < 1e-4


def test_phi_as_bool_int_or_float_and_checks(psi) -> None:
    phi, m, L = _queries(200)
    fast = CachedPsi.from_classifier(psi)
    a = fast(phi, m, L)
    assert torch.equal(a, fast(phi.bool(), m, L))
    assert torch.equal(a, fast(phi.float(), m, L))
    bad = m.clone()
    bad[3] = float("nan")
    with pytest.raises(NumericalError, match="NaN"):
        fast(phi, bad, L)
    fast.check_finite = False
    assert torch.isnan(fast(phi, bad, L)[3])
    with pytest.raises(ValueError, match="rows"):
        fast(phi[:5], m, L)


def test_natural_gradient_model() -> None:
    torch.manual_seed(1)
    settings = GPSettings(n_inducing=20, epochs=3, batch_size=400, natural_gradient=True)
    psi = fit_psi(_data(800, seed=2), settings, progress=False)
    phi, m, L = _queries(1000)
    fast = CachedPsi.from_classifier(psi)
    assert (fast(phi, m, L) - psi(phi, m, L)).abs().max().item() < TOL


def test_simulation_turns_off_the_per_call_check(psi) -> None:
    from surrogate.fields import GaussianField
    from surrogate.simulate import Simulator

    fast = CachedPsi.from_classifier(psi)
    params = EcoliParameters()
    Simulator(AbstractDecision(fast, params), GaussianField(), params, 0.05)
    assert fast.check_finite is False
