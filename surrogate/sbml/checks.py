"""The SBML reader's first layer: what it holds of a libsbml Model (:class:`ReaderChecks`) and
its checks of the model as a whole (unsupported constructs, inputs, substance units, how species
read in formulas), each refusing with every offender in one message (see
:mod:`surrogate.sbml.reader`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import libsbml

from surrogate.sbml.errors import SbmlError


class ReaderChecks:
    """The model's elements by id, and the checks of the model as a whole (the reader's base)."""

    def __init__(
        self,
        model: libsbml.Model,
        inputs: tuple[str, ...],
        label: str,
        substance_units: str | None = None,
        species_in_laws: str | None = None,
        reactant_guard: bool = True,
    ) -> None:
        self.model = model
        self.label = label
        self.inputs = inputs
        self.substance_units = substance_units
        self.species_in_laws = species_in_laws
        self.reactant_guard = reactant_guard
        self.local_parameters = {
            r.getId(): {p.getId(): p for p in _local_parameters(r)}
            for r in model.getListOfReactions()
        }
        self.functions = {f.getId(): f for f in model.getListOfFunctionDefinitions()}
        self.species = list(model.getListOfSpecies())
        self.species_index = {sp.getId(): s for s, sp in enumerate(self.species)}
        self.compartments = {c.getId(): c for c in model.getListOfCompartments()}
        self.parameters = {p.getId(): p for p in model.getListOfParameters()}
        self.initial_assignments = {a.getSymbol(): a for a in model.getListOfInitialAssignments()}
        self.assignment_rules: dict[str, libsbml.Rule] = {}
        self.species_rules: dict[str, libsbml.Rule] = {}
        self._values: dict[str, float] = {}
        self._resolving: list[str] = []

    # -- checks of the model as a whole ---------------------------------------------------

    def _refuse_unsupported(self) -> None:
        """Refuse every construct the stochastic reading has no meaning for, all of them in one
        message (rate and algebraic rules, rules on compartments, event delays, priorities
        and assignments to other than species, conversion factors, required packages):
        ``unsupported construct(s): delay of event 'E0'; rate rule for 't'; package 'distrib'
        (required)``."""
        model = self.model
        found: list[str] = self._unsupported_in_events()
        if model.isSetConversionFactor():
            found.append(f"model conversionFactor {model.getConversionFactor()!r}")
        for rule in model.getListOfRules():
            if rule.isAlgebraic():
                math_text = libsbml.formulaToL3String(rule.getMath())
                found.append(f"algebraic rule {rule.getId() or math_text!r}")
                continue
            variable = rule.getVariable()
            if rule.isRate():
                found.append(f"rate rule for {variable!r}")
            elif variable in self.species_index:
                self.species_rules[variable] = rule
            elif variable not in self.parameters:
                found.append(f"assignment rule for {variable!r} (only parameters and species may "
                             "be assigned by rules; compartments are fixed)")  # fmt: skip
            elif variable in self.inputs:
                raise SbmlError(
                    f"{self.label}: parameter {variable!r} is declared an input but is "
                    "assigned by a rule"
                )
            else:
                self.assignment_rules[variable] = rule
        for sp in self.species:
            if sp.isSetConversionFactor():
                found.append(f"conversionFactor on species {sp.getId()!r}")
        document = model.getSBMLDocument()
        # packages the file declares itself (libsbml adds internal ones, e.g. L3V2's extended
        # math under the core namespace)
        declared = document.getNamespaces()
        uris = {declared.getURI(i) for i in range(declared.getNumNamespaces())}
        uris.discard(document.getSBMLNamespaces().getURI())
        for i in range(document.getNumPlugins() if model.getLevel() >= 3 else 0):  # L3 packages
            plugin = document.getPlugin(i)
            name = plugin.getPackageName()
            if plugin.getURI() in uris and document.getPackageRequired(name):
                found.append(f"package {name!r} (required by the file)")
        if found:
            plural = "s" if len(found) > 1 else ""
            raise SbmlError(f"{self.label}: unsupported construct{plural}: " + "; ".join(found))

    def _check_inputs(self) -> None:
        """Each input is a global parameter not shadowed by a reaction's local parameter of the
        same id, or an existing ``reaction.local`` parameter; unique; never initially assigned."""
        if len(set(self.inputs)) != len(self.inputs):
            raise SbmlError(f"{self.label}: inputs must be unique, got {list(self.inputs)}")
        local_names = [f"{rid}.{pid}" for rid, ps in self.local_parameters.items() for pid in ps]
        for name in self.inputs:
            rid, dot, pid = name.partition(".")
            if dot and rid in self.local_parameters:
                if pid not in self.local_parameters[rid]:
                    raise SbmlError(
                        f"{self.label}: input {name!r}: reaction {rid!r} has no local parameter "
                        f"{pid!r}; its local parameters: {sorted(self.local_parameters[rid])}"
                    )
                continue
            if name not in self.parameters:
                where = f"reaction {rid!r} does not exist; " if dot else ""
                raise SbmlError(
                    f"{self.label}: input {name!r} is not a global parameter of the model nor a "
                    f"local one (<reaction id>.<parameter id>): {where}global parameters: "
                    f"{_listing(sorted(self.parameters))}; local parameters: "
                    f"{_listing(local_names)}"
                )
            if name in self.initial_assignments:
                raise SbmlError(f"{self.label}: input parameter {name!r} has an initial assignment")
            shadowing = [rid for rid, ps in self.local_parameters.items() if name in ps]
            if shadowing:
                listed = ", ".join(f"{rid!r}" for rid in shadowing)
                raise SbmlError(
                    f"{self.label}: input {name!r} is a global parameter, but reaction"
                    f"{'s' if len(shadowing) > 1 else ''} {listed} declare"
                    f"{'' if len(shadowing) > 1 else 's'} a local parameter {name!r} that "
                    f"shadows it in its kinetic law, where the input would have no effect; "
                    f"name the local one as the input ({shadowing[0]}.{name}), or rename or "
                    "remove the local parameter in the file"
                )

    def _check_substance_units(self) -> None:
        """Species amounts must be in items (or unset / dimensionless) unless the reader was told
        to read them as counts (``substance_units="items"``); every offender in one message."""
        if self.substance_units == "items":
            return
        offenders: list[str] = []
        for sp in self.species:
            units = sp.getSubstanceUnits() or self.model.getSubstanceUnits()
            if not units or units in ("item", "dimensionless"):
                continue
            if units in ("mole", "gram", "kilogram", "avogadro"):
                kinds = [units]
            else:
                definition = self.model.getUnitDefinition(units)
                if definition is None:
                    continue
                kinds = [
                    libsbml.UnitKind_toString(u.getKind()) for u in definition.getListOfUnits()
                ]
            if any(k not in ("item", "dimensionless") for k in kinds):
                shown = units if kinds == [units] else f"{units} = {kinds}"
                offenders.append(f"{sp.getId()!r} ({shown})")
        if offenders:
            raise SbmlError(
                f"{self.label}: species {', '.join(offenders)} "
                f"{'have' if len(offenders) > 1 else 'has'} substance units other than items; "
                "the stochastic reading needs molecule counts. If the amounts are counts (as "
                "StochSS and other stochastic exporters write them), read them as such: "
                "`substance_units: items` in the model yaml, or "
                "read_sbml(..., substance_units='items')"
            )

    def _symbol_is_amount(self, sp: libsbml.Species) -> bool:
        """Whether the symbol of ``sp`` in a formula is its count (``hasOnlySubstanceUnits``,
        or ``species_in_laws="counts"``), not its concentration."""
        return sp.getHasOnlySubstanceUnits() or self.species_in_laws == "counts"

    def _check_species_in_laws(self) -> None:
        """With amounts declared counts (``substance_units="items"``, a StochSS export's mark)
        and ``species_in_laws`` unset, refuse a file whose formulas (kinetic laws, rules, events,
        initial assignments) read or assign a species without ``hasOnlySubstanceUnits`` in a
        compartment whose size is not 1: there SBML's reading (a concentration) and the
        exporter's (a count) give different propensities or initial counts."""
        if self.substance_units != "items" or self.species_in_laws is not None:
            return
        maths = [
            r.getKineticLaw().getMath()
            for r in self.model.getListOfReactions()
            if r.getKineticLaw() is not None and r.getKineticLaw().isSetMath()
        ]
        maths += [r.getMath() for r in self.model.getListOfRules() if r.isSetMath()]
        maths += [a.getMath() for a in self.initial_assignments.values() if a.isSetMath()]
        # a species a formula gives the value of reads the same way as one a formula reads
        used = {*self.initial_assignments, *(r.getVariable() for r in self.model.getListOfRules())}
        for event in self.model.getListOfEvents():
            trigger = event.getTrigger()
            if trigger is not None and trigger.isSetMath():
                maths.append(trigger.getMath())
            maths += [a.getMath() for a in event.getListOfEventAssignments() if a.isSetMath()]
            used |= {a.getVariable() for a in event.getListOfEventAssignments()}
        for node in maths:
            used |= _names(node)
        for definition in self.functions.values():  # a species named inside a function
            if definition.isSetMath():
                used |= _names(definition.getMath())
        ambiguous: dict[str, list[str]] = {}
        for sp in self.species:
            if sp.getId() not in used or sp.getHasOnlySubstanceUnits():
                continue
            compartment = self.compartments.get(sp.getCompartment())
            if compartment is None or not compartment.isSetSize():
                continue
            if compartment.getSize() != 1:
                ambiguous.setdefault(sp.getCompartment(), []).append(sp.getId())
        if not ambiguous:
            return
        where = "; ".join(
            f"{', '.join(repr(i) for i in ids)} in compartment {cid!r} of size "
            f"{self.compartments[cid].getSize():g}"
            for cid, ids in ambiguous.items()
        )
        raise SbmlError(
            f"{self.label}: species {where} appear in kinetic laws (or rules, events, initial "
            "assignments) without "
            "hasOnlySubstanceUnits, so SBML reads each there as its concentration (count / "
            "size), while StochSS and GillesPy2 write their propensities over counts (e.g. "
            "`k * X * (X - 1) / 2`) and export them so: the two readings give different "
            "propensities (and initial counts). Say which the file means in the model yaml: `species_in_laws: "
            "counts` (a StochSS or GillesPy2 export, as they simulate it) or `species_in_laws: "
            "concentrations` (SBML's reading); or read_sbml(..., species_in_laws=...)"
        )

    def _input_default(self, name: str) -> float:
        """The file's value of an input parameter (global or ``reaction.local``), NaN if unset."""
        rid, dot, pid = name.partition(".")
        return file_value(self.local_parameters[rid][pid] if dot else self.parameters[name])

    def _unsupported_in_events(self) -> list[str]:
        """What events do that is not simulated: delays, priorities, assignments to other than
        variable species (for the refusal's one message)."""
        found = []
        for k, event in enumerate(self.model.getListOfEvents()):
            name = event.getId() or f"#{k + 1}"
            if event.isSetDelay():
                found.append(f"delay of event {name!r}")
            if event.isSetPriority():
                found.append(f"priority of event {name!r}")
            for assignment in event.getListOfEventAssignments():
                var = assignment.getVariable()
                if var in self.species_index:
                    if self.species[self.species_index[var]].getConstant():
                        found.append(f"event {name!r} assigning constant species {var!r}")
                    continue
                kind = "parameter" if var in self.parameters else (
                    "compartment" if var in self.compartments else "symbol")  # fmt: skip
                found.append(f"event {name!r} assigning {kind} {var!r} (events may assign "
                             "species only)")  # fmt: skip
        return found


def file_value(parameter: libsbml.Parameter) -> float:
    """A parameter's ``value`` attribute as written, NaN where unset."""
    return float(parameter.getValue()) if parameter.isSetValue() else math.nan


def _local_parameters(reaction: libsbml.Reaction) -> list:
    """The local (kinetic-law) parameters of a reaction (Level 3 localParameters, Level 2
    parameters), in file order; none without a law."""
    law = reaction.getKineticLaw()
    if law is None:
        return []
    if reaction.getLevel() >= 3:
        return list(law.getListOfLocalParameters())
    return list(law.getListOfParameters())


def _listing(names: Sequence[str], limit: int = 20) -> str:
    """``names`` for a message: all of them, or the first ``limit`` and a count."""
    if len(names) <= limit:
        return str(list(names))
    return f"{list(names[:limit])} and {len(names) - limit} more"


def _names(node: libsbml.ASTNode) -> set[str]:
    """The names (``ci`` symbols) a MathML tree reads."""
    out = {node.getName()} if node.isName() and node.getName() else set()
    for i in range(node.getNumChildren()):
        out |= _names(node.getChild(i))
    return out


__all__ = ["ReaderChecks", "file_value"]
