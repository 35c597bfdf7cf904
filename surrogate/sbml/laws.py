"""The SBML reader's formulas: kinetic laws (and rules' and events' math) as expressions over
counts and inputs, with rules and local parameters inlined, and reactions' stoichiometry
(:class:`ReaderLaws`); then species assignment rules, events and the initial counts
(:class:`ReaderRules`)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import libsbml
import torch
from torch import Tensor

from surrogate.ctmc.events import Event, SpeciesRule, whole_counts
from surrogate.ctmc.kinetics import Expr, Kinetics, call, const, input_ref, species_ref, time_ref
from surrogate.sbml.amounts import ReaderAmounts
from surrogate.sbml.errors import SbmlError
from surrogate.sbml.math import convert


class ReaderLaws(ReaderAmounts):
    """Kinetic laws and stoichiometry (above the values)."""

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


class ReaderRules(ReaderLaws):
    """Species assignment rules, events and the initial counts (above the laws)."""

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


__all__ = ["ReaderLaws", "ReaderRules"]
