"""SBML reader: what it reads (checked against hand-computed propensities) and what it refuses
(every unsupported construct: the error names the construct and the element id)."""

from __future__ import annotations

import math

import libsbml
import pytest
import torch

from surrogate.ctmc.kinetics import const
from surrogate.errors import ConfigError
from surrogate.sbml import SbmlError, read_sbml, read_sbml_string
from tests.sbml.builder import Reaction, Species, build


def parse(formula: str) -> libsbml.ASTNode:
    return libsbml.parseL3Formula(formula)


def simple(law: str = "k * X", edit=None, level: int = 3, version: int = 1, **kwargs) -> str:
    """X -> 0 with the given law; parameters k (= 2) and a non-constant p."""
    reactions = kwargs.pop("reactions", [Reaction("R1", law, {"X": 1})])
    species = kwargs.pop("species", [Species("X", amount=10)])
    return build(
        "m",
        species,
        {"k": 2.0, **kwargs.pop("parameters", {})},
        reactions,
        edit=edit,
        level=level,
        version=version,
        **kwargs,
    )


def refused(text: str, *needles: str, inputs=()) -> str:
    with pytest.raises(SbmlError) as info:
        read_sbml_string(text, inputs=inputs)
    message = str(info.value)
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"
    return message


# ----------------------------------------------------------------------------------------------
# what is read


def test_error_type_is_a_config_error():
    assert issubclass(SbmlError, ConfigError)


def test_local_parameters_shadow_globals_and_constants_are_recorded():
    text = simple(
        reactions=[Reaction("R1", "k * X", {"X": 1}, local={"k": 5.0})],
        parameters={"unused": 3.0},
    )
    model = read_sbml_string(text)
    state = torch.tensor([[10], [3]])
    assert model.propensities(state, torch.zeros(0)).tolist() == [[50.0], [15.0]]
    assert model.constants == {"cell": 1.0, "k": 2.0, "unused": 3.0}


def test_concentration_initial_value_and_species_as_concentration():
    text = simple(
        law="k * X",
        species=[Species("X", concentration=2.5, only_substance=False)],
        compartments={"cell": 4.0},
    )
    model = read_sbml_string(text)
    assert model.initial_state.tolist() == [10]  # 2.5 x 4
    # X in the law is the concentration 10 / 4
    assert model.propensities(torch.tensor([[10]]), torch.zeros(0)).item() == 2.0 * 10 / 4


def test_initial_assignments_and_parameter_assignment_rules():
    def edit(model):
        ia = model.createInitialAssignment()
        ia.setSymbol("X")
        ia.setMath(parse("3 * k + 1"))  # 7
        q = model.createParameter()
        q.setId("q")
        q.setConstant(False)
        rule = model.createAssignmentRule()
        rule.setVariable("q")
        rule.setMath(parse("k * X^2"))  # a function of the state, inlined

    model = read_sbml_string(simple(law="q + log(2, X) + root(3, X) + avogadro * 0", edit=edit))
    assert model.initial_state.tolist() == [7]
    x = 8.0
    expected = 2.0 * x**2 + math.log(x) / math.log(2) + x ** (1 / 3)
    got = model.propensities(torch.tensor([[8]]), torch.zeros(0)).item()
    assert got == pytest.approx(expected, rel=1e-14)


def test_boolean_logic_piecewise_and_min_max():
    law = "piecewise(k * X, (X > 2 && X <= 5) || !(X != 9), min(X, 3) + max(1, 0))"
    model = read_sbml_string(simple(law=law, version=2))  # min / max are L3V2 MathML
    xs = [0, 3, 5, 7, 9]
    got = model.propensities(torch.tensor([[x] for x in xs]), torch.zeros(0))[:, 0].tolist()
    expected = [2.0 * x if (2 < x <= 5 or x == 9) else min(x, 3) + 1 for x in xs]
    assert got == expected


def test_level2_file_is_read():
    model = read_sbml_string(simple(level=2, version=4))
    assert model.species == ("X",) and model.reaction_names == ("R1",)


def test_initial_concentration_rounds_to_nearest_count():
    text = simple(species=[Species("X", concentration=1.26, only_substance=False)])
    assert read_sbml_string(text).initial_state.tolist() == [1]


# ----------------------------------------------------------------------------------------------
# what is refused


def add_event(model, trigger="X > 5", assignments=(("X", "0"),), eid="ev1", **flags):
    """An event with L3 flags (initialValue, persistent, useValuesFromTriggerTime)."""
    event = model.createEvent()
    event.setId(eid)
    event.setUseValuesFromTriggerTime(flags.get("use_values", True))
    t = event.createTrigger()
    t.setMath(parse(trigger))
    t.setInitialValue(flags.get("initial_value", True))
    t.setPersistent(flags.get("persistent", True))
    for variable, formula in assignments:
        assignment = event.createEventAssignment()
        assignment.setVariable(variable)
        assignment.setMath(parse(formula))
    return event


