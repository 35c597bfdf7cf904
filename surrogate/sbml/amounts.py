"""The SBML reader's values: constants at t = 0 (initial assignments included), compartment
sizes, species' initial amounts and counts, and a species' count from its symbol's value
(:class:`ReaderAmounts`)."""

from __future__ import annotations

import math

import libsbml
import torch

from surrogate.ctmc.events import whole_counts
from surrogate.ctmc.kinetics import Expr, call, const
from surrogate.sbml.checks import ReaderChecks
from surrogate.sbml.errors import SbmlError
from surrogate.sbml.math import convert


class ReaderAmounts(ReaderChecks):
    """Values of constants and initial amounts (above the checks)."""

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

    def _amount(self, sp: libsbml.Species, value: Expr, where: str) -> Expr:
        """The count of ``sp`` whose symbol has ``value`` (a concentration unless
        hasOnlySubstanceUnits or species_in_laws="counts")."""
        if self._symbol_is_amount(sp):
            return value
        return call("times", value, const(self._compartment_size(sp, where)))


__all__ = ["ReaderAmounts"]
