"""An agent's internal network with a species assignment rule and a state-triggered event
(the agent route, window by window with changing inputs): identities that hold in every cell
on both SSAs and through the yaml route; time-triggered events refused there by name."""

from __future__ import annotations

import pytest
import torch
import yaml

from surrogate.config import build_model
from surrogate.errors import ConfigError
from surrogate.fields import ConstantField
from surrogate.models.network import NetworkInternalModel
from surrogate.sbml import read_sbml_string
from surrogate.simulate import FullDecision, Simulator
from tests.sbml.builder import Reaction, Species, build


def crossing_counter(trigger: str = "X >= 5") -> str:
    """Birth (at the input ``kb``) and death of X; the birth at X = 4 is a reaction of its
    own that also makes W, so W counts X's upward crossings of 5; the event counts them in C
    (X untouched, so its trigger stays true after it fires); y = 2 X by a rule."""

    def edit(model) -> None:
        rule = model.createAssignmentRule()
        rule.setVariable("y")
        rule.setMath(parse("2 * X"))
        event = model.createEvent()
        event.setId("count")
        event.setUseValuesFromTriggerTime(True)
        t = event.createTrigger()
        t.setMath(parse(trigger))
        t.setInitialValue(True)
        t.setPersistent(True)
        assignment = event.createEventAssignment()
        assignment.setVariable("C")
        assignment.setMath(parse("C + 1"))

    import libsbml

    parse = libsbml.parseL3Formula
    return build(
        "crossings",
        [Species(name, amount=0) for name in ("X", "W", "C", "y")],
        {"kb": 3.0, "mu": 0.5},
        [
            Reaction("birth_below", "piecewise(0, X == 4, kb)", {}, {"X": 1}),
            Reaction("birth_at_4", "piecewise(kb, X == 4, 0)", {}, {"X": 1, "W": 1}),
            Reaction("death", "mu * X", {"X": 1}),
        ],
        edit=edit,
    )


@pytest.mark.parametrize("ssa", ["compiled", "batched"])
def test_the_internal_network_keeps_its_rule_and_counts_each_crossing(ssa: str) -> None:
    sbml = read_sbml_string(crossing_counter(), inputs=["kb"])
    internal = NetworkInternalModel(sbml, ["kb"], "y >= 10", ssa=ssa, burn_in=2.0)
    assert internal.state_space is None and internal.exact_psi is None  # no generator
    torch.manual_seed(0)
    n = 200
    state = internal.initial_state(torch.full((n, 1), 3.0))
    assert len(state) == 4  # counts, streams, each cell's time and trigger values
    for k, level in enumerate([3.0, 6.0, 0.5, 4.0]):
        state = internal.advance(state, torch.full((n, 1), level), 1.0)
        counts = state[0]
        assert torch.equal(counts[:, 3], 2 * counts[:, 0])
        assert torch.equal(counts[:, 1], counts[:, 2])
        assert torch.equal(state[2], torch.full((n,), 3.0 + k, dtype=torch.float64))
    assert counts[:, 2].double().mean() > 2
    torch.testing.assert_close(internal.phi(state), (counts[:, 0] >= 5).float())


def test_a_time_triggered_event_is_refused_in_the_agent_route() -> None:
    sbml = read_sbml_string(crossing_counter("time >= 5"), inputs=["kb"])
    with pytest.raises(ConfigError, match=r"event\(s\) \['count'\] are triggered by the time"):
        NetworkInternalModel(sbml, ["kb"], "y >= 10")


def test_the_yaml_route_simulates_the_rule_and_event(tmp_path) -> None:
    network = tmp_path / "crossings.xml"
    network.write_text(crossing_counter())
    spec = {
        "network": str(network),
        "inputs": {"kb": "60 * L"},
        "lump": "y >= 10",
        "body": {"kind": "static"},
    }
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump(spec))
    model = build_model({"_target_": "surrogate.models.sbml_agent.SbmlAgentModel",
                         "spec": str(path)})  # fmt: skip
    torch.manual_seed(0)
    sim = Simulator(model, FullDecision(model.internal), ConstantField(0.05), dt=0.5)
    state = sim.initial_state(100, (0.0, 0.0), equilibration_time=0.5)
    for _ in range(10):
        sim.step(state)
        counts = sim.decision.state[0]
        assert torch.equal(counts[:, 3], 2 * counts[:, 0])
        assert torch.equal(counts[:, 1], counts[:, 2])
        torch.testing.assert_close(state.phi.float(), (counts[:, 0] >= 5).float())
    assert counts[:, 2].double().mean() > 1