def test_an_event_is_read_with_its_flags_and_counts():
    """The trigger reads the time csymbol and a species; a concentration species is assigned
    its concentration x size; parameters are inlined."""

    def edit(model):
        add_event(model, "X > 5 && time >= k", (("X", "k + 1"), ("C", "1.5")),
                  initial_value=False, persistent=False, use_values=False)  # fmt: skip

    species = [Species("X", amount=10), Species("C", concentration=0.5, only_substance=False)]
    model = read_sbml_string(simple(edit=edit, species=species, compartments={"cell": 4.0}))
    (event,) = model.kinetics.events
    assert event.name == "ev1" and event.uses_time and event.thresholds == (const(2.0),)
    assert (event.initial_value, event.persistent, event.use_values_from_trigger_time) == (
        False,
        False,
        False,
    )
    assert [(c, e.evaluate([0, 0], [])) for c, e in event.assignments] == [(0, 3.0), (1, 6.0)]
    assert event.trigger.evaluate([6, 0], [], 2.0) and not event.trigger.evaluate([6, 0], [], 1.9)


def test_a_species_assignment_rule_is_inlined_and_sets_the_initial_count():
    """y = 2 X (an amount) and z = X / 2 as a concentration in a compartment of size 4 (so
    2 X molecules); a law reading y reads 2 X."""

    def edit(model):
        for variable, formula in (("y", "2 * X"), ("z", "X / 2")):
            rule = model.createAssignmentRule()
            rule.setVariable(variable)
            rule.setMath(parse(formula))

    species = [
        Species("X", amount=3),
        Species("y", amount=0),
        Species("z", concentration=0, only_substance=False),
    ]
    text = simple(law="k * y", edit=edit, species=species, compartments={"cell": 4.0})
    model = read_sbml_string(text)
    assert model.initial_state.tolist() == [3, 6, 6]
    assert [(r.column, r.expr.evaluate([5, 0, 0], [])) for r in model.kinetics.rules] == [
        (1, 10.0),
        (2, 10.0),
    ]
    assert model.propensities(torch.tensor([[5, 0, 0]]), torch.zeros(0)).item() == 2.0 * 10


def test_what_events_do_beyond_species_assignments_is_refused_in_one_message():
    def edit(model):
        event = add_event(model, assignments=(("X", "0"), ("k", "3"), ("cell", "2")))
        event.createDelay().setMath(parse("1"))
        event.createPriority().setMath(parse("1"))
        add_event(model, eid="ev2", assignments=(("G", "1"),))

    species = [Species("X", amount=10), Species("G", amount=1, constant=True)]
    refused(
        simple(edit=edit, species=species),
        "delay of event 'ev1'",
        "priority of event 'ev1'",
        "event 'ev1' assigning parameter 'k' (events may assign species only)",
        "event 'ev1' assigning compartment 'cell'",
        "event 'ev2' assigning constant species 'G'",
    )


@pytest.mark.parametrize(
    ("trigger", "needles"),
    [
        ("time == 5", ["event 'ev1'", "only be compared"]),
        ("2 * time > 5", ["event 'ev1'", "only be compared"]),
        ("X + 1", ["event 'ev1'", "must be a condition"]),
        ("delay(X, 1) > 2", ["trigger of event 'ev1'", "delay"]),
    ],
)
def test_a_trigger_the_simulation_cannot_follow_exactly_is_refused(trigger, needles):
    refused(simple(edit=lambda model: add_event(model, trigger)), *needles)


def test_rules_on_species_that_cannot_hold_are_refused():
    def rule(variable, formula):
        def edit(model):
            r = model.createAssignmentRule()
            r.setVariable(variable)
            r.setMath(parse(formula))

        return edit

    species = [Species("X", amount=3), Species("y", amount=0)]
    # X is changed by R1 and assigned by a rule
    refused(simple(edit=rule("X", "5")), "rule for species 'X'", "changed by a reaction")
    refused(simple(edit=rule("y", "X / 2"), species=species), "'y'", "1.5", "whole number")
    refused(simple(edit=rule("y", "time"), species=species), "assignment rule for 'y'", "time")

    def from_rule(model):
        rule("y", "2 * X")(model)
        ia = model.createInitialAssignment()
        ia.setSymbol("X")
        ia.setMath(parse("y + 1"))

    refused(simple(edit=from_rule, species=species), "depends on species 'y'", "rule")

    def twice(model):
        rule("y", "2 * X")(model)
        add_event(model, "X > 5", (("y", "1"),))

    refused(simple(edit=twice, species=species), "event 'ev1'", "'y', which a rule assigns")


