"""Bins of a slow count that relax (gp.class_moves=relaxation): the law's stationary bins and
relaxation rate by construction, the relaxation time and stationary law measured on a network
whose answers are known in closed form, and bad settings refused by name."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from surrogate.config import build_field, field_config, seed_everything
from surrogate.errors import ConfigError
from surrogate.gp.class_relaxation import (
    check_shared_bins,
    relaxation_class_law,
    relaxation_time,
    stationary_bin_law,
)
from surrogate.gp.settings import GPSettings
from surrogate.models.capabilities import class_bins_of
from surrogate.models.count_classes import CountClasses
from surrogate.models.sbml_agent import SbmlAgentModel
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import record_stationary_bins
from tests.models.test_count_classes import _hidden_gene as hidden_gene

LUMPS = (0, 0, 0, 1, 1, 1)
BINS = (0, 1, 2, 0, 1, 2)


def _learned(n_nodes: int = 5) -> torch.Tensor:
    """A one-window law over 2 lumps x 3 bins with some moves between bins (to be dropped)."""
    g = torch.Generator().manual_seed(0)
    law = torch.rand(6, n_nodes, 6, generator=g, dtype=torch.float64)
    return law / law.sum(-1, keepdim=True)


def test_the_law_keeps_the_stationary_bins_and_relaxes_at_tau() -> None:
    n_nodes, dt, tau = 5, 0.05, 40.0
    pi = torch.tensor([[0.2, 0.5, 0.3]] * n_nodes, dtype=torch.float64)
    pi[2] = torch.tensor([0.6, 0.3, 0.1])
    law = relaxation_class_law(_learned(n_nodes), pi, BINS, LUMPS, tau, dt)
    assert torch.allclose(law.sum(-1), torch.ones(6, n_nodes, dtype=torch.float64))
    stay = math.exp(-dt / tau)
    for node in range(n_nodes):
        p = law[:, node, :]
        # the bin's own chain (the lump summed out) is the same from either lump: keep the bin
        # with exp(-dt / tau), else draw it from pi
        to_bin = torch.stack([p[:, [b, b + 3]].sum(-1) for b in range(3)], -1)  # 6 x 3
        want = stay * torch.eye(3, dtype=torch.float64) + (1 - stay) * pi[node]
        assert torch.allclose(to_bin[:3], want, atol=1e-12)
        assert torch.allclose(to_bin[3:], want, atol=1e-12)
        # so its second eigenvalue is exp(-dt / tau) and pi is its stationary law
        eig = sorted(torch.linalg.eigvals(want).real.tolist())
        assert eig[-2] == pytest.approx(stay, abs=1e-12)
        assert torch.allclose(pi[node] @ want, pi[node], atol=1e-12)


def test_a_relaxing_chain_starts_with_the_bins_stationary_law() -> None:
    """The chain's own stationary law (where ``decision.initial=stationary`` starts its cells) has
    the bins' law pi at every node, whatever the learned flips."""
    from surrogate.simulate.classes import ClassTable

    n_nodes = 5
    pi = torch.tensor([[0.2, 0.5, 0.3]] * n_nodes, dtype=torch.float64)
    pi[3] = torch.tensor([0.6, 0.3, 0.1])
    law = relaxation_class_law(_learned(n_nodes), pi, BINS, LUMPS, 1500.0, 0.05)
    names = [f"c{k}" for k in range(6)]
    start = ClassTable(law, [(0.0, 1.0)], ("z",), names, LUMPS, 0.05).stationary()
    by_bin = torch.stack([start[:, [b, b + 3]].sum(-1) for b in range(3)], -1)
    assert torch.allclose(by_bin, pi, atol=2e-3)  # float32 table, redraws of 3e-5 per window


def test_the_law_keeps_the_learned_flips_within_a_bin() -> None:
    learned = _learned()
    law = relaxation_class_law(learned, torch.full((5, 3), 1 / 3, dtype=torch.float64), BINS,
                               LUMPS, math.inf, 0.05)  # fmt: skip
    # an infinite relaxation time freezes the bins: only the learned flips, renormalised
    same = torch.tensor([[b == c for c in BINS] for b in BINS], dtype=torch.float64)
    flips = learned * same[:, None, :]
    assert torch.allclose(law, flips / flips.sum(-1, keepdim=True), atol=1e-12)


