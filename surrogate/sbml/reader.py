"""Read an SBML model as a stochastic reaction network with general kinetics.

Reading (the discrete stochastic interpretation of SBML, as in the SBML discrete stochastic
model test suite):

* Species are molecule counts. A species' initial count is the value of its initial
  assignment (a count, or a concentration x compartment size, as its symbol reads in laws),
  else its ``initialAmount``, else ``initialConcentration x compartment size``; one that is
  not a whole number of molecules (within ``WHOLE_TOLERANCE``) is refused, whichever gave it,
  every such species in one message naming it and its value. Substance units must be items (or unset / dimensionless): a model in
  other units (moles, grams) is refused rather than silently rescaled, every such species in
  one message, unless the caller declares the amounts counts (``substance_units="items"``, the
  yaml's ``substance_units: items``): exporters of stochastic models such as StochSS write
  ``substanceUnits="mole"`` and mean counts.
* In a kinetic law a species symbol is its amount when ``hasOnlySubstanceUnits`` is true, else
  its concentration ``amount / compartment size``. The kinetic law's value is the reaction's
  propensity (events per unit time). StochSS and GillesPy2 export their propensities, written
  over counts (``rate3 * Y * X * (X - 1) / 2``), as kinetic laws of species without
  ``hasOnlySubstanceUnits`` in a compartment of the model's volume: ``species_in_laws="counts"``
  (the yaml's ``species_in_laws: counts``) reads every species symbol in laws, rules and events
  as its count, initial assignments included; ``"concentrations"`` states SBML's reading.
  Where the two differ (such a species read or assigned by a formula, its compartment's size
  not 1) and the amounts were declared counts
  (``substance_units="items"``, the mark of such an export) without saying which, the file is
  refused naming the species, the compartment and both settings.
* Boundary-condition and constant species are never changed by reactions.
* Parameters named in ``inputs`` are per-cell inputs, supplied with the state at every window;
  every other parameter and every compartment size is a constant. An input is a global
  parameter by its id (``k``) or a reaction's local (kinetic-law) parameter as
  ``<reaction id>.<parameter id>`` (``Transcription.k2``; SBML ids hold no dot, so the name is
  never ambiguous). Local parameters shadow globals of the same id in their law, so a global
  input that some reaction shadows is refused (naming the input, the reactions and the fix):
  there it would have no effect. An input naming neither is refused with the lists of global
  and local parameters. Function definitions are inlined. Assignment rules whose variable is a
  parameter are inlined where the parameter is used (they are functions of the state).
* A reaction flagged reversible is one propensity only if its law is one-way. The rule, on the
  law after inlining (functions, rules, local parameters): read the law as a signed sum of
  products (its expansion, never built) through sums, differences, negations, products,
  quotients, a power's base, min / max, a piecewise's values (its conditions a positive
  factor) and the functions that keep their argument's sign (sinh, tanh, arcsin, arctan,
  floor, ceiling); any other function (exp, sqrt, abs, ln, ...), a power's exponent and an
  even integer power are one positive factor, whatever minus they hold. The law is a *net
  rate* (forward minus backward) when some negative term depends on a product species of the
  reaction (boundary species included), e.g. ``kf * A - kr * B`` or ``kf * A + (-kr) * B``
  with product ``B``, or ``k * A * (1 - B / K)``; it is refused, naming the reaction, its law
  and the product (write the reaction as two irreversible ones). Otherwise the law is one-way
  (e.g. ``alpha / (1 + V^beta)``, ``mu * U``, ``kf * A * exp(-B / K)``, ``kf * A * K^(-B)``,
  or ``k1 * A - k2 * C`` with ``C`` not a product) and the reaction is read as irreversible,
  with one :class:`~surrogate.sbml.errors.SbmlWarning` listing every such reaction. A
  propensity that turns out negative at run time is refused by both simulators (the compiled
  SSA names the reaction).
* An assignment rule on a species makes its count that function of the others (an amount, or
  a concentration x size), recomputed after every reaction and event and at every window's
  start; wherever the species is used, the rule's formula is inlined. Its initial value is
  the rule's at the initial state.
* Events (:mod:`surrogate.ctmc.events`, simulated exactly by both SSAs) assign species when
  their trigger goes from false to true, with the trigger's ``initialValue`` and
  ``persistent`` and the event's ``useValuesFromTriggerTime``; a trigger may read the time
  csymbol only compared with a formula free of time (``t >= 25``).

A compartment may lack a size (Level 3, every species an amount) unless something needs it.

A document with SBML errors (libsbml's reading) is refused listing each error (the first ten and
a count of the rest) with its line, severity, libsbml's message, the detail that names the
element, and the section of the SBML specification to check. Attributes Level 3 requires that
had a Level 2 default (species ``constant``, reaction ``fast``, ...), omitted by exporters that
write Level 3 with Level 2's habits, are read with that default and listed in one
:class:`~surrogate.sbml.errors.SbmlWarning` (:mod:`surrogate.sbml.defaults`).

Refused, with an :class:`~surrogate.sbml.errors.SbmlError` naming the construct and the element
id (every model-level construct of a file in one message): rate and algebraic rules,
assignment rules on compartments, event delays and priorities, event assignments to anything
but a species, delays, the time csymbol outside event triggers and assignments, rateOf, fast
reactions, reversible reactions with a net-rate law (above), non-integer or
variable stoichiometry, initial assignments that depend on something other than constants,
conversion factors, packages the file marks required (e.g. ``distrib``), unknown MathML.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import libsbml
import torch
from torch import Tensor

from surrogate.ctmc.events import Event, SpeciesRule, whole_counts
from surrogate.ctmc.kinetics import Expr, Kinetics, call, const, input_ref, species_ref, time_ref
from surrogate.ctmc.network import ReactionNetwork
from surrogate.sbml.defaults import fill_level2_defaults
from surrogate.sbml.errors import SbmlError, SbmlWarning
from surrogate.sbml.math import convert

__all__ = [
    "SPECIES_IN_LAWS",
    "SUBSTANCE_UNITS",
    "SbmlModel",
    "SbmlReaction",
    "read_sbml",
    "read_sbml_string",
]

#: values of ``substance_units``: None (amounts must be in items) or "items" (read the file's
#: amounts as molecule counts whatever units it declares)
SUBSTANCE_UNITS = (None, "items")
#: values of ``species_in_laws``: None (SBML's reading: a species symbol in a formula is its
#: concentration unless ``hasOnlySubstanceUnits``; refused where ambiguous, see the module
#: docstring), "concentrations" (the same, stated) or "counts" (every species symbol is its
#: count, as StochSS and GillesPy2 write propensities)
SPECIES_IN_LAWS = (None, "concentrations", "counts")
#: libsbml errors listed in full before the rest are only counted
MAX_LISTED_ERRORS = 10


@dataclass(frozen=True)
class SbmlReaction:
    """One reaction as written in the file.

    Attributes:
        id: The reaction id (also its name in the network).
        reactants: ``{species id: stoichiometry}`` consumed (boundary species included).
        products: ``{species id: stoichiometry}`` produced (boundary species included).
        modifiers: Ids of the modifier species.
    """

    id: str
    reactants: Mapping[str, int]
    products: Mapping[str, int]
    modifiers: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class SbmlModel:
    """An SBML model read as a stochastic reaction network.

    Attributes:
        id: The model id.
        kinetics: Network (species in file order; net stoichiometry, zero for fixed species)
            and one propensity expression per reaction over counts and ``input_names``.
        initial_state: ``(S,)`` int64 initial molecule counts.
        constants: Values of every global parameter that is not an input and of every
            compartment size (by id; NaN for a compartment without a size, legal in Level 3
            where no law, initial value or formula needs it).
        input_defaults: The value the file gives each input parameter (NaN if unset).
        fixed_species: Ids of boundary-condition or constant species.
        reactions: The reactions as written (including fixed species and modifiers).
        source: The file read, or ``None`` for a string.
        species_compartments: The compartment of each species (by id).
        parameters: The file's value of every global parameter by id, inputs included (NaN
            where it has none or a rule assigns it): what the file says, for reports.
        local_parameters: The file's value of every reaction-local (kinetic-law) parameter,
            by ``<reaction id>.<parameter id>`` (NaN where it has none), inputs included.
    """

    id: str
    kinetics: Kinetics
    initial_state: Tensor
    constants: Mapping[str, float]
    input_defaults: Mapping[str, float]
    fixed_species: tuple[str, ...]
    reactions: tuple[SbmlReaction, ...]
    source: Path | None = None
    species_compartments: Mapping[str, str] = field(default_factory=dict)
    parameters: Mapping[str, float] = field(default_factory=dict)
    local_parameters: Mapping[str, float] = field(default_factory=dict)

    @property
    def network(self) -> ReactionNetwork:
        """The reaction network (species, reactants, products, stoichiometry)."""
        return self.kinetics.network

    @property
    def species(self) -> tuple[str, ...]:
        """Species ids, in state column order."""
        return self.kinetics.network.species

    @property
    def reaction_names(self) -> tuple[str, ...]:
        """Reaction ids, in propensity column order."""
        return self.kinetics.network.reaction_names

    @property
    def input_names(self) -> tuple[str, ...]:
        """Per-cell input names, in inputs column order."""
        return self.kinetics.input_names

    @property
    def numba_source(self) -> str:
        """Scalar per-cell ``propensities(x, p, a)`` source for numba (see ``Kinetics``)."""
        return self.kinetics.numba_source

    @property
    def torch_propensity(self) -> Callable[[Tensor, Tensor], Tensor]:
        """Unchecked ``propensities(state (n, S), inputs (n, P)) -> (n, R)`` float64."""
        return self.kinetics.torch_propensity

    def propensities(self, state: Tensor, inputs: Tensor) -> Tensor:
        """Checked propensities.

        Args:
            state: ``n x S`` integer counts.
            inputs: ``n x P`` float inputs (``(P,)`` shared by all cells).

        Returns:
            ``n x R`` float64 propensities on the device of ``state``.
        """
        return self.kinetics.propensities(state, inputs)

    def default_inputs(self) -> Tensor:
        """``(P,)`` float64 input values given in the file (raises if one is unset)."""
        values = [self.input_defaults[name] for name in self.input_names]
        missing = [n for n, v in zip(self.input_names, values, strict=True) if math.isnan(v)]
        if missing:
            raise SbmlError(f"model {self.id!r}: inputs {missing} have no value in the file")
        return torch.tensor(values, dtype=torch.float64)

    def compartment_of(self, species: str) -> str:
        """The id of the compartment ``species`` lives in."""
        return self.species_compartments[species]

    def initial_states(self, n: int) -> Tensor:
        """``n x S`` int64: the initial state repeated for ``n`` cells."""
        return self.initial_state.unsqueeze(0).expand(n, -1).clone()


def read_sbml(
    path: str | Path,
    inputs: Sequence[str] = (),
    substance_units: str | None = None,
    species_in_laws: str | None = None,
) -> SbmlModel:
    """Read an SBML file (levels 2 and 3) as a stochastic reaction network.

    Args:
        path: The ``.xml`` / ``.sbml`` file.
        inputs: Parameters supplied per cell at run time (``inputs (n, P)`` columns in this
            order): a global parameter by its id (``"k"``), or a reaction's local
            (kinetic-law) parameter as ``"<reaction id>.<parameter id>"``
            (``"Transcription.k2"``); all other parameters are constants.
        substance_units: ``None`` (species amounts must be in items, else refused) or
            ``"items"``: read the amounts as molecule counts whatever substance units the file
            declares (exporters of stochastic models such as StochSS write ``"mole"`` and mean
            counts).
        species_in_laws: How a species symbol without ``hasOnlySubstanceUnits`` reads in a
            kinetic law, rule or event: ``None`` or ``"concentrations"`` (SBML's reading,
            ``amount / compartment size``) or ``"counts"`` (its count, as StochSS and GillesPy2
            write propensities). With ``substance_units="items"`` and a compartment size other
            than 1 where such a species is used, it must be given (see the module docstring).

    Returns:
        The :class:`SbmlModel`.

    Raises:
        SbmlError: unreadable file, SBML errors (all listed, up to ten), or an unsupported
            construct (the message names it and the element id).

    Warns:
        SbmlWarning: once, listing every reaction flagged reversible whose law is one-way
            (read as irreversible; see the module docstring).

    Example::

        model = read_sbml("network.xml", inputs=["activity"])
        ssa = CompiledSSA(model.kinetics)
        x, events = ssa.advance(model.initial_states(100), torch.tensor([0.45]), 0.05,
                                CellStreams.from_seed(0, 100))
    """
    path = Path(path)
    if not path.is_file():
        raise SbmlError(f"SBML file {str(path)!r} does not exist")
    document = libsbml.readSBMLFromFile(str(path))
    return _read_document(document, inputs, str(path), path, substance_units, species_in_laws)


def read_sbml_string(
    text: str,
    inputs: Sequence[str] = (),
    substance_units: str | None = None,
    species_in_laws: str | None = None,
) -> SbmlModel:
    """Like :func:`read_sbml`, from the SBML document's text."""
    document = libsbml.readSBMLFromString(text)
    return _read_document(document, inputs, "<string>", None, substance_units, species_in_laws)


