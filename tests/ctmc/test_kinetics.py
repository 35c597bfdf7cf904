"""General kinetics: expression trees, generated torch / numba propensities, the gillespie hook."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from surrogate.ctmc import CompiledSSA, ReactionNetwork, gillespie, mass_action_kinetics
from surrogate.ctmc.kinetics import call, const, input_ref, species_ref, torch_function
from surrogate.sbml import read_sbml
from tests.sbml.builder import DATA, MODELS


def test_mass_action_kinetics_equals_network_propensities():
    net = ReactionNetwork.from_reactions(
        ["A", "B", "C"],
        [
            ("0->A", {}, {"A": 1}),
            ("2A->B", {"A": 2}, {"B": 1}),
            ("A+B->C", {"A": 1, "B": 1}, {"C": 1}),
            ("3C->0", {"C": 3}, {}),
        ],
    )
    kinetics = mass_action_kinetics(net)
    gen = torch.Generator().manual_seed(0)
    state = torch.randint(0, 6, (200, 3), generator=gen)
    rates = torch.rand((200, 4), generator=gen, dtype=torch.float64)
    expected = net.propensities(state, rates)
    got = kinetics.propensities(state, rates)
    torch.testing.assert_close(got, expected, rtol=1e-14, atol=0.0)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_torch_numba_and_reference_evaluation_agree(name):
    """The two generated functions and the tree's own scalar evaluation, on a grid of states."""
    inputs = ["activity"] if name == "induced_production" else []
    model = read_sbml(DATA / f"{name}.xml", inputs=inputs)
    kinetics = model.kinetics
    gen = torch.Generator().manual_seed(1)
    n = 64
    state = torch.randint(0, 120, (n, len(model.species)), generator=gen)
    params = torch.rand((n, kinetics.n_inputs), generator=gen, dtype=torch.float64) * 2
    got_torch = kinetics.propensities(state, params).numpy()
    module = CompiledSSA(kinetics).module
    got_numba = np.empty_like(got_torch)
    for i in range(n):
        module.propensities(state[i].numpy(), params[i].numpy(), got_numba[i])
    reference = np.array(
        [
            [e.evaluate(state[i].tolist(), params[i].tolist()) for e in kinetics.propensity_exprs]
            for i in range(n)
        ]
    )
    np.testing.assert_allclose(got_torch, reference, rtol=1e-13, atol=0)
    np.testing.assert_allclose(got_numba, reference, rtol=1e-13, atol=0)


def test_folding_and_type_checks():
    x = species_ref(0, "X")
    assert call("plus", const(1.0), const(2.0)) == const(3.0)
    assert call("and", const(True), call("gt", x, const(1.0))) == call("gt", x, const(1.0))
    assert call("or", const(True), call("gt", x, const(1.0))) == const(True)
    assert call("piecewise", x, const(False), const(4.0)) == const(4.0)
    with pytest.raises(ValueError, match="argument 1 must be real"):
        call("plus", x, call("lt", x, const(2.0)))
    with pytest.raises(ValueError, match="unknown operator"):
        call("gamma", x)
    with pytest.raises(ValueError, match="takes at least 2"):
        call("minus", x)


def test_piecewise_without_otherwise_is_nan_where_no_piece_holds():
    e = call("piecewise", const(2.0), call("lt", species_ref(0, "X"), input_ref(0, "a")))
    assert e.evaluate([1.0], [3.0]) == 2.0
    assert math.isnan(e.evaluate([5.0], [3.0]))


def test_nan_and_inf_constants_generate_valid_code_on_both_paths():
    """NaN and +-inf constants (a piecewise without otherwise, INF in a formula) are numbers in
    the torch code as in the numba code: both agree with the tree, NaN where no piece holds."""
    x, a = species_ref(0, "X"), input_ref(0, "a")
    exprs = (
        call("piecewise", call("times", a, x), call("lt", x, const(4.0))),  # NaN for X >= 4
        call("min", x, const(math.inf)),
        call("piecewise", a, call("gt", x, const(-math.inf)), const(math.nan)),
        call("times", a, call("piecewise", const(1.0), call("lt", x, const(math.inf)))),
    )
    from surrogate.ctmc.kinetics import Kinetics

    net = ReactionNetwork.from_reactions(["X"], [(f"r{k}", {}, {"X": 1}) for k in range(4)])
    kinetics = Kinetics(net, ("a",), exprs)
    state = torch.arange(8).reshape(8, 1)
    params = torch.full((8, 1), 0.5, dtype=torch.float64)
    got_torch = kinetics.torch_propensity(state, params).numpy()
    module = CompiledSSA(kinetics).module
    got_numba = np.empty_like(got_torch)
    for i in range(8):
        module.propensities(state[i].numpy(), params[i].numpy(), got_numba[i])
    reference = np.array([[e.evaluate(s, [0.5]) for e in exprs] for s in state.tolist()])
    assert np.isnan(reference[4:, 0]).all() and not np.isnan(reference[:4]).any()
    np.testing.assert_array_equal(got_torch, reference)
    np.testing.assert_array_equal(got_numba, reference)
    condition = torch_function([call("lt", x, const(math.inf))])
    assert condition(state, params)[:, 0].all()


def _decay():
    net = ReactionNetwork.from_reactions(["X", "Y"], [("X->Y", {"X": 1}, {"Y": 1})])
    return net, mass_action_kinetics(net)


def test_gillespie_hook_reproduces_the_default_path_exactly():
    """First-order mass action through the hook: same propensities, same random numbers."""
    net = ReactionNetwork.from_reactions(
        ["A", "B"], [("AB", {"A": 1}, {"B": 1}), ("BA", {"B": 1}, {"A": 1})]
    )
    kinetics = mass_action_kinetics(net)
    state = torch.tensor([[30, 5]]).repeat(500, 1)
    rates = torch.tensor([1.0, 2.5], dtype=torch.float64).repeat(500, 1)
    a = gillespie(net, state, rates, 0.7, torch.Generator().manual_seed(3))
    b = gillespie(
        net,
        state,
        rates,
        0.7,
        torch.Generator().manual_seed(3),
        propensity=kinetics.torch_propensity,
    )
    assert torch.equal(a, b)


def test_gillespie_hook_refuses_bad_propensities_and_negative_counts():
    net, _ = _decay()
    state = torch.tensor([[3, 0]])

    def negative(x, p):
        return -torch.ones((x.shape[0], 1), dtype=torch.float64)

    with pytest.raises(ValueError, match="negative or non-finite"):
        gillespie(net, state, torch.zeros((1, 0)), 1.0, propensity=negative)

    def constant(x, p):  # fires even without X: drives X negative
        return torch.full((x.shape[0], 1), 50.0, dtype=torch.float64)

    with pytest.raises(ValueError, match="drove a count negative"):
        gillespie(net, state, torch.zeros((1, 0)), 1.0, propensity=constant)
    with pytest.raises(ValueError, match="must be finite"):
        gillespie(net, state, torch.tensor([[math.nan]]), 1.0, propensity=constant)
    with pytest.raises(ValueError, match=r"shape \(n, P\)"):
        gillespie(net, state, torch.zeros((2, 1)), 1.0, propensity=constant)
