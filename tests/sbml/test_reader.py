"""SBML reader: what it reads (checked against hand-computed propensities) and what it refuses
(every unsupported construct: the error names the construct and the element id)."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import libsbml
import pytest
import torch

from surrogate.ctmc import CellStreams, CompiledSSA, gillespie
from surrogate.ctmc.kinetics import const
from surrogate.errors import ConfigError
from surrogate.sbml import SbmlError, SbmlModel, SbmlWarning, read_sbml, read_sbml_string
from tests.sbml.builder import Reaction, Species, build

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
TOGGLE = EXAMPLES / "toggle_switch" / "Genetic_Toggle_Switch.sbml"
AUTOREGULATION = EXAMPLES / "autoregulation" / "ch07-ar-stoch.xml"
TYSON = EXAMPLES / "tyson_oscillator" / "Tyson_2_State_Oscillator.sbml"
VILAR = EXAMPLES / "vilar_oscillator" / "Vilar_Oscillator.sbml"
DIMERISATION = EXAMPLES / "dimerisation" / "ch07-dimer-stoch.xml"


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


def test_an_initial_concentration_giving_a_whole_count_within_rounding_is_read():
    """0.1 x 30 is 3.0000000000000004 in floats: a whole number of molecules."""
    text = simple(species=[Species("X", concentration=0.1, only_substance=False)],
                  compartments={"cell": 30.0})  # fmt: skip
    assert read_sbml_string(text).initial_state.tolist() == [3]


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


def test_fast_reactions_refused():
    def fast(model):
        model.getReaction("R1").setFast(True)

    refused(simple(edit=fast), "fast reaction", "R1")


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


# ----------------------------------------------------------------------------------------------
# reaction-local parameters as inputs (issue 37)


def two_reactions(level: int = 3, version: int = 1, parameters=None) -> str:
    """X -> 0 at k X with a local k = 5 in R1; X -> 0 at k X with the global k = 2 in R2."""
    return simple(
        reactions=[
            Reaction("R1", "k * X", {"X": 1}, local={"k": 5.0}),
            Reaction("R2", "k * X", {"X": 1}),
        ],
        parameters=parameters or {},
        level=level,
        version=version,
    )


@pytest.mark.parametrize(("level", "version"), [(3, 1), (2, 4)])
def test_a_local_parameter_is_an_input_as_reaction_dot_parameter(level, version):
    """``R1.k`` feeds R1's law only (its propensity scales with the input, R2's global k does
    not), and its default is the file's local value."""
    model = read_sbml_string(two_reactions(level, version), inputs=["R1.k"])
    assert model.input_names == ("R1.k",) and model.input_defaults == {"R1.k": 5.0}
    state = torch.tensor([[10], [10]])
    rates = model.propensities(state, torch.tensor([[0.5], [3.0]], dtype=torch.float64))
    assert rates.tolist() == [[5.0, 20.0], [30.0, 20.0]]
    assert model.default_inputs().tolist() == [5.0]
    assert "R1.k" not in model.constants and model.constants["k"] == 2.0


def test_a_published_file_with_only_local_constants_takes_a_local_input():
    """Wilkinson's auto-regulatory network (L2V1, every constant local): Transcription's
    propensity is input x Gene, the other reactions keep the file's constants."""
    model = read_sbml(AUTOREGULATION, inputs=["Transcription.k2"])
    state = torch.tensor([[7, 3, 4, 25, 30]])  # Gene, P2Gene, Rna, P, P2
    low, high = (model.propensities(state, torch.tensor([v])) for v in (0.02, 0.06))
    r = model.reaction_names.index("Transcription")
    assert low[0, r].item() == pytest.approx(0.02 * 7) and high[0, r].item() == pytest.approx(0.42)
    others = [i for i in range(len(model.reaction_names)) if i != r]
    assert torch.equal(low[0, others], high[0, others])
    assert model.input_defaults == {"Transcription.k2": 0.02}


def test_a_local_input_needs_no_value_in_the_file():
    def unset(model):
        model.getReaction("R1").getKineticLaw().getLocalParameter("k").unsetValue()

    model = read_sbml_string(simple(edit=unset, reactions=[
        Reaction("R1", "k * X", {"X": 1}, local={"k": 5.0})]), inputs=["R1.k"])  # fmt: skip
    assert math.isnan(model.input_defaults["R1.k"])
    with pytest.raises(SbmlError, match=r"inputs \['R1.k'\] have no value in the file"):
        model.default_inputs()