def _read_document(
    document: libsbml.SBMLDocument,
    inputs: Sequence[str],
    label: str,
    source: Path | None,
    substance_units: str | None = None,
    species_in_laws: str | None = None,
) -> SbmlModel:
    if substance_units not in SUBSTANCE_UNITS:
        raise SbmlError(
            f"substance_units must be 'items' (read the file's amounts as molecule counts) or "
            f"unset, got {substance_units!r}"
        )
    if species_in_laws not in SPECIES_IN_LAWS:
        raise SbmlError(
            f"species_in_laws must be 'counts' (a species symbol in a formula is its count, as "
            f"StochSS and GillesPy2 write propensities), 'concentrations' (SBML's reading) or "
            f"unset, got {species_in_laws!r}"
        )
    errors = [
        document.getError(i)
        for i in range(document.getNumErrors())
        if document.getError(i).getSeverity() >= libsbml.LIBSBML_SEV_ERROR
    ]
    # Level 3's required flags a Level-2-minded exporter omits: Level 2's defaults, said once
    errors, filled = fill_level2_defaults(document, errors)
    if errors:
        raise SbmlError(_error_listing(label, errors))
    if filled:
        warnings.warn(f"{label}: {filled}", SbmlWarning, stacklevel=3)  # read_sbml's caller
    model = document.getModel()
    if model is None:
        raise SbmlError(f"{label}: the document has no model")
    return _Reader(model, tuple(inputs), label, substance_units, species_in_laws).read(source)


