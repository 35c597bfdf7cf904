"""ReactionNetwork construction, validation and mass-action propensities."""

from __future__ import annotations

import dataclasses
from math import comb

import pytest
import torch

from surrogate.ctmc import ReactionNetwork


def mixed_network() -> ReactionNetwork:
    """Orders 0, 1, 2 (homo- and heteromeric) and 3, so every propensity code path is used."""
    return ReactionNetwork.from_reactions(
        ["A", "B", "C"],
        [
            ("dimerise", {"A": 2}, {"B": 1}),
            ("bind", {"A": 1, "B": 1}, {"C": 1}),
            ("decay", {"C": 1}, {}),
            ("influx", {}, {"A": 1}),
            ("trimerise", {"B": 3}, {"C": 1}),
        ],
    )


def test_from_reactions_builds_coefficient_matrices() -> None:
    net = mixed_network()
    assert net.species == ("A", "B", "C")
    assert net.reaction_names == ("dimerise", "bind", "decay", "influx", "trimerise")
    assert (net.n_species, net.n_reactions) == (3, 5)
    expected_reactants = [[2, 0, 0], [1, 1, 0], [0, 0, 1], [0, 0, 0], [0, 3, 0]]
    expected_products = [[0, 1, 0], [0, 0, 1], [0, 0, 0], [1, 0, 0], [0, 0, 1]]
    assert net.reactants.tolist() == expected_reactants
    assert net.products.tolist() == expected_products
    assert net.reactants.dtype == net.products.dtype == torch.int64
    assert net.stoichiometry.tolist() == [
        [-2, 1, 0],
        [-1, -1, 1],
        [0, 0, -1],
        [1, 0, 0],
        [0, -3, 1],
    ]


def test_mass_action_propensities_match_hand_computed_values() -> None:
    net = mixed_network()
    c = torch.tensor([[0.5, 2.0, 3.0, 7.0, 0.25], [1.5, 0.1, 1.0, 0.0, 4.0]], dtype=torch.float64)
    state = torch.tensor([[4, 3, 2], [1, 5, 0]])
    # Cell 0 (A, B, C) = (4, 3, 2): 0.5 * 4*3/2, 2 * 4*3, 3 * 2, 7, 0.25 * C(3, 3).
    # Cell 1 (1, 5, 0): dimerisation impossible with one A, 0.1 * 1*5, no C, no influx,
    # 4 * C(5, 3) = 40.
    expected = torch.tensor(
        [[3.0, 24.0, 6.0, 7.0, 0.25], [0.0, 0.5, 0.0, 0.0, 40.0]], dtype=torch.float64
    )
    a = net.propensities(state, c)
    assert a.dtype == torch.float64
    torch.testing.assert_close(a, expected, rtol=1e-15, atol=0.0)
    # Positive zeros: x < coefficient passes through the factor (x - x) = 0.
    assert not torch.signbit(a).any()


def test_propensities_agree_with_binomial_formula_over_a_grid() -> None:
    net = mixed_network()
    grid = torch.cartesian_prod(torch.arange(6), torch.arange(6), torch.arange(4))
    generator = torch.Generator().manual_seed(0)
    c = torch.rand((grid.shape[0], net.n_reactions), generator=generator, dtype=torch.float64)
    c = c + 0.5
    a = net.propensities(grid, c)
    for row, (x, rates) in enumerate(zip(grid.tolist(), c.tolist(), strict=True)):
        for r, coeffs in enumerate(net.reactants.tolist()):
            value = rates[r]
            for xs, rs in zip(x, coeffs, strict=True):
                value *= comb(xs, rs)
            assert a[row, r].item() == pytest.approx(value, rel=1e-14, abs=0.0)