def test_a_global_input_shadowed_by_a_local_parameter_is_refused():
    message = refused(two_reactions(), inputs=["k"])
    for needle in ("input 'k' is a global parameter", "reaction 'R1'", "local parameter 'k'",
                   "no effect", "(R1.k)"):  # fmt: skip
        assert needle in message, needle
    text = simple(
        reactions=[
            Reaction("R1", "k * X", {"X": 1}, local={"k": 5.0}),
            Reaction("R2", "k * X", {"X": 1}, local={"k": 1.0}),
        ]
    )
    refused(text, "reactions 'R1', 'R2' declare a local parameter 'k'", inputs=["k"])


def test_an_input_that_names_no_parameter_lists_what_exists():
    text = two_reactions(parameters={"a": 1.0})
    message = refused(text, "input 'nope' is not a global parameter", inputs=["nope"])
    assert "global parameters: ['a', 'k']" in message and "local parameters: ['R1.k']" in message
    refused(text, "reaction 'R1' has no local parameter 'q'", "its local parameters: ['k']",
            inputs=["R1.q"])  # fmt: skip
    refused(text, "input 'R9.k'", "reaction 'R9' does not exist", "local parameters: ['R1.k']",
            inputs=["R9.k"])  # fmt: skip
    refused(text, "inputs must be unique", inputs=["R1.k", "R1.k"])


# ----------------------------------------------------------------------------------------------
# reactions flagged reversible (issue 37)


def flagged(*laws: str, level: int = 3, version: int = 1) -> str:
    """One reaction A -> B flagged reversible per law (R1, R2, ...), plus a species C that is
    neither reactant nor product."""
    return simple(
        reactions=[
            Reaction(f"R{i}", law, {"A": 1}, {"B": 1}, reversible=True)
            for i, law in enumerate(laws, 1)
        ],
        species=[Species("A", amount=5), Species("B", amount=3), Species("C", amount=1)],
        parameters={"kf": 2.0, "kr": 0.5, "K": 10.0},
        level=level,
        version=version,
    )


def test_one_way_reversible_laws_are_read_as_irreversible_with_one_warning():
    """Laws whose negated parts depend on no product: one warning names every such reaction,
    and the propensities are the laws as written."""
    text = flagged("kf * A", "kf * A / (1 + B^2)", "kf * A - kr * C", "kf * A + k")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = read_sbml_string(text)
    ours = [w for w in caught if issubclass(w.category, SbmlWarning)]
    assert len(ours) == 1, [str(w.message) for w in caught]
    message = str(ours[0].message)
    assert "4 reactions flagged reversible" in message
    assert "read as irreversible: 'R1', 'R2', 'R3', 'R4'" in message
    rates = model.propensities(torch.tensor([[5, 3, 1]]), torch.zeros(0))
    assert rates.tolist() == [[10.0, 1.0, 9.5, 12.0]]
    assert model.network.stoichiometry.tolist() == [[-1, 1, 0]] * 4


def test_an_irreversible_model_reads_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_sbml(AUTOREGULATION, inputs=["Transcription.k2"])


@pytest.mark.parametrize(
    "law",
    [
        "kf * A - kr * B",  # forward minus backward
        "kf * A + (-kr) * B",  # a negated factor makes the product a negated part
        "kf * A - 2 * B",  # a constant rate, subtracted
        "kf * A * (1 - B / K)",  # logistic: negative above B = K
        "-(kr * B) + kf * A",  # unary minus
    ],
)
def test_a_net_rate_reversible_law_is_refused(law):
    message = refused(flagged(law), "reversible reaction 'R1'", "subtracts a term",
                      "on its product 'B'", "two irreversible reactions")  # fmt: skip
    assert "law '" in message  # the law as written


@pytest.mark.parametrize(("level", "version"), [(2, 4), (3, 1)])
def test_a_minus_that_subtracts_no_term_is_not_a_net_rate(level, version):
    """Issue 54 (6): a minus inside exp(), in a power's exponent, or in a factor squared makes
    no negative term (Level 2 flags reactions reversible by default, so such files were
    refused): read as one-way, with the laws' values; a real net rate is still refused."""
    laws = ["kf * A * exp(-B / K)", "kf * A * K^(-B)", "kf * A * (1 - B / K)^2",
            "kf * A * sqrt(K - B)", "(-kf) * (-A) * (B + 1)"]  # fmt: skip
    with pytest.warns(SbmlWarning, match="5 reactions flagged reversible"):
        model = read_sbml_string(flagged(*laws, level=level, version=version))
    a, b, kf, k = 5.0, 3.0, 2.0, 10.0
    expected = [kf * a * math.exp(-b / k), kf * a * k**-b, kf * a * (1 - b / k) ** 2,
                kf * a * math.sqrt(k - b), kf * a * (b + 1)]  # fmt: skip
    got = model.propensities(torch.tensor([[5, 3, 1]]), torch.zeros(0))[0].tolist()
    assert got == pytest.approx(expected, rel=1e-14)
    refused(flagged("kf * A - kr * B", level=level, version=version),
            "reversible reaction 'R1'", "on its product 'B'")  # fmt: skip


