"""Sequential design: the acquisition table, guided jumps (rejection sampling) and a collection
that goes on between rounds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from surrogate.fields import GaussianField
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import FullDecision, Simulator
from surrogate.simulate.design import Acquisition, GuidedJump
from surrogate.simulate.transitions import (
    CollectOptions,
    TransitionCollector,
    collect_transitions,
)


def test_acquisition_is_occupancy_times_posterior_sd() -> None:
    """Each grid cell weighs (occupied rows of that origin in it) x (posterior sd at its centre);
    inputs outside the grid weigh 0."""
    z = torch.tensor([[0.1], [0.1001], [0.9], [0.5], [0.5001], [0.7]], dtype=torch.float64)
    phi = torch.tensor([0, 0, 0, 1, 1, 1])

    def spread(p: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sd = torch.where(p > 0, 2.0 * c[:, 0], torch.ones_like(c[:, 0]))
        return torch.full_like(sd, 0.5), sd

    w = Acquisition.from_posterior(spread, phi, z, margin=0.0)
    edges = w.edges[0]
    assert float(edges[0]) == pytest.approx(0.1) and float(edges[-1]) == pytest.approx(0.9)
    query = torch.tensor([[0.1], [0.5], [0.7], [0.3]], dtype=torch.float64)
    origin = torch.tensor([0, 1, 1, 1])
    k = torch.bucketize(query[:, 0], edges, right=True) - 1
    centre = (edges[k] + edges[k + 1]) / 2
    # rows per cell: two near 0.1 (origin 0), two near 0.5 and one at 0.7 (origin 1), none at 0.3
    c1, c2 = float(centre[1]), float(centre[2])
    expected = torch.tensor([2.0 * 1.0, 2.0 * 2.0 * c1, 1.0 * 2.0 * c2, 0.0], dtype=torch.float64)
    torch.testing.assert_close(w(origin, query), expected)
    assert float(w.weights[0].sum()) == pytest.approx(3.0)  # origin 0: sd 1, weights count rows
    assert float(w(torch.tensor([0]), torch.tensor([[5.0]]))[0]) == 0.0
    with pytest.raises(ValueError, match="non-negative"):
        Acquisition([torch.linspace(0, 1, 3)], -torch.ones(2, 2))


class _BandWeights(Acquisition):
    """Weight 1 where L > ``high``, ``mid`` where ``low`` < L <= ``high``, else 0."""

    def __init__(self, low: float, high: float, mid: float) -> None:
        edges = [torch.tensor([0.0, low, high, 1.0], dtype=torch.float64)]
        super().__init__(edges, torch.tensor([[0.0, mid, 1.0], [0.0, mid, 1.0]]))


def _guided(explore: float, candidates: int, weights: Acquisition) -> tuple[GuidedJump, dict]:
    model, field = EcoliModel(), GaussianField()
    perturbation = model.body.perturbation(field, model.perturbation_options)
    guide = GuidedJump(perturbation, model.body, field, lambda x: x[:, 1:2], weights,
                       candidates, explore)  # fmt: skip
    state = model.body.initial_state(20_000, torch.tensor([2.0, 0.0]), field, 0.05)
    return guide, state


def _ligand(guide: GuidedJump, state: dict) -> np.ndarray:
    return guide.body.inputs(state, guide.field, 0.0)[:, 1].numpy()


def test_guided_jumps_accept_by_rejection() -> None:
    """0/1 weights: a jump lands in the band with probability 1 - (1 - p)^K (K candidates, p the
    perturbation's own chance), within 4 binomial standard errors (p from unguided draws); with
    explore = 1 the jumps are the perturbation's own."""
    torch.manual_seed(0)
    band = _BandWeights(0.02, 0.05, 0.0)
    guide, state = _guided(0.0, 4, band)
    n = state["position"].shape[0]
    jump = torch.ones(n, dtype=torch.bool)
    phi = torch.zeros(n, dtype=torch.bool)
    plain = _ligand(guide, guide.perturbation.apply(state, jump))
    p = float((plain > 0.05).mean())
    assert 0.1 < p < 0.7  # the test needs a band neither empty nor certain
    guided = _ligand(guide, guide.apply(state, jump, phi, 0.0))
    expected = 1 - (1 - p) ** 4
    se = math.sqrt(expected * (1 - expected) / n) + 4 * (1 - p) ** 3 * math.sqrt(p * (1 - p) / n)
    assert abs(float((guided > 0.05).mean()) - expected) < 4 * se
    guide.explore = 1.0
    kept = _ligand(guide, guide.apply(state, jump, phi, 0.0))
    se = math.sqrt(2 * p * (1 - p) / n)
    assert abs(float((kept > 0.05).mean()) - p) < 4 * se
    # cells that do not jump stay where they were
    still = torch.zeros(n, dtype=torch.bool)
    guide.explore = 0.0
    moved = guide.apply(state, still, phi, 0.0)
    torch.testing.assert_close(moved["position"], state["position"])


def test_accepted_jumps_follow_the_weights() -> None:
    """Weights 1 and 1/2 on two bands and many candidates (almost every jump accepted): landing
    odds high:mid are the perturbation's own odds times 2, within 4 standard errors (delta
    method on the log odds)."""
    torch.manual_seed(1)
    guide, state = _guided(0.0, 64, _BandWeights(0.02, 0.05, 0.5))
    n = state["position"].shape[0]
    jump = torch.ones(n, dtype=torch.bool)
    phi = torch.ones(n, dtype=torch.bool)
    plain = _ligand(guide, guide.perturbation.apply(state, jump))
    guided = _ligand(guide, guide.apply(state, jump, phi, 0.0))

    def log_odds(L: np.ndarray) -> tuple[float, float]:
        hi, mid = int((L > 0.05).sum()), int(((L > 0.02) & (L <= 0.05)).sum())
        return math.log(hi / mid), math.sqrt(1 / hi + 1 / mid)

    (base, se0), (got, se1) = log_odds(plain), log_odds(guided)
    assert abs(got - base - math.log(2.0)) < 4 * math.hypot(se0, se1)
    assert float((guided <= 0.02).mean()) < 0.01  # weight 0: taken only when 64 draws fail


def test_collection_goes_on_between_takes() -> None:
    """A collector's second take simulates on (later windows of the same cells); its first take
    is collect_transitions' table from the same seed."""

    def simulator() -> Simulator:
        model = EcoliModel()
        return Simulator(model, FullDecision(model.internal), GaussianField(), 0.05)

    model = EcoliModel()
    sim = simulator()
    perturbation = model.body.perturbation(sim.field, model.perturbation_options)
    args = {"n_cells": 200, "perturb_rate": 0.5, "progress": False,
            "options": CollectOptions(record_every=3, equilibration_time=1.0, blackout=4)}  # fmt: skip
    torch.manual_seed(3)
    collector = TransitionCollector(sim, perturbation, **args)
    first, second = collector.take(300), collector.take(300)
    torch.manual_seed(3)
    once = collect_transitions(simulator(), perturbation, n_per_state=300, **args)
    np.testing.assert_array_equal(first["t"], once["t"])
    np.testing.assert_array_equal(first["phi_next"], once["phi_next"])
    assert second["t"].min() > first["t"].max()
    assert (second["phi"] == 0).sum() == (second["phi"] == 1).sum() == 300
    assert collector.kept.tolist() == [600, 600]