def _error_listing(label: str, errors: Sequence[libsbml.SBMLError]) -> str:
    """Every libsbml error (the first :data:`MAX_LISTED_ERRORS`, then a count), one a line:
    its line, severity, libsbml's short message, the detail that names the element, and the
    section of the SBML specification to check."""
    n = len(errors)
    lines = [
        f"{label}: {n} SBML error{'s' if n > 1 else ''} (libsbml "
        f"{libsbml.getLibSBMLDottedVersion()}); fix them in the file, each at its line:"
    ]
    for error in errors[:MAX_LISTED_ERRORS]:
        rule, _, rest = error.getMessage().partition("\nReference:")
        reference, _, detail = rest.partition("\n")
        hint = detail.strip() or rule.strip()
        check = f" (see {reference.strip()})" if reference.strip() else ""
        lines.append(
            f"  line {error.getLine()}, {error.getSeverityAsString().lower()} "
            f"[{error.getCategoryAsString()}]: {error.getShortMessage().strip()}: {hint}{check}"
        )
    if n > MAX_LISTED_ERRORS:
        lines.append(f"  ... and {n - MAX_LISTED_ERRORS} more")
    return "\n".join(lines)


def _ids(items: Iterable) -> list[str]:
    return [item.getId() for item in items]


class _Reader:
    """One pass over a libsbml Model; builds the SbmlModel or raises on the first problem."""

    def __init__(
        self,
        model: libsbml.Model,
        inputs: tuple[str, ...],
        label: str,
        substance_units: str | None = None,
        species_in_laws: str | None = None,
    ) -> None:
        self.model = model
        self.label = label
        self.inputs = inputs
        self.substance_units = substance_units
        self.species_in_laws = species_in_laws
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
        return _file_value(self.local_parameters[rid][pid] if dot else self.parameters[name])

    # -- values of constants ------------------------------------------------------------

    def constant_value(self, name: str, where: str) -> float:
        """Value of a compartment, parameter or species at t = 0 (initial assignments used)."""
        if name in self._values:
            return self._values[name]
        if name in self._resolving:
            raise SbmlError(f"{where}: circular initial assignments through {name!r}")
        self._resolving.append(name)
        try:
            value = self._constant_value(name, where)
        finally:
            self._resolving.pop()
        self._values[name] = value
        return value

    def _constant_value(self, name: str, where: str) -> float:
        if name in self.initial_assignments:
            assignment = self.initial_assignments[name]
            return self._evaluate_constant(assignment.getMath(), f"initial assignment of {name!r}")
        if name in self.compartments:
            c = self.compartments[name]
            if not c.isSetSize():
                raise SbmlError(
                    f"{where}: compartment {name!r} has no size, and this needs it (a species "
                    "read as a concentration, an initial concentration or the compartment's "
                    "id in a formula); give the compartment a size, or mark the species "
                    "hasOnlySubstanceUnits"
                )
            return float(c.getSize())
        if name in self.parameters:
            p = self.parameters[name]
            if name in self.assignment_rules:
                raise SbmlError(
                    f"{where}: parameter {name!r} is assigned by a rule, so it is not a constant"
                )
            if not p.isSetValue():
                raise SbmlError(f"{where}: parameter {name!r} has no value")
            return float(p.getValue())
        if name in self.species_index:
            return self._initial_species_value(self.species[self.species_index[name]])
        raise SbmlError(f"{where}: unknown symbol {name!r}")

    def _evaluate_constant(self, math_node: libsbml.ASTNode, where: str) -> float:
        def resolve(name: str) -> Expr:
            if name in self.inputs:
                raise SbmlError(f"{where}: depends on input parameter {name!r}")
            if name in self.species_rules:
                raise SbmlError(f"{where}: depends on species {name!r}, assigned by a rule")
            if name in self.species_index and name not in self.initial_assignments:
                sp = self.species[self.species_index[name]]
                amount = self._initial_amount(sp)
                if self._symbol_is_amount(sp):
                    return const(amount)
                return const(amount / self._compartment_size(sp, where))
            return const(self.constant_value(name, where))

        expr = convert(math_node, resolve, self.functions, where)
        if not expr.is_const:
            raise SbmlError(f"{where}: unsupported construct: value is not a constant")
        return float(expr.value)

    def _compartment_size(self, sp: libsbml.Species, where: str) -> float:
        cid = sp.getCompartment()
        if cid not in self.compartments:
            raise SbmlError(f"species {sp.getId()!r}: unknown compartment {cid!r}")
        size = self.constant_value(cid, where)
        if not (size > 0 and math.isfinite(size)):
            raise SbmlError(f"compartment {cid!r}: size must be finite and > 0, got {size}")
        return size

    def _initial_amount(self, sp: libsbml.Species) -> float:
        sid = sp.getId()
        where = f"species {sid!r}"
        if sid in self.initial_assignments:
            value = self._evaluate_constant(
                self.initial_assignments[sid].getMath(), f"initial assignment of {sid!r}"
            )
            if self._symbol_is_amount(sp):  # the symbol's value, as in laws and rules
                return value
            return value * self._compartment_size(sp, where)
        if sp.isSetInitialAmount():
            return float(sp.getInitialAmount())
        if sp.isSetInitialConcentration():
            return float(sp.getInitialConcentration()) * self._compartment_size(sp, where)
        raise SbmlError(f"{where}: no initialAmount, initialConcentration or initial assignment")

    def _initial_species_value(self, sp: libsbml.Species) -> float:
        amount = self._initial_amount(sp)
        if self._symbol_is_amount(sp):
            return amount
        return amount / self._compartment_size(sp, f"species {sp.getId()!r}")

    def initial_count(self, sp: libsbml.Species) -> tuple[int, str | None]:
        """``(count, why not)``: the initial molecule count of ``sp`` from what the file gives
        (an initial assignment, ``initialAmount`` or ``initialConcentration x size``), and
        ``None``, or ``(0, its source and value)`` where that is not a whole number of
        molecules (within :data:`~surrogate.ctmc.events.WHOLE_TOLERANCE`, as rules' values)."""
        sid = sp.getId()
        amount = self._initial_amount(sp)
        if not (math.isfinite(amount) and amount >= 0):
            raise SbmlError(
                f"species {sid!r}: initial amount must be finite and >= 0, got {amount}"
            )
        count, ok = whole_counts(torch.tensor([amount], dtype=torch.float64))
        if bool(ok):
            return int(count), None
        if sid in self.initial_assignments:
            source = "initial assignment, a count of"
        elif sp.isSetInitialAmount():
            source = "initialAmount"
        else:
            cid = sp.getCompartment()
            source = (
                f"initialConcentration {sp.getInitialConcentration():.10g} x size "
                f"{self.constant_value(cid, f'species {sid!r}'):.10g} of {cid!r} ="
            )
        return 0, f"{sid!r} ({source} {amount:.10g})"

    # -- kinetic laws ---------------------------------------------------------------------

    def expression(
        self,
        math_node: libsbml.ASTNode,
        local: Mapping[str, Expr],
        where: str,
        time: Expr | None = None,
    ) -> Expr:
        """Convert a kinetic law (or a rule's or event's math) to an expression; ``local``: the
        law's local parameters (constants, or inputs); ``time``: what the time csymbol reads
        (None: refused)."""

        def resolve(name: str) -> Expr:
            if name in local:
                return local[name]
            if name in self.species_rules:
                return self._inlined(name, self.species_rules, where)
            if name in self.species_index:
                s = self.species_index[name]
                sp = self.species[s]
                x = species_ref(s, name)
                if self._symbol_is_amount(sp):
                    return x
                return call("divide", x, const(self._compartment_size(sp, where)))
            if name in self.compartments:
                return const(self.constant_value(name, where))
            if name in self.inputs:
                return input_ref(self.inputs.index(name), name)
            if name in self.assignment_rules:
                return self._inlined(name, self.assignment_rules, where)
            if name in self.parameters:
                return const(self.constant_value(name, where))
            if self.model.getReaction(name) is not None:
                raise SbmlError(
                    f"{where}: unsupported construct: reaction id {name!r} used as a value"
                )
            if self._is_species_reference(name):
                raise SbmlError(
                    f"{where}: unsupported construct: species reference {name!r} used as a value"
                )
            raise SbmlError(f"{where}: unknown symbol {name!r}")

        return convert(math_node, resolve, self.functions, where, time=time)

    def _inlined(self, name: str, rules: Mapping[str, libsbml.Rule], where: str) -> Expr:
        """The formula of the rule assigning ``name`` (a parameter or species), inlined."""
        if name in self._resolving:
            raise SbmlError(f"{where}: circular assignment rules through {name!r}")
        self._resolving.append(name)
        try:
            return self.expression(rules[name].getMath(), {}, f"assignment rule for {name!r}")
        finally:
            self._resolving.pop()

    def _is_species_reference(self, name: str) -> bool:
        for reaction in self.model.getListOfReactions():
            for ref in (*reaction.getListOfReactants(), *reaction.getListOfProducts()):
                if ref.isSetId() and ref.getId() == name:
                    return True
        return False

    def _stoichiometry(self, reaction: libsbml.Reaction, refs: Iterable, side: str) -> dict:
        rid = reaction.getId()
        out: dict[str, int] = {}
        for ref in refs:
            sid = ref.getSpecies()
            if sid not in self.species_index:
                raise SbmlError(f"reaction {rid!r}: {side} {sid!r} is not a species")
            if ref.isSetStoichiometryMath():
                raise SbmlError(
                    f"reaction {rid!r}: unsupported construct: stoichiometryMath for {side} {sid!r}"
                )
            if ref.isSetId() and (
                ref.getId() in self.initial_assignments
                or self.model.getRule(ref.getId()) is not None
            ):
                raise SbmlError(
                    f"reaction {rid!r}: unsupported construct: variable stoichiometry of {side} "
                    f"{sid!r} (species reference {ref.getId()!r} is assigned)"
                )
            level = self.model.getLevel()
            coeff = (
                float(ref.getStoichiometry()) if (level < 3 or ref.isSetStoichiometry()) else 1.0
            )
            if level >= 3 and not ref.isSetStoichiometry():
                raise SbmlError(f"reaction {rid!r}: {side} {sid!r} has no stoichiometry")
            if not (math.isfinite(coeff) and coeff >= 0 and coeff.is_integer()):
                raise SbmlError(
                    f"reaction {rid!r}: unsupported construct: non-integer stoichiometry {coeff} "
                    f"of {side} {sid!r}"
                )
            out[sid] = out.get(sid, 0) + int(coeff)
        return out

    # -- species assignment rules and events ----------------------------------------------

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

    def _amount(self, sp: libsbml.Species, value: Expr, where: str) -> Expr:
        """The count of ``sp`` whose symbol has ``value`` (a concentration unless
        hasOnlySubstanceUnits or species_in_laws="counts")."""
        if self._symbol_is_amount(sp):
            return value
        return call("times", value, const(self._compartment_size(sp, where)))

    def _rules(self) -> tuple[SpeciesRule, ...]:
        rules = []
        for sid in self.species_rules:
            sp = self.species[self.species_index[sid]]
            where = f"assignment rule for {sid!r}"
            value = self._inlined(sid, self.species_rules, where)
            rules.append(SpeciesRule(self.species_index[sid], self._amount(sp, value, where)))
        return tuple(rules)

    def _events(self) -> tuple[Event, ...]:
        events = []
        for k, event in enumerate(self.model.getListOfEvents()):
            name = event.getId() or f"#{k + 1}"
            where = f"event {name!r}"
            trigger = event.getTrigger()
            if trigger is None or trigger.getMath() is None:
                raise SbmlError(f"{self.label}: {where} has no trigger")
            condition = self.expression(trigger.getMath(), {}, f"trigger of {where}", time_ref())
            assignments = []
            for assignment in event.getListOfEventAssignments():
                sid = assignment.getVariable()
                sp = self.species[self.species_index[sid]]
                value = self.expression(
                    assignment.getMath(), {}, f"{where}: assignment to {sid!r}", time_ref()
                )
                assignments.append((self.species_index[sid], self._amount(sp, value, where)))
            events.append(
                Event(
                    name,
                    condition,
                    tuple(assignments),
                    initial_value=trigger.getInitialValue(),
                    persistent=trigger.getPersistent(),
                    use_values_from_trigger_time=event.getUseValuesFromTriggerTime(),
                )
            )
        return tuple(events)

    def _initial_counts(self, kinetics: Kinetics, inputs: Sequence[float]) -> Tensor:
        """``(S,)`` initial counts; a species assigned by a rule takes the rule's value there
        (with ``inputs``, the file's values of the inputs; left 0 where one has none: the SSAs
        set it from each cell's inputs at every window's start)."""
        counts: list[int] = []
        fractional: list[str] = []  # one rule for amounts, concentrations and assignments
        for sp in self.species:
            initial, why = (0, None) if sp.getId() in self.species_rules else self.initial_count(sp)
            counts.append(initial)
            if why is not None:
                fractional.append(why)
        if fractional:
            raise SbmlError(
                f"{self.label}: the initial value of species {', '.join(fractional)} "
                f"{'is' if len(fractional) == 1 else 'are'} not a whole number of molecules: "
                "the stochastic reading needs counts, and these are not (a model written for "
                "ODEs, in concentrations or moles?). Rescale it to molecule counts in the file "
                "(initial amounts or concentrations x compartment sizes, and the rate "
                "constants of reactions of order 2 and more by the volume), or use a "
                "deterministic simulator"
            )
        for rule in kinetics.rules:
            value = float(rule.expr.evaluate(counts, inputs))
            if math.isnan(value) and rule.expr.inputs_used():
                continue
            count, ok = whole_counts(torch.tensor([value], dtype=torch.float64))
            if not bool(ok):
                raise SbmlError(
                    f"assignment rule for {self.species[rule.column].getId()!r}: its value at "
                    f"the initial state, {value!r}, is not a whole number of molecules >= 0"
                )
            counts[rule.column] = int(count)
        return torch.tensor(counts, dtype=torch.int64)

    def read(self, source: Path | None) -> SbmlModel:
        self._refuse_unsupported()
        self._check_inputs()
        self._check_substance_units()
        self._check_species_in_laws()
        model = self.model
        if not self.species:
            raise SbmlError(f"{self.label}: the model has no species")
        if model.getNumReactions() == 0:
            raise SbmlError(f"{self.label}: the model has no reactions")
        fixed = {sp.getId() for sp in self.species if sp.getBoundaryCondition() or sp.getConstant()}
        species_ids = tuple(sp.getId() for sp in self.species)
        reactions: list[SbmlReaction] = []
        exprs: list[Expr] = []
        n_species = len(species_ids)
        reactants = torch.zeros((model.getNumReactions(), n_species), dtype=torch.int64)
        products = torch.zeros_like(reactants)
        one_way: list[str] = []  # flagged reversible, read as irreversible
        net_rates: list[str] = []  # flagged reversible with a net-rate law: refused
        for r, reaction in enumerate(model.getListOfReactions()):
            rid = reaction.getId()
            if reaction.isSetFast() and reaction.getFast():
                raise SbmlError(f"reaction {rid!r}: unsupported construct: fast reaction")
            consumed = self._stoichiometry(reaction, reaction.getListOfReactants(), "reactant")
            produced = self._stoichiometry(reaction, reaction.getListOfProducts(), "product")
            modifiers = tuple(m.getSpecies() for m in reaction.getListOfModifiers())
            for sid in modifiers:
                if sid not in self.species_index:
                    raise SbmlError(f"reaction {rid!r}: modifier {sid!r} is not a species")
            law = reaction.getKineticLaw()
            if law is None:
                raise SbmlError(f"reaction {rid!r}: no kinetic law (needed as the propensity)")
            local: dict[str, Expr] = {}
            for pid, p in self.local_parameters[rid].items():
                if f"{rid}.{pid}" in self.inputs:
                    local[pid] = input_ref(self.inputs.index(f"{rid}.{pid}"), f"{rid}.{pid}")
                elif not p.isSetValue():
                    raise SbmlError(f"reaction {rid!r}: local parameter {pid!r} has no value")
                else:
                    local[pid] = const(float(p.getValue()))
            expr = self.expression(law.getMath(), local, f"kinetic law of reaction {rid!r}")
            if reaction.getReversible():
                backward = _net_rate_products(expr, {self.species_index[s] for s in produced})
                if backward:
                    formula = libsbml.formulaToL3String(law.getMath())
                    net_rates.append(
                        f"{rid!r} (its law {formula!r} subtracts a term that depends on its "
                        f"product{'s' if len(backward) > 1 else ''} {', '.join(backward)})"
                    )
                else:
                    one_way.append(rid)
            exprs.append(expr)
            for sid, coeff in consumed.items():
                if sid not in fixed:
                    reactants[r, self.species_index[sid]] = coeff
            for sid, coeff in produced.items():
                if sid not in fixed:
                    products[r, self.species_index[sid]] = coeff
            reactions.append(SbmlReaction(rid, consumed, produced, modifiers))
        if net_rates:
            raise SbmlError(
                f"{self.label}: reversible reaction{'s' if len(net_rates) > 1 else ''} "
                f"{'; '.join(net_rates)}: a net rate (forward minus backward) is not one "
                "event's propensity and can be negative; write each as two irreversible "
                "reactions, one per direction"
            )
        if one_way:
            warnings.warn(
                f"{self.label}: {len(one_way)} reaction{'s' if len(one_way) > 1 else ''} "
                f"flagged reversible with a one-way kinetic law (no subtracted term depends on "
                f"a product) read as irreversible: {', '.join(repr(r) for r in one_way)}; a "
                "propensity that turns negative is refused when simulated",
                SbmlWarning,
                stacklevel=4,  # the caller of read_sbml / read_sbml_string
            )
        network = ReactionNetwork(
            species=species_ids,
            reactants=reactants,
            products=products,
            reaction_names=tuple(r.id for r in reactions),
        )
        try:
            kinetics = Kinetics(network=network, input_names=self.inputs,
                                propensity_exprs=tuple(exprs), rules=self._rules(),
                                events=self._events())  # fmt: skip
        except ValueError as error:
            raise SbmlError(f"{self.label}: {error}") from None
        defaults = {name: self._input_default(name) for name in self.inputs}
        initial = self._initial_counts(kinetics, [defaults[name] for name in self.inputs])
        constants = {  # NaN: a compartment without a size (legal where no law needs one)
            name: self.constant_value(name, f"compartment {name!r}")
            if self.compartments[name].isSetSize() or name in self.initial_assignments
            else math.nan
            for name in self.compartments
        }
        for name in self.parameters:
            if name not in self.inputs and name not in self.assignment_rules:
                try:
                    constants[name] = self.constant_value(name, f"parameter {name!r}")
                except SbmlError:
                    if name in self.initial_assignments:
                        raise
                    constants[name] = math.nan  # declared without a value and never used
        globals_ = {name: math.nan if name in self.assignment_rules else _file_value(p)
                    for name, p in self.parameters.items()}  # fmt: skip
        locals_ = {f"{rid}.{pid}": _file_value(p) for rid, ps in self.local_parameters.items()
                   for pid, p in ps.items()}  # fmt: skip
        return SbmlModel(
            id=model.getId(),
            kinetics=kinetics,
            initial_state=initial,
            constants=constants,
            input_defaults=defaults,
            fixed_species=tuple(s for s in species_ids if s in fixed),
            reactions=tuple(reactions),
            source=source,
            species_compartments={sp.getId(): sp.getCompartment() for sp in self.species},
            parameters=globals_,
            local_parameters=locals_,
        )