@pytest.mark.parametrize(
    "law",
    [
        "kf * A + piecewise(-kr * B, A > 1, 0)",  # a piecewise's value is a term
        "kf * A * sinh(1 - B / K)",  # sinh keeps its argument's sign
        "kf * A * (1 - B / K)^3",  # an odd power keeps its base's sign
        "kf * A / (K - B)",  # a quotient has its denominator's sign
    ],
)
def test_a_negative_term_through_a_sign_keeping_construct_is_a_net_rate(law):
    refused(flagged(law), "reversible reaction 'R1'", "on its product 'B'")


def test_an_autocatalytic_law_is_not_a_net_rate():
    """StochSS's Brusselator flags 2 X + Y -> 3 X reversible with the mass-action law
    k * Y * X * (X - 1) / 2: its falling factorial subtracts a term in X, a product that the
    reaction also consumes, not a backward direction. Read as one-way, with the law's value;
    a term in a product it does not consume (Z) is still a net rate."""

    def autocatalytic(law: str) -> str:
        return simple(
            reactions=[Reaction("R1", law, {"X": 2, "Y": 1}, {"X": 3, "Z": 1}, reversible=True)],
            species=[Species("X", amount=7), Species("Y", amount=4), Species("Z", amount=2)],
            parameters={"k": 0.5, "kr": 0.1},
        )

    with pytest.warns(SbmlWarning, match="read as irreversible: 'R1'"):
        model = read_sbml_string(autocatalytic("k * Y * X * (X - 1) / 2"))
    rate = model.propensities(torch.tensor([[7, 4, 2]]), torch.zeros(0))
    assert rate.tolist() == [[0.5 * 4 * 7 * 6 / 2]]
    assert model.network.stoichiometry.tolist() == [[1, -1, 1]]
    refused(autocatalytic("k * Y * X * (X - 1) / 2 - kr * Z"), "reversible reaction 'R1'",
            "on its product 'Z'")  # fmt: skip


def test_every_net_rate_law_is_named_at_once():
    refused(flagged("kf * A - kr * B", "kf * A", "kf * A - kr * B"), "reactions 'R1'", "'R3'")


def test_a_negative_propensity_is_refused_by_both_simulators():
    """A reversible-flagged law that is one-way by the rule (its subtracted part depends on a
    reactant, not a product) but negative below A = 4 is read; the simulators refuse it when it
    turns negative (the compiled SSA names the reaction)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        model = read_sbml_string(flagged("kf * (A - 4)"))
    state = torch.tensor([[3, 0, 0]] * 4)
    with pytest.raises(ValueError, match="propensity of reaction 'R1' is negative"):
        CompiledSSA(model.kinetics).advance(state, torch.zeros(0), 1.0, CellStreams.from_seed(0, 4))
    with pytest.raises(ValueError, match="negative or non-finite"):
        gillespie(model.network, state, torch.zeros(4, 0), 1.0, propensity=model.torch_propensity)


# ----------------------------------------------------------------------------------------------
# laws that fire without their reactants


def activation_text() -> str:
    """Wilkinson's ch05-act.xml in a string: I -> A at alpha, A -> I at beta (laws that read
    neither I nor A), plus a dimerisation 2 P -> D at kd that reads no P, a catalysed
    conversion S + E -> E + T at kc * S (E consumed and made: not flagged) and a decay T -> 0
    at kt * T (reads its reactant)."""
    return simple(
        reactions=[
            Reaction("Activation", "alpha", {"I": 1}, {"A": 1}, local={"alpha": 0.5}),
            Reaction("Inactivation", "beta", {"A": 1}, {"I": 1}, local={"beta": 1.0}),
            Reaction("Dimerise", "kd", {"P": 2}, {"D": 1}, local={"kd": 3.0}),
            Reaction("Convert", "kc * S", {"S": 1, "E": 1}, {"E": 1, "T": 1}, local={"kc": 0.1}),
            Reaction("Decay", "kt * T", {"T": 1}, local={"kt": 0.2}),
        ],
        species=[
            Species("A", amount=0),
            Species("I", amount=1),
            Species("P", amount=3),
            Species("D", amount=0),
            Species("S", amount=5),
            Species("E", amount=0),
            Species("T", amount=1),
        ],
    )


def activation(**guard) -> tuple[SbmlModel, list[str]]:
    """:func:`activation_text` read, and the warnings that name its unguarded laws."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = read_sbml_string(activation_text(), **guard)
    messages = [str(w.message) for w in caught if issubclass(w.category, SbmlWarning)]
    return model, [m for m in messages if "without their reactants" in m]