def test_rules_refused():
    def add_parameter(model, pid):
        p = model.createParameter()
        p.setId(pid)
        p.setValue(1.0)
        p.setConstant(False)

    def algebraic(model):
        add_parameter(model, "p1")
        model.createAlgebraicRule().setMath(parse("p1 - 1"))

    def rate(model):
        add_parameter(model, "p2")
        rule = model.createRateRule()
        rule.setVariable("p2")
        rule.setMath(parse("1"))

    def compartment_assignment(model):
        model.getCompartment("cell").setConstant(False)
        rule = model.createAssignmentRule()
        rule.setVariable("cell")
        rule.setMath(parse("2"))

    refused(simple(edit=algebraic), "algebraic rule", "p1 - 1")
    refused(simple(edit=rate), "rate rule", "p2")
    refused(simple(edit=compartment_assignment), "assignment rule for 'cell'", "compartments")


@pytest.mark.parametrize(
    ("law", "construct"),
    [
        ("k * delay(X, 1)", "delay"),
        ("k * X * time", "time"),
        ("quotient(X, 2)", "quotient"),
        ("rem(X, 2)", "rem"),
        ("factorial(X)", "factorial"),
        ("k * (X > 2)", "must be real"),
        ("k * nothing", "unknown symbol 'nothing'"),
        ("k * undefined_fn(X)", "unknown function 'undefined_fn'"),
        ("k * R1", "reaction id 'R1'"),
    ],
)
def test_unsupported_math_refused(law, construct):
    refused(simple(law=law, version=2), construct, "R1")  # L3V2 has quotient / rem


def test_rate_of_refused():
    refused(simple(law="k * rateOf(X)", level=3, version=2), "rateOf", "R1")


def test_function_body_with_free_name_refused():
    text = simple(law="f(X)", functions={"f": "lambda(x, k * x)"})
    refused(text, "function definition 'f'", "'k'")


def test_fast_and_reversible_reactions_refused():
    def fast(model):
        model.getReaction("R1").setFast(True)

    refused(simple(edit=fast), "fast reaction", "R1")
    text = simple(
        reactions=[Reaction("R1", "k * X", {"X": 1}, {"Y": 1}, reversible=True)],
        species=[Species("X", amount=1), Species("Y", amount=0)],
    )
    refused(text, "reversible reaction", "R1")


def test_stoichiometry_refused():
    refused(
        simple(reactions=[Reaction("R1", "k * X", {"X": 1.5})]), "non-integer stoichiometry", "R1"
    )

    def variable(model):
        model.getReaction("R1").getReactant(0).setId("sr1")
        ia = model.createInitialAssignment()
        ia.setSymbol("sr1")
        ia.setMath(parse("2"))

    refused(simple(edit=variable), "variable stoichiometry", "sr1", "R1")

    def stoichiometry_math(model):
        ref = model.getReaction("R1").getReactant(0)
        ref.createStoichiometryMath().setMath(parse("2"))

    refused(simple(edit=stoichiometry_math, level=2, version=4), "stoichiometryMath", "R1")


def test_initial_assignment_that_cannot_be_evaluated_refused():
    def edit(model):
        ia = model.createInitialAssignment()
        ia.setSymbol("X")
        ia.setMath(parse("k * time"))

    refused(simple(edit=edit), "initial assignment of 'X'", "time")

    def from_input(model):
        ia = model.createInitialAssignment()
        ia.setSymbol("X")
        ia.setMath(parse("a * 2"))

    text = simple(edit=from_input, parameters={"a": 1.0})
    refused(text, "initial assignment of 'X'", "input parameter 'a'", inputs=["a"])


def test_units_and_conversion_factors_refused():
    def mole(model):
        model.getSpecies("X").setSubstanceUnits("mole")

    refused(simple(edit=mole), "species 'X'", "mole")

    def conversion(model):
        model.setConversionFactor("k")

    refused(simple(edit=conversion), "conversionFactor", "'k'")


def test_bad_inputs_and_missing_pieces_refused():
    refused(simple(), "input 'nope'", inputs=["nope"])

    def no_law(model):
        model.getReaction("R1").unsetKineticLaw()

    refused(simple(edit=no_law), "no kinetic law", "R1")
    refused(simple(species=[Species("X", amount=2.5)]), "species 'X'", "whole number")
    with pytest.raises(SbmlError, match="does not exist"):
        read_sbml("/nonexistent/model.xml")
    with pytest.raises(SbmlError, match="SBML error"):
        read_sbml_string("<sbml>not really</sbml>")


def test_a_rule_on_an_input_without_a_value_is_set_from_each_cells_inputs():
    """y = X + a, with the input a unset in the file: y starts at 0 in the file's state (the
    SSAs set it from each cell's a at every window's start); with a = 2 in the file, X + 2."""

    def edit(model):
        rule = model.createAssignmentRule()
        rule.setVariable("y")
        rule.setMath(parse("X + a"))

    species = [Species("X", amount=3), Species("y", amount=0)]
    unset = simple(edit=edit, species=species, parameters={"a": None})
    assert read_sbml_string(unset, inputs=["a"]).initial_state.tolist() == [3, 0]
    given = simple(edit=edit, species=species, parameters={"a": 2.0})
    assert read_sbml_string(given, inputs=["a"]).initial_state.tolist() == [3, 5]
