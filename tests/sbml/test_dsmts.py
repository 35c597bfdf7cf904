"""DSMTS-style checks: SBML models read by surrogate.sbml, simulated by BOTH SSA backends, against
exact moments (closed forms, or the chemical master equation by matrix exponential).

Each test draws N_CELLS independent cells with a fixed seed and compares the sample mean and
standard deviation at three times with the exact values. Tolerance (see ``reference``): every
z-score must stay below the normal quantile with a Bonferroni correction over the test's
comparisons at a family-wise false-alarm probability ALPHA = 1e-3, i.e. had the seed been drawn
at random a correct simulator would fail a test with probability <= 1e-3. The standard errors
are computed from the exact moments (sd: asymptotic variance of the sample variance).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pytest
import torch

from surrogate.ctmc import CellStreams, CompiledSSA, gillespie
from surrogate.sbml import SbmlModel, read_sbml
from tests.sbml import builder
from tests.sbml.reference import (
    Moments,
    chain_moments,
    check_moments,
    poisson_moments,
    truncated_mass,
    z_bonferroni,
)

ALPHA = 1e-3
N_CELLS = 4000
DATA = builder.DATA
BACKENDS = ["torch", "compiled"]


def simulate(
    model: SbmlModel, backend: str, inputs: torch.Tensor, times: Sequence[float], seed: int
) -> list[np.ndarray]:
    """States (n, S) of N_CELLS cells at each time, window by window from the initial state."""
    n = inputs.shape[0]
    state = model.initial_states(n)
    out, previous = [], 0.0
    if backend == "torch":
        generator = torch.Generator().manual_seed(seed)
        for t in times:
            state = gillespie(
                model.network,
                state,
                inputs,
                t - previous,
                generator,
                propensity=model.torch_propensity,
            )
            out.append(state.numpy().copy())
            previous = t
    else:
        ssa = CompiledSSA(model.kinetics)
        streams = CellStreams.from_seed(seed, n)
        for t in times:
            state, _ = ssa.advance(state, inputs, t - previous, streams)
            out.append(state.numpy().copy())
            previous = t
    return out


def no_inputs(n: int = N_CELLS) -> torch.Tensor:
    return torch.zeros((n, 0), dtype=torch.float64)


def test_data_files_match_builder():
    for name, make in builder.MODELS.items():
        assert (DATA / f"{name}.xml").read_text() == make(), (
            f"tests/data/sbml/{name}.xml is stale: run python -m tests.sbml.builder"
        )


@pytest.mark.parametrize("backend", BACKENDS)
def test_birth_death(backend):
    """dsmts-001-01 style: closed-form mean and variance; mu4 from the CME truncated at 400."""
    lam, mu, x0, times = 0.1, 0.11, 100, [2.0, 5.0, 10.0]
    model = read_sbml(DATA / "birth_death.xml")
    up, down = (lambda x: lam * x), (lambda x: mu * x)
    exact = chain_moments(up, down, x0, 400, times)
    assert truncated_mass(up, down, x0, 400, times[-1]) < 1e-12
    for t, m in zip(times, exact, strict=True):
        g = math.exp((lam - mu) * t)
        assert m.mean == pytest.approx(x0 * g, rel=1e-9)
        assert m.var == pytest.approx(x0 * (lam + mu) / (lam - mu) * g * (g - 1), rel=1e-8)
    states = simulate(model, backend, no_inputs(), times, seed=11)
    z = z_bonferroni(ALPHA, 2 * len(times))
    for t, m, x in zip(times, exact, states, strict=True):
        check_moments(x[:, 0], m, z, f"{backend} birth-death X at t={t}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_immigration_death_concentration_semantics(backend):
    """dsmts-002 style: Poisson with mean alpha/mu (1 - e^{-mu t}); the species is read as a
    concentration in a compartment of size 2, so this also checks amount/size handling."""
    alpha, mu, times = 1.0, 0.1, [1.0, 5.0, 20.0]
    model = read_sbml(DATA / "immigration_death.xml")
    exact = [poisson_moments(alpha / mu * (1 - math.exp(-mu * t))) for t in times]
    states = simulate(model, backend, no_inputs(), times, seed=12)
    z = z_bonferroni(ALPHA, 2 * len(times))
    for t, m, x in zip(times, exact, states, strict=True):
        check_moments(x[:, 0], m, z, f"{backend} immigration-death X at t={t}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_dimerisation(backend):
    """dsmts-003 style: CME over P2 in 0..50 (P = 100 - 2 P2); P and P2 compared."""
    k1, k2, times = 0.001, 0.01, [1.0, 5.0, 20.0]
    model = read_sbml(DATA / "dimerisation.xml")
    up = lambda k: k1 * (100 - 2 * k) * (99 - 2 * k) / 2  # noqa: E731
    down = lambda k: k2 * k  # noqa: E731
    exact_p2 = chain_moments(up, down, 0, 50, times)
    exact_p = chain_moments(up, down, 0, 50, times, value=lambda k: 100 - 2 * k)
    states = simulate(model, backend, no_inputs(), times, seed=13)
    z = z_bonferroni(ALPHA, 4 * len(times))
    for t, mp, mp2, x in zip(times, exact_p, exact_p2, states, strict=True):
        assert (x[:, 0] + 2 * x[:, 1] == 100).all()
        check_moments(x[:, 0], mp, z, f"{backend} dimerisation P at t={t}")
        check_moments(x[:, 1], mp2, z, f"{backend} dimerisation P2 at t={t}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_general_kinetics_hill_repression(backend):
    """Non-mass-action laws (function definition, Hill repression, piecewise cap, Michaelis-
    Menten degradation, a boundary gene species): exact CME on X in 0..80."""
    times = [1.0, 3.0, 10.0]
    model = read_sbml(DATA / "hill_repression.xml")
    up = lambda x: 0.0 if x >= 80 else 2 * 7.5 * 20.0**2 / (20.0**2 + x**2)  # noqa: E731
    down = lambda x: 8.0 * x / (10.0 + x)  # noqa: E731
    exact = chain_moments(up, down, 0, 80, times)
    states = simulate(model, backend, no_inputs(), times, seed=14)
    z = z_bonferroni(ALPHA, 2 * len(times))
    for t, m, x in zip(times, exact, states, strict=True):
        assert (x[:, 0] == 2).all(), "the boundary species G must not change"
        check_moments(x[:, 1], m, z, f"{backend} Hill repression X at t={t}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_input_parameter_per_cell(backend):
    """An input parameter supplied per cell: two groups with activity 0.25 and 1.0 get
    production rates 8 and 32; each group is Poisson with mean rate / gamma (1 - e^{-gamma t})."""
    gamma, times = 0.5, [0.5, 2.0, 8.0]
    model = read_sbml(DATA / "induced_production.xml", inputs=["activity"])
    assert model.input_names == ("activity",)
    assert model.input_defaults == {"activity": 0.5}
    activity = torch.tensor([0.25, 1.0], dtype=torch.float64).repeat(N_CELLS // 2)
    inputs = activity.unsqueeze(1)
    states = simulate(model, backend, inputs, times, seed=15)
    z = z_bonferroni(ALPHA, 4 * len(times))
    for rate, group in ((8.0, 0), (32.0, 1)):
        for t, x in zip(times, states, strict=True):
            exact: Moments = poisson_moments(rate / gamma * (1 - math.exp(-gamma * t)))
            label = f"{backend} induced production (rate {rate}) at t={t}"
            check_moments(x[group::2, 0], exact, z, label)
