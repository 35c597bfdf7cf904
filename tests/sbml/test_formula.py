"""Hand-written formulas (a lump property, an input's formula) through libsbml's parser."""

from __future__ import annotations

import pytest
import torch

from surrogate.ctmc.kinetics import input_ref, species_ref, torch_function
from surrogate.sbml import SbmlError
from surrogate.sbml.formula import parse_formula

SPECIES = {name: species_ref(s, name) for s, name in enumerate(["S", "C", "N"])}


@pytest.mark.parametrize(
    "text",
    ["N >= 2 and S == 0", "N >= 2 && S == 0", "and(N >= 2, S == 0)", "not (N < 2 or S != 0)"],
)
def test_the_run_property_in_its_spellings(text: str) -> None:
    """Every spelling gives RUN iff N >= 2 and S == 0 on every motor configuration of 4."""
    counts = torch.tensor([[s, c, 4 - s - c] for s in range(5) for c in range(5 - s)])
    run = torch_function([parse_formula(text, SPECIES, "model.lump", "bool")])
    got = run(counts, torch.zeros(len(counts), 0))[:, 0]
    assert torch.equal(got, (counts[:, 2] >= 2) & (counts[:, 0] == 0))


def test_a_value_formula_over_inputs() -> None:
    symbols = {"F": input_ref(0, "F"), "L": input_ref(1, "L")}
    expr = parse_formula("1 / (1 + exp(F)) + 0 * L", symbols, "model.inputs.activity", "real")
    values = torch.tensor([[0.0, 1.0], [2.0, 0.5]], dtype=torch.float64)
    got = torch_function([expr])(torch.zeros(2, 0, dtype=torch.long), values)[:, 0]
    torch.testing.assert_close(got, torch.sigmoid(-values[:, 0]))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("N >= 2 and Q == 0", "unknown species 'Q'"),
        ("N + 2", "must be a condition"),
        ("__import__('os')", "cannot parse"),
        ("N >=", "cannot parse"),
        ("log(N) > 1", "cannot parse"),  # ambiguous: ln or log10
        ("", "expected a formula"),
        ("N > true", "must be real"),
    ],
)
def test_a_bad_formula_is_refused_by_name(text: str, message: str) -> None:
    with pytest.raises(SbmlError) as info:
        parse_formula(text, SPECIES, "model.lump", "bool", what="species")
    assert message in str(info.value) and "model.lump" in str(info.value)