def _jittered_sample(n: int, tau: float, lags: list[float], jitter: float, seed: int):
    """Bins 0..3 of cells: keep the bin over a lag with exp(-lag / tau), else redraw from
    Binomial(3, 1/2); then each read is replaced by a fresh draw with probability ``jitter``
    (edge jitter: correlation A exp(-s / tau) with A = (1 - jitter)^2)."""
    rng = np.random.default_rng(seed)
    true = rng.binomial(3, 0.5, n)
    reads, now = [], 0.0
    for lag in [0.0, *lags]:
        keep = rng.random(n) < math.exp(-(lag - now) / tau)
        true = np.where(keep, true, rng.binomial(3, 0.5, n))
        now = lag
        noisy = np.where(rng.random(n) < jitter, rng.binomial(3, 0.5, n), true)
        reads.append(noisy)
    return np.stack(reads, 1)


@pytest.mark.parametrize("jitter", [0.0, 0.2])
def test_relaxation_time_is_recovered_through_edge_jitter(jitter: float) -> None:
    n, tau, lags = 20_000, 400.0, [50.0, 100.0, 150.0, 200.0]
    bins = _jittered_sample(n, tau, lags, jitter, seed=3)
    est, metrics = relaxation_time(bins, np.full(n, 1.5), lags)
    # tolerance: 4 standard errors of the estimate from the last lag alone (delta method)
    rho = math.exp(-lags[-1] / tau)
    se = (1 - rho**2) / math.sqrt(n) / (rho * abs(math.log(rho))) / (1 - jitter) ** 2
    assert est == pytest.approx(tau, rel=4 * se)
    assert metrics["jitter_factor"] == pytest.approx((1 - jitter) ** 2, abs=0.05)


def test_a_count_without_memory_at_the_lags_is_refused() -> None:
    bins = np.random.default_rng(0).integers(0, 4, size=(5000, 3))
    with pytest.raises(Exception, match="class_moves=learned"):
        relaxation_time(bins, np.full(5000, 1.5), [50.0, 100.0])


def test_stationary_bin_law_follows_the_inputs() -> None:
    """pi(bin | z) for bins whose law moves with z: P(bin 1 | z) = z on [0, 1]."""
    g = torch.Generator().manual_seed(1)
    z = torch.rand(3000, 1, generator=g)
    bins = (torch.rand(3000, generator=g) < z[:, 0]).long()
    grid = torch.linspace(0, 1, 11).unsqueeze(1)
    settings = GPSettings(n_inducing=16, epochs=300, bins=50, seed=0)
    law, metrics = stationary_bin_law(z, bins, 2, grid, settings)
    assert torch.allclose(law.sum(-1), torch.ones(11, dtype=torch.float64))
    # binomial noise of ~3000 samples over a smooth line: 0.06 is > 4 standard errors of a
    # local estimate over ~300 samples (sqrt(0.25 / 300) = 0.029) at the interior nodes
    assert torch.allclose(law[1:-1, 1], grid[1:-1, 0].double(), atol=0.06)
    assert sum(metrics["samples_per_bin"]) == 3000


def _hidden_gene(tmp_path, edges) -> SbmlAgentModel:
    """The hidden-gene network of tests/models/test_count_classes.py (three copies flipping on
    and off at a = 0.05/s each: G1 ~ Binomial(3, 1/2) at stationarity, its correlation
    exp(-2 a t), tau = 10 s), burned in, started where a disc perturbation starts cells, with
    classes over G1."""
    return hidden_gene(tmp_path, burn_in=100.0,
                       body={"kind": "static", "perturbation": {"radius": 3.0}},
                       classes={"species": "G1", "edges": edges})  # fmt: skip