def test_a_law_that_fires_without_its_reactants_is_guarded_and_named():
    """By default such a law is 0 while the species it uses up lacks the molecules (the SSA's
    propensity on the lattice of counts), its value as written otherwise; one warning names
    each such law, what it needs, and the setting that reads the laws as written. A catalyst
    (consumed and made) and a law reading its reactant are neither flagged nor changed."""
    model, messages = activation()
    assert len(messages) == 1, messages
    message = messages[0]
    for needle in ("3 kinetic laws that can fire without their reactants",
                   "'Activation' consumes I but its law 'alpha' does not read it (0 unless I >= 1)",
                   "'Dimerise' consumes P but its law 'kd' does not read it (0 unless P >= 2)",
                   "`reactant_guard: false` in the model yaml"):  # fmt: skip
        assert needle in message, needle
    assert "Convert" not in message and "Decay" not in message
    #                 A  I  P  D  S  E  T
    state = torch.tensor(
        [
            [0, 1, 2, 0, 5, 0, 1],  # I there, A not; P enough to dimerise
            [1, 0, 1, 0, 0, 1, 0],
        ]
    )  # A there, I not; one P; no S, T
    rates = model.propensities(state, torch.zeros(0))
    assert rates.tolist() == [[0.5, 0.0, 3.0, 0.5, 0.2], [0.0, 1.0, 0.0, 0.0, 0.0]]
    assert rates.tolist() == [
        [law.evaluate(row, ()) for law in model.kinetics.propensity_exprs] for row in state.tolist()
    ]


def test_reactant_guard_false_reads_the_laws_as_written():
    model, messages = activation(reactant_guard=False)
    assert len(messages) == 1 and "read as written (reactant_guard=False)" in messages[0]
    assert "0 unless" not in messages[0]
    rates = model.propensities(torch.tensor([[1, 0, 1, 0, 0, 1, 0]]), torch.zeros(0))
    assert rates.tolist() == [[0.5, 1.0, 3.0, 0.0, 0.0]]
    with pytest.raises(SbmlError, match="reactant_guard must be true or false, got 'yes'"):
        read_sbml_string(simple(), reactant_guard="yes")


def test_a_guarded_telegraph_has_the_telegraph_law():
    """Simulated by the compiled SSA, the guarded ch05-act telegraph never leaves {0, 1} and is
    active alpha / (alpha + beta) = 1/3 of the time at stationarity: 4,000 cells at 30 s (30
    relaxation times 1 / (alpha + beta)), within 4 binomial standard errors (0.030)."""
    model, _ = activation()
    n = 4000
    state = model.initial_states(n)
    out, _ = CompiledSSA(model.kinetics).advance(state, torch.zeros(0), 30.0,
                                                 CellStreams.from_seed(11, n))  # fmt: skip
    active, inactive = out[:, 0], out[:, 1]
    assert bool(((active == 0) | (active == 1)).all()) and bool((active + inactive == 1).all())
    share = active.double().mean().item()
    assert abs(share - 1 / 3) < 4 * math.sqrt((1 / 3) * (2 / 3) / n)


# ----------------------------------------------------------------------------------------------
# substance units (issue 37)


def test_substance_units_other_than_items_are_refused_with_the_fix():
    def model_in_moles(model):
        model.setSubstanceUnits("mole")

    text = simple(edit=model_in_moles, species=[Species("X", amount=10), Species("Y", amount=2)])
    message = refused(text, "species 'X' (mole), 'Y' (mole) have substance units other than")
    assert "substance_units: items" in message and "substance_units='items'" in message

    def grams(model):
        unit = model.createUnitDefinition()
        unit.setId("mass")
        u = unit.createUnit()
        u.setKind(libsbml.UNIT_KIND_GRAM)
        u.setExponent(1)
        u.setScale(0)
        u.setMultiplier(1)
        model.getSpecies("X").setSubstanceUnits("mass")

    refused(simple(edit=grams), "species 'X' (mass = ['gram']) has substance units")


def test_substance_units_items_reads_the_amounts_as_counts():
    """The StochSS toggle switch (substanceUnits="mole", all reactions flagged reversible with
    one-way laws) is read as published once the amounts are declared counts."""
    with pytest.raises(SbmlError, match="substance_units: items"):
        read_sbml(TOGGLE)
    with pytest.warns(SbmlWarning, match="'cu', 'cv', 'du', 'dv'"):
        model = read_sbml(TOGGLE, inputs=["alpha1"], substance_units="items")
    assert model.species == ("U", "V") and model.initial_state.tolist() == [10, 10]
    rates = model.propensities(torch.tensor([[3, 2]]), torch.tensor([0.5]))
    assert rates.tolist() == [[0.5 / (1 + 2**2), 1 / (1 + 3**2), 3.0, 2.0]]