def _file_value(parameter: libsbml.Parameter) -> float:
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


@dataclass(frozen=True)
class _Terms:
    """A law read as a signed sum of products (its expansion, not built): whether some term is
    positive / negative, and the species (by column) found in positive / negative terms."""

    positive: bool
    negative: bool
    in_positive: frozenset[int] = frozenset()
    in_negative: frozenset[int] = frozenset()

    def flipped(self) -> _Terms:
        return _Terms(self.negative, self.positive, self.in_negative, self.in_positive)

    def __add__(self, other: _Terms) -> _Terms:
        return _Terms(
            self.positive or other.positive,
            self.negative or other.negative,
            self.in_positive | other.in_positive,
            self.in_negative | other.in_negative,
        )

    def __mul__(self, other: _Terms) -> _Terms:
        # a term of the product is one term of each factor: negative where their signs differ
        a, b = self, other
        in_positive: frozenset[int] = frozenset()
        in_negative: frozenset[int] = frozenset()
        for mine, theirs in ((a, b), (b, a)):
            if theirs.positive:
                in_positive |= mine.in_positive
                in_negative |= mine.in_negative
            if theirs.negative:
                in_positive |= mine.in_negative
                in_negative |= mine.in_positive
        return _Terms(
            (a.positive and b.positive) or (a.negative and b.negative),
            (a.positive and b.negative) or (a.negative and b.positive),
            in_positive,
            in_negative,
        )


