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
  reaction that it does not also consume (boundary species included), e.g. ``kf * A - kr * B``
  or ``kf * A + (-kr) * B`` with product ``B``, or ``k * A * (1 - B / K)``; not an
  autocatalytic law, ``k * Y * X * (X - 1) / 2`` for ``2 X + Y -> 3 X`` (StochSS's
  Brusselator), whose falling factorial subtracts a term in the reactant X, which is also a
  product. A net rate is refused, naming the reaction, its law
  and the product (write the reaction as two irreversible ones). Otherwise the law is one-way
  (e.g. ``alpha / (1 + V^beta)``, ``mu * U``, ``kf * A * exp(-B / K)``, ``kf * A * K^(-B)``,
  or ``k1 * A - k2 * C`` with ``C`` not a product) and the reaction is read as irreversible,
  with one :class:`~surrogate.sbml.errors.SbmlWarning` listing every such reaction. A
  propensity that turns out negative at run time is refused by both simulators (the compiled
  SSA names the reaction).
* A kinetic law that does not read a species its reaction uses up (consumed more than made,
  not fixed) stays positive at that species' count 0, and the SSA would drive the count
  negative (Wilkinson's ``ch05-act.xml``: ``I -> A`` at ``alpha``, ``A -> I`` at ``beta``, one
  molecule between them). By default (``reactant_guard=True``, the yaml's ``reactant_guard``
  unset) such a law is read as 0 while any such species has fewer molecules than the reaction
  consumes, its value as written otherwise: the propensity on the lattice of counts, where a
  reaction without its molecules cannot happen. A law that reads the species (mass action) is
  read as written, as is a species consumed and made again (a catalyst). One
  :class:`~surrogate.sbml.errors.SbmlWarning` names every such law and what it needs;
  ``reactant_guard=False`` reads them as written (a count driven negative is then refused when
  simulated, naming the reaction).
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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import libsbml
import torch
from torch import Tensor

from surrogate.ctmc.kinetics import Expr, Kinetics, call, const, input_ref, species_ref
from surrogate.ctmc.network import ReactionNetwork
from surrogate.sbml.checks import file_value
from surrogate.sbml.defaults import fill_level2_defaults
from surrogate.sbml.errors import SbmlError, SbmlWarning
from surrogate.sbml.laws import ReaderRules
from surrogate.sbml.net_rate import net_rate_products

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
    reactant_guard: bool = True,
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
        reactant_guard: A kinetic law that does not read a species its reaction uses up stays
            positive at that species' count 0 (``I -> A`` at ``alpha``): with True, it is read
            as 0 while any such species has fewer molecules than the reaction consumes, as the
            SSA's propensity must be; with False, as written (a count it drives negative is
            refused when simulated). Either way one warning names every such law.

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
    return _read_document(
        document, inputs, str(path), path, substance_units, species_in_laws, reactant_guard
    )


def read_sbml_string(
    text: str,
    inputs: Sequence[str] = (),
    substance_units: str | None = None,
    species_in_laws: str | None = None,
    reactant_guard: bool = True,
) -> SbmlModel:
    """Like :func:`read_sbml`, from the SBML document's text."""
    document = libsbml.readSBMLFromString(text)
    return _read_document(
        document, inputs, "<string>", None, substance_units, species_in_laws, reactant_guard
    )


def _read_document(
    document: libsbml.SBMLDocument,
    inputs: Sequence[str],
    label: str,
    source: Path | None,
    substance_units: str | None = None,
    species_in_laws: str | None = None,
    reactant_guard: bool = True,
) -> SbmlModel:
    if not isinstance(reactant_guard, bool):
        raise SbmlError(f"reactant_guard must be true or false, got {reactant_guard!r}")
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
    return _Reader(
        model, tuple(inputs), label, substance_units, species_in_laws, reactant_guard
    ).read(source)


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