def test_first_order_path_and_dtype_and_shared_rates() -> None:
    net = ReactionNetwork.from_reactions(
        ["A", "B"],
        [("ab", {"A": 1}, {"B": 1}), ("ba", {"B": 1}, {"A": 1}), ("make", {}, {"A": 1})],
    )
    state = torch.tensor([[3, 0], [2, 5]], dtype=torch.int32)
    shared = torch.tensor([2.0, 0.5, 1.25], dtype=torch.float32)
    a = net.propensities(state, shared)
    assert a.dtype == torch.float32
    expected = torch.tensor([[6.0, 0.0, 1.25], [4.0, 2.5, 1.25]])
    torch.testing.assert_close(a, expected, rtol=0.0, atol=0.0)


def test_network_is_frozen_and_owns_its_tensors() -> None:
    reactants = torch.tensor([[1, 0]])
    net = ReactionNetwork(("A", "B"), reactants, torch.tensor([[0, 1]]), ("ab",))
    reactants[0, 0] = 5  # the caller's tensor, not the network's
    assert net.reactants.tolist() == [[1, 0]]
    with pytest.raises(dataclasses.FrozenInstanceError):
        net.species = ("X", "Y")  # type: ignore[misc]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"species": ()}, "at least one species"),
        ({"species": ("A", "A")}, "unique"),
        ({"reaction_names": ()}, "at least one reaction"),
        ({"reaction_names": ("r", "r")}, "unique"),
        ({"reaction_names": ("r",)}, "shape"),
        ({"reactants": torch.tensor([[1, 0, 0], [0, 1, 0]])}, "shape"),
        ({"products": torch.tensor([1, 0])}, "shape"),
        ({"reactants": torch.tensor([[1, -1], [0, 1]])}, "non-negative"),
        ({"products": torch.tensor([[0.0, 1.0], [1.0, 0.0]])}, "integer"),
    ],
)
def test_constructor_validation(kwargs: dict, match: str) -> None:
    base = {
        "species": ("A", "B"),
        "reactants": torch.tensor([[1, 0], [0, 1]]),
        "products": torch.tensor([[0, 1], [1, 0]]),
        "reaction_names": ("ab", "ba"),
    }
    base.update(kwargs)
    with pytest.raises(ValueError, match=match):
        ReactionNetwork(**base)


@pytest.mark.parametrize(
    ("reactions", "match"),
    [
        ([("r", {"X": 1}, {"A": 1})], "unknown species"),
        ([("r", {"A": -1}, {"A": 1})], "non-negative int"),
        ([("r", {"A": 1.0}, {"A": 1})], "non-negative int"),
        ([("r", {"A": True}, {"A": 1})], "non-negative int"),
        ([("r", {"A": 1})], "name, reactants, products"),
    ],
)
def test_from_reactions_validation(reactions: list, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ReactionNetwork.from_reactions(["A", "B"], reactions)


@pytest.mark.parametrize(
    ("state", "rates", "match"),
    [
        (torch.tensor([[1, 2, 3, 4]]), torch.ones(1, 5), "state must have shape"),
        (torch.tensor([1, 2, 3]), torch.ones(1, 5), "state must have shape"),
        (torch.tensor([[1.0, 2.0, 3.0]]), torch.ones(1, 5), "integer counts"),
        (torch.tensor([[1, -2, 3]]), torch.ones(1, 5), "non-negative counts"),
        (torch.tensor([[1, 2, 3]]), torch.ones(2, 5), "rate_constants must have shape"),
        (torch.tensor([[1, 2, 3]]), torch.ones(1, 4), "rate_constants must have shape"),
        (torch.tensor([[1, 2, 3]]), torch.ones(1, 5, dtype=torch.int64), "floating point"),
        (torch.tensor([[1, 2, 3]]), -torch.ones(1, 5), "non-negative"),
        (torch.tensor([[1, 2, 3]]), torch.full((1, 5), float("nan")), "finite"),
        (torch.tensor([[1, 2, 3]]), torch.full((1, 5), float("inf")), "finite"),
    ],
)
def test_propensity_input_validation(state: torch.Tensor, rates: torch.Tensor, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        mixed_network().propensities(state, rates)