#: functions whose sign is their argument's (the argument's terms are the value's terms)
_SIGN_OF_ARGUMENT = frozenset({"sinh", "tanh", "arcsin", "arctan", "floor", "ceiling"})


def _positive_factor(expr: Expr) -> _Terms:
    """A factor read as one positive term holding every species it reads (a function's value,
    a power's exponent): a minus inside it subtracts no term from the law."""
    return _Terms(True, False, frozenset(n.index for n in _leaves(expr) if n.op == "species"))


def _terms(expr: Expr) -> _Terms:
    """The signed terms of ``expr`` (see :class:`_Terms` and the module docstring): through
    sums, differences, negations, products, quotients, a power's base, min / max, the values
    of a piecewise (its conditions a positive factor) and sign-keeping functions; every other
    function (``exp``, ``sqrt``, ``abs``, ``ln``, ...) and a power's exponent is a positive
    factor, and so is an even integer power."""
    op, args = expr.op, expr.args
    if op == "const":
        return _Terms(not expr.value < 0, expr.value < 0)
    if op == "species":
        return _Terms(True, False, frozenset({expr.index}))
    if op in ("input", "time"):
        return _Terms(True, False)
    if op in ("plus", "min", "max"):
        out = _terms(args[0])
        for arg in args[1:]:
            out = out + _terms(arg)
        return out
    if op == "minus":
        return _terms(args[0]) + _terms(args[1]).flipped()
    if op == "negate":
        return _terms(args[0]).flipped()
    if op in ("times", "divide"):  # 1 / b has the sign of b
        out = _terms(args[0])
        for arg in args[1:]:
            out = out * _terms(arg)
        return out
    if op == "power":
        base, exponent = args
        if exponent.is_const and float(exponent.value) % 2 == 0:
            return _positive_factor(expr)
        return _terms(base) * _positive_factor(exponent)
    if op in _SIGN_OF_ARGUMENT:
        return _terms(args[0])
    if op == "piecewise":
        values = [*args[0:-1:2], *([args[-1]] if len(args) % 2 else [])]
        conditions = args[1::2]
        out = _terms(values[0])
        for value in values[1:]:
            out = out + _terms(value)
        for condition in conditions:
            out = out * _positive_factor(condition)
        return out
    return _positive_factor(expr)


def _net_rate_products(expr: Expr, products: set[int]) -> list[str]:
    """The products (by name) that some negative term of a reversible reaction's law depends
    on: a non-empty list marks the law a net rate (forward minus backward). See the module
    docstring."""
    names = {n.index: repr(n.name) for n in _leaves(expr) if n.op == "species"}
    return [names[i] for i in sorted(_terms(expr).in_negative & products)]


def _names(node: libsbml.ASTNode) -> set[str]:
    """The names (``ci`` symbols) a MathML tree reads."""
    out = {node.getName()} if node.isName() and node.getName() else set()
    for i in range(node.getNumChildren()):
        out |= _names(node.getChild(i))
    return out


def _leaves(expr: Expr) -> Iterable[Expr]:
    if not expr.args:
        yield expr
    for arg in expr.args:
        yield from _leaves(arg)