class _Reader(ReaderRules):
    """One pass over a libsbml Model; builds the SbmlModel or raises on the first problem (the
    layers below: :class:`~surrogate.sbml.checks.ReaderChecks`,
    :class:`~surrogate.sbml.amounts.ReaderAmounts`, :class:`~surrogate.sbml.laws.ReaderLaws`,
    :class:`~surrogate.sbml.laws.ReaderRules`)."""

    def read(self, source: Path | None) -> SbmlModel:  # noqa: C901  # the document's parts in order
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
        unguarded: list[str] = []  # laws that fire without the molecules they consume
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
                # a species the reaction also consumes is no backward direction's: an
                # autocatalytic law (2 X + Y -> 3 X at k Y X (X - 1) / 2) subtracts a term in X
                backward = net_rate_products(
                    expr, {self.species_index[s] for s in produced if s not in consumed}
                )
                if backward:
                    formula = libsbml.formulaToL3String(law.getMath())
                    net_rates.append(
                        f"{rid!r} (its law {formula!r} subtracts a term that depends on its "
                        f"product{'s' if len(backward) > 1 else ''} {', '.join(backward)})"
                    )
                else:
                    one_way.append(rid)
            unread = self._unread_reactants(expr, consumed, produced, fixed)
            if unread:
                formula = libsbml.formulaToL3String(law.getMath())
                needs = " and ".join(f"{sid} >= {consumed[sid]}" for sid in unread)
                unguarded.append(f"{rid!r} consumes {', '.join(unread)} but its law {formula!r} "
                                 f"does not read {'them' if len(unread) > 1 else 'it'}"
                                 + (f" (0 unless {needs})" if self.reactant_guard else ""))  # fmt: skip
                if self.reactant_guard:
                    expr = call("piecewise", expr, self._available(unread, consumed), const(0.0))
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
        if unguarded:
            reading = (
                "read as 0 while a reactant has fewer molecules than the reaction consumes (a "
                "propensity is 0 where the reaction cannot happen; `reactant_guard: false` in "
                "the model yaml, read_sbml(..., reactant_guard=False), reads the laws as "
                "written, and a count they drive negative is refused when simulated)"
                if self.reactant_guard
                else "read as written (reactant_guard=False): a count they drive negative is "
                "refused when simulated"
            )
            warnings.warn(
                f"{self.label}: {len(unguarded)} kinetic law{'s' if len(unguarded) > 1 else ''}"
                f" that can fire without {'their' if len(unguarded) > 1 else 'its'} reactants, "
                f"{reading}: {'; '.join(unguarded)}",
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
        globals_ = {name: math.nan if name in self.assignment_rules else file_value(p)
                    for name, p in self.parameters.items()}  # fmt: skip
        locals_ = {f"{rid}.{pid}": file_value(p) for rid, ps in self.local_parameters.items()
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

    def _unread_reactants(
        self, law: Expr, consumed: Mapping[str, int], produced: Mapping[str, int], fixed: set[str]
    ) -> list[str]:
        """The species ``law`` fires without: those the reaction uses up (more consumed than
        produced, not fixed, not set by a rule) that the law does not read, so that it stays
        positive at their count 0 (Wilkinson's ``ch05-act.xml``: ``I -> A`` at ``alpha``)."""
        read = law.species_used()
        return [
            sid
            for sid, coeff in consumed.items()
            if produced.get(sid, 0) < coeff
            and sid not in fixed
            and sid not in self.species_rules
            and self.species_index[sid] not in read
        ]

    def _available(self, unread: Sequence[str], consumed: Mapping[str, int]) -> Expr:
        """The condition that every species of ``unread`` has the molecules the reaction
        consumes (counts, whatever ``species_in_laws`` says of the laws)."""
        return call(
            "and",
            *(
                call("geq", species_ref(self.species_index[sid], sid), const(float(consumed[sid])))
                for sid in unread
            ),
        )