def test_an_unknown_substance_units_option_is_refused():
    with pytest.raises(SbmlError, match="substance_units must be 'items'.*got 'moles'"):
        read_sbml_string(simple(), substance_units="moles")


def stochss_export(volume: float) -> str:
    """What StochSS / GillesPy2 write (its Brusselator, volume 1000): amounts in "mole",
    species without hasOnlySubstanceUnits in the compartment `vol` of the model's volume,
    and propensities over counts as kinetic laws (2 X + Y -> 3 X at k3 Y X (X - 1) / 2)."""

    def in_moles(model):
        model.setSubstanceUnits("mole")

    return build(
        "export",
        [Species("X", amount=20, only_substance=False, compartment="vol"),
         Species("Y", amount=10, only_substance=False, compartment="vol")],
        {"k1": 5.0, "k3": 0.5},
        [Reaction("make", "k1", {}, {"X": 1}),
         Reaction("cubic", "k3 * Y * X * (X - 1) / 2", {"X": 2, "Y": 1}, {"X": 3})],
        compartments={"vol": volume}, edit=in_moles,
    )  # fmt: skip


def test_fractional_amounts_are_refused_all_at_once_with_the_reason():
    """StochSS's Lotka-Volterra export (an ODE model: R = 0.0095, W = 0.008 "mole") was refused
    at its first species, without the file or what to do: now every such species, the file
    and the fix are named."""
    species = [Species("R", amount=0.0095), Species("W", amount=0.008), Species("Z", amount=3)]
    reactions = [Reaction("R1", "k * R", {"R": 1}), Reaction("R2", "k * W", {"W": 1})]
    message = refused(simple(species=species, reactions=reactions),
                      "<string>: the initial value of species 'R' (initialAmount 0.0095), 'W' "
                      "(initialAmount 0.008) are not a whole number of molecules",
                      "Rescale it to molecule counts")  # fmt: skip
    assert "'Z'" not in message


@pytest.mark.parametrize(("level", "version"), [(2, 4), (3, 1)])
def test_fractional_initial_concentrations_are_refused_as_fractional_amounts_are(level, version):
    """Issue 54 (5): 0.4 and 2.6 in a compartment of size 1 were read as [0, 3] without a word,
    while a fractional initialAmount was refused: both are now refused in one message, each
    with where its count came from; a whole count (3 x 2) reads."""
    species = [
        Species("A", concentration=0.4, only_substance=False),
        Species("B", concentration=2.6, only_substance=False),
        Species("C", amount=0.5),
        Species("D", concentration=3, only_substance=False),
    ]
    text = build("m", species, {"k": 1.0}, [Reaction("R1", "k * A", {"A": 1})],
                 compartments={"cell": 1.0}, level=level, version=version)  # fmt: skip
    message = refused(text, "the initial value of species 'A' (initialConcentration 0.4 x size "
                      "1 of 'cell' = 0.4), 'B' (initialConcentration 2.6 x size 1 of 'cell' = "
                      "2.6), 'C' (initialAmount 0.5) are not a whole number of molecules",
                      "Rescale it to molecule counts")  # fmt: skip
    assert "'D'" not in message
    whole = build("m", species[3:], {"k": 1.0}, [Reaction("R1", "k * D", {"D": 1})],
                  compartments={"cell": 2.0}, level=level, version=version)  # fmt: skip
    assert read_sbml_string(whole).initial_state.tolist() == [6]


def test_a_fractional_count_from_an_initial_assignment_is_refused():
    def half(model):
        model.createInitialAssignment().setSymbol("X")
        model.getInitialAssignment(0).setMath(parse("k / 4"))

    refused(simple(edit=half), "species 'X' (initial assignment, a count of 0.5) is not a whole")


def test_a_stochss_export_with_a_volume_says_how_its_species_read_in_laws():
    """Such an export with volume 1000 used to be read silently as concentrations (X / 1000 in
    every law: the cubic propensity 1e9 times too small, the Brusselator never oscillated):
    with the amounts declared counts, the reader now asks which reading the file means,
    naming the species and the compartment, and reads either as told; at volume 1 (the
    toggle switch) both agree and nothing is asked."""
    text = stochss_export(1000.0)
    with pytest.raises(SbmlError) as info:
        read_sbml_string(text, substance_units="items")
    message = str(info.value)
    for needle in ("'X', 'Y' in compartment 'vol' of size 1000", "species_in_laws: counts",
                   "species_in_laws: concentrations", "StochSS"):  # fmt: skip
        assert needle in message, f"{needle!r} not in {message!r}"
    state = torch.tensor([[20, 10]])
    counts = read_sbml_string(text, substance_units="items", species_in_laws="counts")
    assert counts.propensities(state, torch.zeros(0)).tolist() == [[5.0, 0.5 * 10 * 20 * 19 / 2]]
    conc = read_sbml_string(text, substance_units="items", species_in_laws="concentrations")
    x, y = 20 / 1000, 10 / 1000
    assert conc.propensities(state, torch.zeros(0))[0, 1].item() == pytest.approx(
        0.5 * y * x * (x - 1) / 2
    )
    unit = read_sbml_string(stochss_export(1.0), substance_units="items")
    assert unit.propensities(state, torch.zeros(0)).tolist() == [[5.0, 0.5 * 10 * 20 * 19 / 2]]
    with pytest.raises(SbmlError, match="species_in_laws must be 'counts'.*got 'amounts'"):
        read_sbml_string(text, substance_units="items", species_in_laws="amounts")


