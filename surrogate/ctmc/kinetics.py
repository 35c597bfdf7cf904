"""General reaction kinetics: propensities as validated expression trees, compiled twice.

A :class:`Kinetics` is a :class:`~surrogate.ctmc.ReactionNetwork` (who is consumed and produced)
plus one expression per reaction giving its propensity (events per unit time) as a function of
the state (species counts) and of per-cell *inputs* (parameters supplied by the caller every
window, e.g. a receptor activity). Expressions are small immutable trees built only from the
operators in ``OPERATORS``; every node is type-checked (real or boolean) and constant subtrees
are folded when the tree is built. From one tree we generate, once, Python source for

* a torch function ``propensities(state (n, S), inputs (n, P)) -> (n, R) float64`` that runs on
  any device (vectorised over cells), and
* a scalar per-cell function ``propensities(x (S,), p (P,), a (R,))`` that numba compiles into
  the per-cell Gillespie kernel of :mod:`surrogate.ctmc.compiled`.

The generated source contains only our own templates, column indices and ``repr`` of floats, so
nothing read from a model file is ever evaluated as code. We hand-write this small tree (rather
than use sympy's ``lambdify``) because it must emit numba-compilable scalar code and device-safe
torch code from the same tree, with SBML's piecewise/boolean semantics and no import-time cost.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from surrogate.ctmc.expr import (
    OPERATORS,
    REAL,
    Expr,
    call,
    combine_scalar,
    const,
    input_ref,
    numba_source,
    scalar_code,
    scalar_locals,
    species_ref,
    substitute,
    time_ref,
    torch_function,
    torch_source,
)
from surrogate.ctmc.network import ReactionNetwork

# the expression names are re-exported: kinetics is where a model reads them
__all__ = [
    "OPERATORS",
    "Event",
    "Expr",
    "Kinetics",
    "SpeciesRule",
    "call",
    "combine_scalar",
    "const",
    "input_ref",
    "mass_action_kinetics",
    "scalar_code",
    "scalar_locals",
    "species_ref",
    "substitute",
    "time_comparison",
    "time_ref",
    "time_thresholds",
    "torch_function",
]


_TIME_COMPARISONS = ("lt", "leq", "gt", "geq")
_MIRRORED = {"lt": "gt", "leq": "geq", "gt": "lt", "geq": "leq"}


def time_comparison(e: Expr) -> tuple[str, Expr] | None:
    """``(op, c)`` if ``e`` compares the bare time with an expression ``c`` free of time, as
    ``t op c`` (the time moved to the left); else None."""
    if e.op not in _TIME_COMPARISONS:
        return None
    a, b = e.args
    if a.op == "time" and not b.uses_time():
        return e.op, b
    if b.op == "time" and not a.uses_time():
        return _MIRRORED[e.op], a
    return None


def time_thresholds(e: Expr, where: str = "trigger") -> tuple[Expr, ...]:
    """The values ``c`` at which a condition's comparisons ``t op c`` switch (over species and
    inputs, free of time), in tree order.

    Raises:
        ValueError: the time occurs anywhere else (``t == 5``, ``2 * t > 5``, ``t > t0 + t``),
            naming ``where``: a trigger must be piecewise constant in t between reactions.
    """
    found = time_comparison(e)
    if found is not None:
        return (found[1],)
    if e.op == "time":
        raise ValueError(
            f"{where}: the time may only be compared with an expression free of time "
            "(t < c, t <= c, t > c, t >= c); == and != with the time, or the time inside "
            "arithmetic, would make the event's instant depend on the time continuously"
        )
    return tuple(c for arg in e.args for c in time_thresholds(arg, where))


@dataclass(frozen=True)
class SpeciesRule:
    """A species whose count is a function of the state: ``x[column] = expr(x, inputs)``.

    Attributes:
        column: The species' state column.
        expr: Its count (real, rounded to a whole number; free of time), over species that no
            rule assigns (nest rules by inlining) and inputs.
    """

    column: int
    expr: Expr

    def __post_init__(self) -> None:
        if self.expr.kind != "real":
            raise ValueError(f"rule for species column {self.column}: value must be real")
        if self.expr.uses_time():
            raise ValueError(
                f"rule for species column {self.column}: a rule may not read the time (its "
                "value would change between reactions)"
            )


@dataclass(frozen=True)
class Event:
    """A discrete event: when ``trigger`` goes from false to true, set species counts.

    Attributes:
        name: For messages.
        trigger: A condition over species, inputs and the time (see :func:`time_thresholds`).
        assignments: ``(species column, count expression)`` pairs; the counts are computed
            from the state at the instant (they may read the time) and must be whole numbers
            >= 0.
        initial_value: The trigger's value before t = 0 (SBML ``initialValue``): False fires
            an event whose trigger holds at t = 0.
        persistent: False: among events firing at one instant, dropped when an earlier one
            makes its trigger false.
        use_values_from_trigger_time: True: among events firing at one instant, its values
            are computed before any of them runs; False: when it runs.
    """

    name: str
    trigger: Expr
    assignments: tuple[tuple[int, Expr], ...] = ()
    initial_value: bool = True
    persistent: bool = True
    use_values_from_trigger_time: bool = True

    def __post_init__(self) -> None:
        pairs = tuple((int(column), expr) for column, expr in self.assignments)
        object.__setattr__(self, "assignments", pairs)
        if self.trigger.kind != "bool":
            raise ValueError(f"event {self.name!r}: the trigger must be a condition (boolean)")
        time_thresholds(self.trigger, f"event {self.name!r}")
        columns = [column for column, _ in pairs]
        if len(set(columns)) != len(columns):
            raise ValueError(f"event {self.name!r}: a species is assigned twice")
        if any(expr.kind != "real" for _, expr in pairs):
            raise ValueError(f"event {self.name!r}: assigned values must be real")

    @property
    def thresholds(self) -> tuple[Expr, ...]:
        """The values of t at which the trigger may switch (see :func:`time_thresholds`)."""
        return time_thresholds(self.trigger)

    @property
    def uses_time(self) -> bool:
        """True if the trigger reads the time (a time-triggered event)."""
        return self.trigger.uses_time()


@dataclass(frozen=True, eq=False)
class Kinetics:
    """A reaction network with general propensities over its state and per-cell inputs.

    Attributes:
        network: Species, reactions and their (net) stoichiometry. Species that the model
            holds fixed (boundary or constant species) have zero net change.
        input_names: Names of the per-cell inputs, in column order of the ``inputs`` tensor.
        propensity_exprs: One expression per reaction (events per unit time), over species
            counts and inputs (not the time).
        rules: Species whose count is a function of the others, recomputed after every
            reaction and event (:class:`SpeciesRule`; their columns
            change by no reaction, and no rule reads another's column).
        events: Discrete events (:class:`Event`), simulated exactly by
            both SSAs (see :mod:`surrogate.ctmc.events`).
    """

    network: ReactionNetwork
    input_names: tuple[str, ...]
    propensity_exprs: tuple[Expr, ...]
    rules: tuple[SpeciesRule, ...] = ()
    events: tuple[Event, ...] = ()
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        exprs = tuple(self.propensity_exprs)
        names = tuple(self.input_names)
        object.__setattr__(self, "propensity_exprs", exprs)
        object.__setattr__(self, "input_names", names)
        if len(exprs) != self.network.n_reactions:
            raise ValueError(
                f"need one propensity per reaction ({self.network.n_reactions}), got {len(exprs)}"
            )
        if len(set(names)) != len(names):
            raise ValueError(f"input names must be unique, got {names}")
        for r, e in enumerate(exprs):
            name = self.network.reaction_names[r]
            if e.kind != REAL:
                raise ValueError(f"reaction {name!r}: propensity must be real, got boolean")
            if e.species_used() and max(e.species_used()) >= self.network.n_species:
                raise ValueError(f"reaction {name!r}: species column out of range")
            if e.inputs_used() and max(e.inputs_used()) >= len(names):
                raise ValueError(f"reaction {name!r}: input column out of range")
            if e.uses_time():
                raise ValueError(
                    f"reaction {name!r}: propensity depends on the time (only event triggers "
                    "may read it)"
                )
        self._check_rules_and_events()

    def _check_rules_and_events(self) -> None:
        rules, events = tuple(self.rules), tuple(self.events)
        object.__setattr__(self, "rules", rules)
        object.__setattr__(self, "events", events)
        species = self.network.species

        def check_columns(e: Expr, where: str) -> None:
            if e.species_used() and max(e.species_used()) >= self.network.n_species:
                raise ValueError(f"{where}: species column out of range")
            if e.inputs_used() and max(e.inputs_used()) >= self.n_inputs:
                raise ValueError(f"{where}: input column out of range")

        ruled = [rule.column for rule in rules]
        if any(not 0 <= c < self.network.n_species for c in ruled) or len(set(ruled)) != len(ruled):
            raise ValueError(f"rule columns must be distinct species columns, got {ruled}")
        changed = self.network.stoichiometry[:, ruled].ne(0).any(0).tolist() if ruled else []
        for rule, moved in zip(rules, changed, strict=True):
            where = f"rule for species {species[rule.column]!r}"
            check_columns(rule.expr, where)
            if moved:
                raise ValueError(f"{where}: the species is also changed by a reaction")
            read = sorted(rule.expr.species_used() & set(ruled))
            if read:
                raise ValueError(
                    f"{where}: reads {[species[c] for c in read]}, assigned by rules "
                    "themselves (inline their expressions)"
                )
        for event in events:
            where = f"event {event.name!r}"
            check_columns(event.trigger, where)
            for column, expr in event.assignments:
                check_columns(expr, where)
                if not 0 <= column < self.network.n_species:
                    raise ValueError(f"{where}: assigned species column {column} out of range")
                if column in ruled:
                    raise ValueError(
                        f"{where}: assigns species {species[column]!r}, which a rule assigns"
                    )

    @property
    def has_rules_or_events(self) -> bool:
        """True if the network has species assignment rules or events (simulated by the
        SSAs' event kernels, not by the generator of :mod:`surrogate.ctmc.lumped`)."""
        return bool(self.rules or self.events)

    def __getstate__(self) -> dict:
        """Picklable: the expressions, not the generated code (loaded again on first use)."""
        return {**self.__dict__, "_cache": {}}

    @property
    def n_inputs(self) -> int:
        """Number of per-cell inputs ``P``."""
        return len(self.input_names)

    @property
    def torch_source(self) -> str:
        """Generated source of the torch propensity function (for inspection)."""
        return torch_source(self.propensity_exprs)

    @property
    def numba_source(self) -> str:
        """Generated source of ``propensities(x, p, a)``: scalar per-cell code for numba.

        ``x`` is one cell's ``(S,)`` int64 counts, ``p`` its ``(P,)`` float64 inputs, and the
        ``(R,)`` float64 propensities are written into ``a``. Uses ``np`` (numpy) only.
        """
        return numba_source(self.propensity_exprs)

    @property
    def torch_propensity(self) -> Callable[[Tensor, Tensor], Tensor]:
        """``propensities(state (n, S), inputs (n, P)) -> (n, R) float64`` on any device.

        Generated once from the expression trees and cached. No validation (hot path); use
        :meth:`propensities` for a checked call.
        """
        fn = self._cache.get("torch")
        if fn is None:
            from surrogate.ctmc.codegen import load_generated

            source = "import torch\n\n\n" + self.torch_source
            fn = load_generated(source, prefix="kinetics").propensities
            self._cache["torch"] = fn
        return fn

    def check_inputs(self, state: Tensor, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Validate ``state`` ``(n, S)`` integer counts >= 0 and ``inputs`` ``(n, P)`` (or
        ``(P,)``, shared) finite floats on the same device; return (int64 state, (n, P) inputs).
        """
        network = self.network
        if not isinstance(state, Tensor) or not isinstance(inputs, Tensor):
            raise ValueError("state and inputs must be torch tensors")
        if state.dim() != 2 or state.shape[1] != network.n_species:
            raise ValueError(
                f"state must have shape (n, S) with S = {network.n_species} species "
                f"{network.species}, got {tuple(state.shape)}"
            )
        if state.dtype.is_floating_point or state.dtype.is_complex or state.dtype == torch.bool:
            raise ValueError(f"state must hold integer counts, got dtype {state.dtype}")
        n = state.shape[0]
        if inputs.dim() == 1:
            inputs = inputs.unsqueeze(0).expand(n, -1)
        if inputs.dim() != 2 or tuple(inputs.shape) != (n, self.n_inputs):
            raise ValueError(
                f"inputs must have shape (n, P) = ({n}, {self.n_inputs}) for inputs "
                f"{self.input_names}, or (P,), got {tuple(inputs.shape)}"
            )
        if not inputs.dtype.is_floating_point:
            raise ValueError(f"inputs must be floating point, got dtype {inputs.dtype}")
        if inputs.device != state.device:
            raise ValueError(f"state is on {state.device} but inputs on {inputs.device}")
        bad = torch.stack([(state < 0).any(), ~torch.isfinite(inputs).all()]).tolist()
        if bad[0]:
            raise ValueError("state must hold non-negative counts")
        if bad[1]:
            raise ValueError("inputs must be finite")
        return state.to(torch.int64), inputs

    def propensities(self, state: Tensor, inputs: Tensor) -> Tensor:
        """Checked propensities.

        Args:
            state: ``n x S`` integer species counts.
            inputs: ``n x P`` float per-cell inputs (``(P,)`` is shared by all cells).

        Returns:
            ``n x R`` float64 propensities, on the device of ``state``.
        """
        state, inputs = self.check_inputs(state, inputs)
        return self.torch_propensity(state, inputs)


def mass_action_kinetics(network: ReactionNetwork) -> Kinetics:
    """Mass-action kinetics of ``network`` with the rate constants as per-cell inputs.

    Input ``r`` (named ``k_<reaction name>``) is reaction ``r``'s rate constant ``c_r``, and
    ``a_r(x) = c_r prod_s binom(x_s, r_rs)`` as in :mod:`surrogate.ctmc.network`, so
    ``kinetics.torch_propensity(state, rate_constants)`` equals ``network.propensities``.
    """
    exprs = []
    reactants = network.reactants.tolist()
    for r, coeffs in enumerate(reactants):
        factors = [input_ref(r, f"k_{network.reaction_names[r]}")]
        for s, m in enumerate(coeffs):
            for k in range(m):
                x = species_ref(s, network.species[s])
                # binom(x, m) = prod_{k<m} (x - k) / (k + 1)
                factors.append(
                    x if k == 0 else call("divide", call("minus", x, const(k)), const(k + 1))
                )
        exprs.append(call("times", *factors))
    names = tuple(f"k_{name}" for name in network.reaction_names)
    return Kinetics(network=network, input_names=names, propensity_exprs=tuple(exprs))
