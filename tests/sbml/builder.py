"""Build small SBML documents from readable specs with libsbml (our own test models).

``python -m tests.sbml.builder`` (re)writes the DSMTS-style models in tests/data/sbml/; the
tests check that the committed files equal what this builder makes. Formulas are SBML L3
infix strings, converted to MathML by libsbml.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import libsbml

DATA = Path(__file__).resolve().parents[1] / "data" / "sbml"


@dataclass
class Species:
    id: str
    amount: float | None = None
    concentration: float | None = None
    only_substance: bool = True
    boundary: bool = False
    constant: bool = False
    compartment: str = "cell"


@dataclass
class Reaction:
    id: str
    law: str
    reactants: dict[str, float] = field(default_factory=dict)
    products: dict[str, float] = field(default_factory=dict)
    modifiers: Sequence[str] = ()
    local: dict[str, float] = field(default_factory=dict)
    reversible: bool = False


def _check(status: int, what: str) -> None:
    if status != libsbml.LIBSBML_OPERATION_SUCCESS:
        raise RuntimeError(
            f"libsbml failed to {what}: {libsbml.OperationReturnValue_toString(status)}"
        )


def _math(formula: str) -> libsbml.ASTNode:
    node = libsbml.parseL3Formula(formula)
    if node is None:
        raise ValueError(f"cannot parse {formula!r}: {libsbml.getLastParseL3Error()}")
    return node


def build(  # noqa: C901  # one branch per SBML part a test may give
    model_id: str,
    species: Sequence[Species],
    parameters: dict[str, float | None],
    reactions: Sequence[Reaction],
    *,
    compartments: dict[str, float] | None = None,
    functions: dict[str, str] | None = None,
    edit: Callable[[libsbml.Model], None] | None = None,
    level: int = 3,
    version: int = 1,
) -> str:
    """An SBML document (text). ``functions`` maps ids to ``lambda(...)`` formulas; ``edit``
    may change the model (add rules, events, ...) before it is written."""
    document = libsbml.SBMLDocument(level, version)
    model = document.createModel()
    model.setId(model_id)
    if level >= 3:
        model.setSubstanceUnits("item")
        model.setTimeUnits("second")
        model.setExtentUnits("item")
    for fid, formula in (functions or {}).items():
        f = model.createFunctionDefinition()
        f.setId(fid)
        _check(f.setMath(_math(formula)), f"set function {fid}")
    for cid, size in (compartments or {"cell": 1.0}).items():
        c = model.createCompartment()
        c.setId(cid)
        c.setSize(size)
        c.setConstant(True)
        c.setSpatialDimensions(3)
    for sp in species:
        s = model.createSpecies()
        s.setId(sp.id)
        s.setCompartment(sp.compartment)
        if sp.amount is not None:
            s.setInitialAmount(sp.amount)
        if sp.concentration is not None:
            s.setInitialConcentration(sp.concentration)
        s.setHasOnlySubstanceUnits(sp.only_substance)
        s.setBoundaryCondition(sp.boundary)
        s.setConstant(sp.constant)
    for pid, value in parameters.items():
        p = model.createParameter()
        p.setId(pid)
        if value is not None:
            p.setValue(value)
        p.setConstant(True)
    for rx in reactions:
        r = model.createReaction()
        r.setId(rx.id)
        r.setReversible(rx.reversible)
        if level < 3 or version < 2:
            r.setFast(False)
        for side, refs in (("reactant", rx.reactants), ("product", rx.products)):
            for sid, coeff in refs.items():
                ref = r.createReactant() if side == "reactant" else r.createProduct()
                ref.setSpecies(sid)
                ref.setStoichiometry(coeff)
                if level >= 3:
                    ref.setConstant(True)
        for sid in rx.modifiers:
            r.createModifier().setSpecies(sid)
        law = r.createKineticLaw()
        for pid, value in rx.local.items():
            p = law.createLocalParameter() if level >= 3 else law.createParameter()
            p.setId(pid)
            p.setValue(value)
        _check(law.setMath(_math(rx.law)), f"set the kinetic law of {rx.id}")
    if edit is not None:
        edit(model)
    return libsbml.writeSBMLToString(document)


# ----------------------------------------------------------------------------------------------
# the DSMTS-style models (our own files; parameters as in the suite's descriptions)


def birth_death() -> str:
    """dsmts-001-01 style: X -> 2X at lambda X, X -> 0 at mu X; X(0) = 100."""
    return build(
        "birth_death",
        [Species("X", amount=100)],
        {"Lambda": 0.1, "Mu": 0.11},
        [
            Reaction("Birth", "Lambda * X", {"X": 1}, {"X": 2}),
            Reaction("Death", "Mu * X", {"X": 1}),
        ],
    )


def immigration_death() -> str:
    """dsmts-002 style, with concentration semantics: compartment size 2, X read as a
    concentration (hasOnlySubstanceUnits false), laws written in amounts per time."""
    return build(
        "immigration_death",
        [Species("X", concentration=0.0, only_substance=False)],
        {"Alpha": 1.0, "Mu": 0.1},
        [
            Reaction("Immigration", "Alpha", {}, {"X": 1}),
            Reaction("Death", "Mu * X * cell", {"X": 1}),
        ],
        compartments={"cell": 2.0},
    )


def dimerisation() -> str:
    """dsmts-003 style: P + P -> P2 at k1 P (P - 1) / 2, P2 -> P + P at k2 P2; P(0) = 100."""
    return build(
        "dimerisation",
        [Species("P", amount=100), Species("P2", amount=0)],
        {"k1": 0.001, "k2": 0.01},
        [
            Reaction("Dimerisation", "k1 * P * (P - 1) / 2", {"P": 2}, {"P2": 1}),
            Reaction("Disassociation", "k2 * P2", {"P2": 1}, {"P": 2}),
        ],
    )


def hill_repression() -> str:
    """General kinetics: repressed production (a function definition with a Hill law, capped by
    a piecewise), Michaelis-Menten degradation, a constant boundary species as the gene."""
    return build(
        "hill_repression",
        [Species("G", amount=2, boundary=True, constant=True), Species("X", amount=0)],
        {"Vmax": 15.0, "K": 20.0, "Vd": 8.0},
        [
            Reaction(
                "Production",
                "piecewise(0, X >= 80, G * hill_rep(X, Vmax / 2, K, 2))",
                {},
                {"X": 1},
                modifiers=("G",),
            ),
            Reaction("Degradation", "Vd * X / (Km + X)", {"X": 1}, local={"Km": 10.0}),
        ],
        functions={"hill_rep": "lambda(x, v, k, n, v * k^n / (k^n + x^n))"},
    )


def induced_production() -> str:
    """An input parameter: production at kmax a^2 / (Ka^2 + a^2) for a per-cell activity a,
    first-order degradation (Poisson at all times from X(0) = 0)."""
    return build(
        "induced_production",
        [Species("X", amount=0)],
        {"activity": 0.5, "kmax": 40.0, "Ka": 0.5, "gamma": 0.5},
        [
            Reaction("Production", "kmax * activity^2 / (Ka^2 + activity^2)", {}, {"X": 1}),
            Reaction("Degradation", "gamma * X", {"X": 1}),
        ],
    )


MODELS: dict[str, Callable[[], str]] = {
    "birth_death": birth_death,
    "immigration_death": immigration_death,
    "dimerisation": dimerisation,
    "hill_repression": hill_repression,
    "induced_production": induced_production,
}


def main() -> None:
    """Write every model to tests/data/sbml/<name>.xml."""
    DATA.mkdir(parents=True, exist_ok=True)
    for name, make in MODELS.items():
        (DATA / f"{name}.xml").write_text(make())


if __name__ == "__main__":
    main()
