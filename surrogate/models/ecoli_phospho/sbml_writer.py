"""The phospho network as SBML: written from the constants (``network.xml``,
``network_amounts.xml``, :func:`main`) and read back with the receptor activity as the per-cell
input (:func:`load_network`)."""

from __future__ import annotations

from pathlib import Path

from surrogate.models.ecoli_phospho.constants import (
    PhosphoConstants,
    calibrated,
    mean_field_steady_state,
)
from surrogate.sbml import SbmlModel, read_sbml

NETWORK_PATH = Path(__file__).with_name("network.xml")
# The same model written with amounts only (explicit / 840 in the laws, no function definition):
# read identically by any SBML tool, e.g. GillesPy2 for the benchmark (scripts/bench_ssa.py).
NETWORK_AMOUNTS_PATH = Path(__file__).with_name("network_amounts.xml")


def network_sbml(c: PhosphoConstants | None = None, *, amounts: bool = False) -> str:
    """The network as an SBML L3V1 document (the text of ``network.xml`` for the defaults).

    Initial counts: the mean-field steady state at a*, motors (S, C, N) = (0, 1, 3). With
    ``amounts`` every species is a count in the laws (hasOnlySubstanceUnits) and the laws divide
    by ``nuM`` = 840 explicitly, with dG written out (``network_amounts.xml``): the same
    propensities, in the form that tools without concentration semantics read identically.
    """
    import libsbml

    c = c if c is not None and c.k_a is not None else calibrated(c)
    assert c.k_a is not None  # calibrated
    ap, yp = mean_field_steady_state(c, c.adapted_activity)
    n = c.n_per_um
    document = libsbml.SBMLDocument(3, 1)
    model = document.createModel()
    model.setId("ecoli_cheY_phosphorylation")
    model.setName("E. coli CheY phosphorylation and flagellar motors (surrogate issue 12)")
    model.setSubstanceUnits("item")
    model.setTimeUnits("second")
    model.setExtentUnits("item")
    if not amounts:
        unit = model.createUnitDefinition()
        unit.setId("uM_volume")  # the volume in which one molecule is 1 uM: 1 / (N_A 1e-6) litre
        u = unit.createUnit()
        u.setKind(libsbml.UNIT_KIND_LITRE)
        u.setExponent(1)
        u.setScale(0)
        u.setMultiplier(1.0 / (6.02214076e23 * 1e-6))
    if not amounts:
        fn = model.createFunctionDefinition()
        fn.setId("dG")
        fn.setMath(libsbml.parseL3Formula("lambda(y, g0, g1, KD, g0 / 4 - g1 / 2 * y / (y + KD))"))
    compartment = model.createCompartment()
    compartment.setId("cell")
    compartment.setSize(1.0 if amounts else n)
    if not amounts:
        compartment.setUnits("uM_volume")
    compartment.setSpatialDimensions(3)
    compartment.setConstant(True)
    counts = {
        "S": (0, True),
        "C": (1, True),
        "N": (c.n_motors - 1, True),
        "CheA": (round((c.cheA_total - ap) * n), False),
        "CheAp": (round(ap * n), False),
        "CheY": (round((c.cheY_total - yp) * n), False),
        "CheYp": (round(yp * n), False),
        "CheZ": (round(c.cheZ * n), False),
    }
    for sid, (amount, only_substance) in counts.items():
        sp = model.createSpecies()
        sp.setId(sid)
        sp.setCompartment("cell")
        sp.setInitialAmount(amount)
        # motors: counts; proteins: uM in laws (unless amounts)
        sp.setHasOnlySubstanceUnits(only_substance or amounts)
        fixed = sid == "CheZ"
        sp.setBoundaryCondition(fixed)
        sp.setConstant(fixed)
    parameters = {
        "activity": (c.adapted_activity, "receptor activity a(m, L): the per-cell input"),
        "kA": (c.k_a, "CheA autophosphorylation at full activity, 1/s (calibrated)"),
        "kY": (c.k_y, "phosphotransfer CheA-P -> CheY, 1/(uM s)"),
        "kZ": (c.k_z, "CheZ phosphatase, 1/(uM s) (kZ [CheZ] = 30/s)"),
        "gY": (c.gamma_y, "CheZ-independent CheY-P hydrolysis, 1/s"),
        "mu": (c.mu, "S -> C, 1/s"),
        "omega": (c.omega, "motor switching frequency scale, 1/s"),
        "g0": (c.g0, "kT"),
        "g1": (c.g1, "kT"),
        "KD": (c.k_d, "CheY-P dissociation constant at the motor, uM"),
    }
    if amounts:
        parameters["nuM"] = (n, "molecules per uM")
    for pid, (value, note) in parameters.items():
        p = model.createParameter()
        p.setId(pid)
        p.setName(note)
        p.setValue(float(value))
        p.setConstant(True)
    k_plus = "omega * exp(dG(CheYp, g0, g1, KD))"
    k_minus = "omega * exp(-dG(CheYp, g0, g1, KD))"
    laws = {
        "autophosphorylation": "kA * activity * CheA * cell",
        "phosphotransfer": "kY * CheAp * CheY * cell",
        "dephosphorylation": "(kZ * CheZ + gY) * CheYp * cell",
    }
    if amounts:
        dg = "(g0 / 4 - g1 / 2 * (CheYp / nuM) / (CheYp / nuM + KD))"
        k_plus, k_minus = f"omega * exp({dg})", f"omega * exp(-{dg})"
        laws = {
            "autophosphorylation": "kA * activity * CheA",
            "phosphotransfer": "kY * CheAp * CheY / nuM",
            "dephosphorylation": "(kZ * CheZ / nuM + gY) * CheYp",
        }
    reactions = [
        ("autophosphorylation", {"CheA": 1}, {"CheAp": 1}, (), laws["autophosphorylation"]),
        (
            "phosphotransfer",
            {"CheAp": 1, "CheY": 1},
            {"CheA": 1, "CheYp": 1},
            (),
            laws["phosphotransfer"],
        ),
        (
            "dephosphorylation",
            {"CheYp": 1},
            {"CheY": 1},
            ("CheZ",),
            laws["dephosphorylation"],
        ),
        ("S_to_C", {"S": 1}, {"C": 1}, (), "mu * S"),
        ("C_to_N", {"C": 1}, {"N": 1}, ("CheYp",), f"{k_plus} * C"),
        ("S_to_N", {"S": 1}, {"N": 1}, ("CheYp",), f"{k_plus} * S"),
        ("N_to_S", {"N": 1}, {"S": 1}, ("CheYp",), f"{k_minus} * N"),
    ]
    for rid, consumed, produced, modifiers, law in reactions:
        r = model.createReaction()
        r.setId(rid)
        r.setReversible(False)
        r.setFast(False)
        for side, refs in ((r.createReactant, consumed), (r.createProduct, produced)):
            for sid, coeff in refs.items():
                ref = side()
                ref.setSpecies(sid)
                ref.setStoichiometry(coeff)
                ref.setConstant(True)
        for sid in modifiers:
            r.createModifier().setSpecies(sid)
        r.createKineticLaw().setMath(libsbml.parseL3Formula(law))
    return libsbml.writeSBMLToString(document)


def load_network(path: str | Path = NETWORK_PATH) -> SbmlModel:
    """Read the shipped network with ``activity`` as the per-cell input."""
    return read_sbml(path, inputs=["activity"])


def main() -> None:
    """Write ``network.xml`` from the default constants (``python -m
    surrogate.models.ecoli_phospho``)."""
    from surrogate.io import write_text

    write_text(NETWORK_PATH, network_sbml())
    write_text(NETWORK_AMOUNTS_PATH, network_sbml(amounts=True))


__all__ = ["NETWORK_AMOUNTS_PATH", "NETWORK_PATH", "load_network", "main", "network_sbml"]