def test_the_stationary_sample_measures_a_known_count(tmp_path) -> None:
    """The hidden gene count: bins = G1, stationary Binomial(3, 1/2) at any input, tau = 10 s."""
    model = _hidden_gene(tmp_path, [1, 2, 3])
    bins = class_bins_of(model.internal)
    assert bins == (0, 1, 2, 3, 0, 1, 2, 3)
    seed_everything(0)
    field = build_field(field_config("gaussian"))
    sim = Simulator(model, FullDecision(model.internal), field, 0.05)
    perturbation = model.body.perturbation(field, model.perturbation_options)
    n, lags = 4000, [2.0, 4.0, 6.0, 8.0]
    sample = record_stationary_bins(sim, perturbation, n, lags, ["k"], bins)
    assert list(sample.columns) == ["k", "bin_0", "bin_1", "bin_2", "bin_3", "bin_4"]
    counts = np.bincount(sample["bin_0"], minlength=4) / n
    want = np.array([1, 3, 3, 1]) / 8
    # 4 binomial standard errors per bin
    assert np.all(np.abs(counts - want) < 4 * np.sqrt(want * (1 - want) / n))
    tau, _ = relaxation_time(sample[[f"bin_{j}" for j in range(5)]].to_numpy(), np.full(n, 1.5),
                             lags)  # fmt: skip
    rho = math.exp(-lags[-1] / 10.0)
    se = (1 - rho**2) / math.sqrt(n) / (rho * abs(math.log(rho)))
    assert tau == pytest.approx(10.0, rel=4 * se)


def test_bins_of_each_lump_its_own_are_refused(tmp_path) -> None:
    assert CountClasses("P", ((2.0,), (3.0,)), ("a", "b")).bins is None
    with pytest.raises(ConfigError, match="shared by both"):
        check_shared_bins(None, LUMPS)
    with pytest.raises(ConfigError, match="each of the"):
        check_shared_bins((0, 1, 2, 0, 1, 1), LUMPS)
    model = _hidden_gene(tmp_path, {"off": [1, 2], "on": [1, 3]})
    assert class_bins_of(model.internal) is None


def test_only_a_k_lumps_chain_starts_from_its_stationary_law() -> None:
    """``decision.initial``: internal for any chain, stationary for a K-lumps chain only."""
    from types import SimpleNamespace

    from surrogate.kinds import chain_kind
    from surrogate.stages.settings import resolve_start

    relaxing = SimpleNamespace(kind=chain_kind("classes", class_moves="relaxation"))
    two_state = SimpleNamespace(kind=chain_kind("phi"))
    assert resolve_start("internal", relaxing, "decision.initial") == "internal"  # type: ignore[arg-type]
    assert resolve_start("stationary", relaxing, "x") == "stationary"  # type: ignore[arg-type]
    assert resolve_start("internal", two_state, "x") == "internal"  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="x=stationary starts a K-lumps chain"):
        resolve_start("stationary", two_state, "x")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="must be one of"):
        resolve_start("auto", relaxing, "x")  # type: ignore[arg-type]


def test_the_stationary_sample_grows_with_the_bins(tmp_path) -> None:
    """``gp.relaxation.n_cells: null`` (the default): 150 cells per shared bin, at least 600;
    an integer is kept; only a relaxing chain asks the model for its bins."""
    from surrogate.gp.class_relaxation import relaxation_cells
    from surrogate.kinds.chains import fit_chain

    assert relaxation_cells(16) == 2400 and relaxation_cells(4) == 600
    assert relaxation_cells(16, 800) == 800
    model = _hidden_gene(tmp_path, [1, 2, 3])  # 4 bins shared by both lumps
    gp = GPSettings.from_config({"seed": 0})
    relaxing = {"lumps": "classes", "class_moves": "relaxation"}
    chain = fit_chain(relaxing, gp, ("k",), model.internal, "m")
    assert chain.relaxation_cells == 600
    many = _hidden_gene(tmp_path, list(range(1, 8)))  # 8 bins by its edges
    assert fit_chain(relaxing, gp, ("k",), many.internal, "m").relaxation_cells == 1200
    given = {**relaxing, "relaxation": {"n_cells": 800}}
    assert fit_chain(given, gp, ("k",), many.internal, "m").relaxation_cells == 800
    with pytest.raises(ConfigError, match="integer >= 10 or null"):
        fit_chain({**relaxing, "relaxation": {"n_cells": 5}}, gp, ("k",), many.internal, "m")