def test_species_in_laws_counts_reads_rules_and_events_as_counts():
    """With species_in_laws="counts" a species assignment rule's value is its count, not a
    concentration x size: Z = 2 X is 40 at X = 20 in a compartment of size 1000."""

    def rule(model):
        model.createAssignmentRule().setVariable("Z")
        model.getRule(0).setMath(parse("2 * X"))

    text = build("r", [Species("X", amount=20, only_substance=False, compartment="vol"),
                       Species("Z", amount=0, only_substance=False, compartment="vol")],
                 {"k": 1.0}, [Reaction("R1", "k * X", {"X": 1})],
                 compartments={"vol": 1000.0}, edit=rule)  # fmt: skip
    model = read_sbml_string(text, species_in_laws="counts")
    assert model.initial_state.tolist() == [20, 40]
    assert model.propensities(model.initial_state[None], torch.zeros(0)).tolist() == [[20.0]]


@pytest.mark.parametrize(("level", "version"), [(2, 4), (3, 1)])
def test_species_in_laws_counts_reads_initial_assignments_as_counts(level, version):
    """Issue 54 (4): under species_in_laws="counts" an initial assignment was read as a
    concentration (X = n0 = 5 in a compartment of size 10 gave 50 molecules): it is now the
    count, as in laws and rules, and so is a species an initial assignment reads (Y = 2 X)."""

    def assign(model):
        model.createInitialAssignment().setSymbol("X")
        model.getInitialAssignment("X").setMath(parse("n0"))
        model.createInitialAssignment().setSymbol("Y")
        model.getInitialAssignment("Y").setMath(parse("2 * X"))

    text = build("ia", [Species("X", amount=0, only_substance=False, compartment="vol"),
                        Species("Y", amount=0, only_substance=False, compartment="vol")],
                 {"k": 1.0, "n0": 5.0}, [Reaction("R1", "k * X", {"X": 1})],
                 compartments={"vol": 10.0}, edit=assign, level=level, version=version)  # fmt: skip
    assert read_sbml_string(text, species_in_laws="counts").initial_state.tolist() == [5, 10]
    # SBML's reading: X is the concentration 5 (50 molecules), Y = 2 x 5 = 10 (100 molecules)
    concentrations = read_sbml_string(text, species_in_laws="concentrations")
    assert concentrations.initial_state.tolist() == [50, 100]


def _assigned_only(model, how: str) -> None:
    """X is in no formula; a formula assigns it (initial assignment, event) or reads it (an
    initial assignment of the parameter n)."""
    if how == "assigned initially":
        model.createInitialAssignment().setSymbol("X")
        model.getInitialAssignment("X").setMath(parse("n0"))
    elif how == "read initially":
        p = model.createParameter()
        p.setId("n")
        p.setConstant(True)
        model.createInitialAssignment().setSymbol("n")
        model.getInitialAssignment("n").setMath(parse("2 * X"))
    else:
        add_event(model, "Y > 3", (("X", "n0"),))


@pytest.mark.parametrize("how", ["assigned initially", "read initially", "assigned by an event"])
def test_a_species_only_initial_assignments_or_events_use_is_asked_about(how):
    """Issue 54 (4): with the amounts declared counts and species_in_laws unset, a species in
    a compartment of size 10 that only an initial assignment or an event uses (the laws read
    only Y, of size 1) was read silently as SBML does; now the reader asks which is meant."""
    text = build("ia", [Species("X", amount=5, only_substance=False, compartment="vol"),
                        Species("Y", amount=5, only_substance=False)],
                 {"k": 1.0, "n0": 5.0},
                 [Reaction("R1", "k", {"X": 1}), Reaction("R2", "k * Y", {"Y": 1})],
                 compartments={"vol": 10.0, "cell": 1.0},
                 edit=lambda model: _assigned_only(model, how))  # fmt: skip
    with pytest.raises(SbmlError, match="species 'X' in compartment 'vol' of size 10 appear"):
        read_sbml_string(text, substance_units="items")
    read_sbml_string(text, substance_units="items", species_in_laws="counts")


# ----------------------------------------------------------------------------------------------
# libsbml's errors, all of them (issue 37)


def test_every_sbml_error_is_listed_with_its_line_up_to_ten():
    species = "".join(f'<species id="S{i}" compartment="c" size="2" units="item"/>\n'
                      for i in range(6))  # fmt: skip
    text = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<sbml xmlns="http://www.sbml.org/sbml/level3/version2/core" level="3" version="2">\n'
        '<model id="m">\n<listOfCompartments><compartment id="c" size="1"/>'
        "</listOfCompartments>\n"
        f"<listOfSpecies>\n{species}</listOfSpecies>\n</model>\n</sbml>\n"
    )
    # each species (lines 6-11) carries two attributes a species has not: 12 errors. The
    # attributes Level 3 requires and the file omits (the compartment's and each species'
    # `constant`, ...) had Level 2 defaults: filled, not listed (the next test)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        message = refused(text, "<string>: 12 SBML errors")
    lines = message.splitlines()
    assert len(lines) == 1 + 10 + 1 and lines[-1] == "  ... and 2 more"
    assert lines[1].startswith("  line 6, error [SBML component consistency]: ")
    assert "Attribute 'size' is not part of the definition of an SBML Level 3" in lines[1]
    assert "(see L3V2 Section 4.6)" in lines[1]
    assert all(line.startswith("  line ") and ", error [" in line for line in lines[1:11])
    assert "'units'" in lines[2] and lines[3].startswith("  line 7, ")
    assert "missing" not in message


#: the Level 3 attributes that had a Level 2 default, as a file may omit them
OMITTABLE = re.compile(
    r" (constant|boundaryCondition|hasOnlySubstanceUnits|fast|reversible|"
    r'useValuesFromTriggerTime|initialValue|persistent)="(true|false)"'
)


def test_level3_attributes_a_file_omits_are_read_with_level2_defaults():
    """A Level 3 file written with Level 2's habits (Wilkinson's models at their repository's
    head): every omitted attribute that had a Level 2 default is filled with it, listed in one
    warning, and the file reads as the complete one; a parameter a rule assigns is not
    constant; a reaction without ``reversible`` is reversible, so its one-way law warns too."""

    def edit(model):
        rule = model.createAssignmentRule()
        rule.setVariable("p")
        rule.setMath(parse("2 * k"))
        event = model.createEvent()
        event.setId("refill")
        event.setUseValuesFromTriggerTime(True)
        trigger = event.createTrigger()
        trigger.setMath(parse("X < 3"))
        trigger.setInitialValue(True)
        trigger.setPersistent(True)
        assign = event.createEventAssignment()
        assign.setVariable("X")
        assign.setMath(parse("10"))

    complete = simple(law="p * X", edit=edit, parameters={"p": None})
    omitted = OMITTABLE.sub("", complete)
    assert omitted != complete and 'constant="' not in omitted
    assert libsbml.readSBMLFromString(omitted).getNumErrors() >= 8
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        model = read_sbml_string(omitted)
    texts = [str(w.message) for w in record if issubclass(w.category, SbmlWarning)]
    filled = [t for t in texts if "Level 2's defaults" in t]
    assert len(filled) == 1, texts
    for needle in ("compartment constant=true (cell)",
                   "species boundaryCondition=false, constant=false, "
                   "hasOnlySubstanceUnits=false (X)",
                   "parameter constant=true (k)", "parameter constant=false (p)",
                   "reaction fast=false, reversible=true (R1)",
                   "speciesReference constant=true (R1:X)",
                   "event useValuesFromTriggerTime=true (refill)",
                   "trigger initialValue=true, persistent=true (refill)"):  # fmt: skip
        assert needle in filled[0], (needle, filled[0])
    assert any("flagged reversible with a one-way kinetic law" in t for t in texts)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        reference = read_sbml_string(complete)
    assert model.initial_state.tolist() == reference.initial_state.tolist()
    states = torch.arange(12).reshape(-1, 1)
    empty = torch.zeros(0)
    assert torch.equal(model.propensities(states, empty), reference.propensities(states, empty))
    assert [r.id for r in model.reactions] == [r.id for r in reference.reactions]


def test_the_textbooks_level3_file_reads_as_its_level2_file():
    """Wilkinson's auto-regulatory network at its repository's head (Level 3 Version 1, 37
    libsbml errors, all omitted attributes with Level 2 defaults) and the Level 2 file the
    example reads: one network (species, initial counts, reactions, propensities)."""
    head = AUTOREGULATION.parent / "head" / "ch07-ar-stoch.xml"
    assert libsbml.readSBMLFromFile(str(head)).getNumErrors() == 37
    with pytest.warns(SbmlWarning, match="read with SBML Level 2's defaults") as record:
        level3 = read_sbml(head, inputs=["Transcription.k2"])
    assert len(record) == 1 and "(8 in all)" in str(record[0].message)
    level2 = read_sbml(AUTOREGULATION, inputs=["Transcription.k2"])
    assert level3.network.species == level2.network.species
    assert level3.initial_state.tolist() == level2.initial_state.tolist() == [10, 0, 0, 0, 0]
    assert [r.id for r in level3.reactions] == [r.id for r in level2.reactions]
    states = torch.randint(0, 60, (200, 5), generator=torch.Generator().manual_seed(0))
    k2 = torch.tensor([0.03])
    assert torch.equal(level3.propensities(states, k2), level2.propensities(states, k2))


def test_malformed_xml_is_listed_at_its_line():
    text = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<sbml xmlns="http://www.sbml.org/sbml/level3/version2/core" level="3" version="2">\n'
        '<model id="m">\n<listOfSpecies>\n</model>\n</sbml>\n'
    )
    message = refused(text, "<string>: 1 SBML error ", "line 5, error [XML content]: XML tag ")
    assert "... and" not in message


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


@pytest.mark.parametrize(
    "path",
    [TOGGLE, AUTOREGULATION, AUTOREGULATION.parent / "head" / "ch07-ar-stoch.xml", TYSON,
     DIMERISATION, VILAR],
    ids=lambda path: f"{path.parent.name}/{path.name}",
)  # fmt: skip
def test_the_vendored_files_are_the_published_bytes(path: Path) -> None:
    """Each vendored public file is byte for byte what its README records (the sha256 of the
    file at the repository and commit named there): no editor, formatter or line-ending rule
    has touched it."""
    import hashlib
    import re

    readme = (path.parent if path.parent.name != "head" else path.parent.parent) / "README.md"
    text = " ".join(readme.read_text().split())  # the README wraps its lines
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    at = text.index(f"`{path.name}`") if path.parent.name != "head" else text.index("`head/")
    recorded = re.search(r"sha256 `([0-9a-f]{64})`", text[at:])
    assert recorded is not None and recorded.group(1) == digest


def test_the_tyson_oscillator_reads_its_laws_over_counts():
    """StochSS's Tyson oscillator (volume 300, amounts in "mole", laws written over counts that
    divide by `vol` themselves, all five reactions flagged reversible with one-way laws) is
    read as StochSS simulates it once the yaml says counts: X made at
    vol / (1 + (Y / vol)^2), Y made at kt X, degraded at kd Y + Y / (a0 + a1 y + a2 y^2) with
    y = Y / vol."""
    with pytest.raises(SbmlError, match="substance_units: items"):
        read_sbml(TYSON)
    with pytest.raises(SbmlError, match="'X', 'Y' in compartment 'vol' of size 300"):
        read_sbml(TYSON, substance_units="items")
    with pytest.warns(SbmlWarning, match="'rxn1', 'rxn2', 'rxn3', 'rxn4', 'rxn5'"):
        model = read_sbml(TYSON, inputs=["kt"], substance_units="items", species_in_laws="counts")
    assert model.species == ("X", "Y") and model.initial_state.tolist() == [196, 255]
    assert model.input_defaults == {"kt": 20.0}
    x, y = 150, 600  # y / vol = 2
    rates = model.propensities(torch.tensor([[x, y]]), torch.tensor([30.0]))
    expected = [300 / (1 + 2.0**2), x, 30.0 * x, y, y / (0.005 + 0.05 * 2 + 0.1 * 2**2)]
    torch.testing.assert_close(rates[0], torch.tensor(expected, dtype=rates.dtype))


def test_the_textbooks_dimerisation_reads_with_level2_defaults():
    """Wilkinson's dimerisation (Level 3 Version 1 without the attributes Level 3 requires: 11
    libsbml errors) is read with Level 2's defaults and one warning: 2 P -> P2 at
    c1 P (P - 1) / 2 (c1 local, the input), P2 -> 2 P at c2 P2, from 301 monomers."""
    assert libsbml.readSBMLFromFile(str(DIMERISATION)).getNumErrors() == 11
    with pytest.warns(SbmlWarning, match="read with SBML Level 2's defaults") as record:
        model = read_sbml(DIMERISATION, inputs=["Dimerisation.c1"])
    assert len(record) == 1
    assert model.species == ("P", "P2") and model.initial_state.tolist() == [301, 0]
    assert model.reaction_names == ("Dimerisation", "Dissociation")
    assert model.input_defaults == {"Dimerisation.c1": 0.00166}
    rates = model.propensities(torch.tensor([[41, 130]]), torch.tensor([0.002]))
    torch.testing.assert_close(rates[0], torch.tensor([0.002 * 41 * 40 / 2, 0.2 * 130],
                                                      dtype=rates.dtype))  # fmt: skip
