"""Species assignment rules and discrete events of a reaction network, simulated exactly.

A :class:`~surrogate.ctmc.kinetics.Kinetics` may carry

* species assignment rules (:class:`SpeciesRule`): a species whose count is a function of the
  others, recomputed after every reaction and event (every other expression reads the function
  itself, inlined, not the column);
* events (:class:`Event`): a trigger (a condition over species, inputs and the cell's own time)
  and assignments of species counts, executed at the instant the trigger goes from false to
  true. This is SBML's semantics without delays: ``initial_value`` is the trigger's value
  before t = 0; ``persistent`` and ``use_values_from_trigger_time`` matter only among events
  that fire at the same instant (executed in their order; a non-persistent one is dropped when
  an earlier one made its trigger false; assignment values are taken before any of them runs,
  or when the event runs); an event whose assignments make a trigger rise fires that event at
  the same instant (at most :data:`MAX_CASCADE` rounds).

Exactness. Between reactions the state is fixed, so a trigger over species and inputs can only
change at a reaction or event: triggers are checked after each. Time may enter a trigger only
in comparisons ``t < c``, ``t <= c``, ``t > c``, ``t >= c`` with ``c`` free of time (``t >= 25``,
``t < T_off``, also inside piecewise conditions), so between reactions a trigger is piecewise
constant in t and changes only where t crosses such a ``c``: the direct method stops at the next
crossing, checks the triggers there, and draws the next reaction time afresh from there (exact:
the waiting time is memoryless). A trigger is read as its value just after the instant (its
right limit: ``t > 25`` holds from 25 on), so an event fires at its threshold itself, also when
that is a window's end; at t = 0 the instant itself is checked first, against
``initial_value`` (:func:`start_events`), then its right limit. Inputs change only between
windows; each window starts with a check, so a trigger on an input fires where it changes.

Both SSA backends run them: :class:`~surrogate.ctmc.CompiledSSA` (numba source from
:func:`numba_source`) and :func:`~surrogate.ctmc.gillespie` (torch, :class:`EventProgram`). Each
cell carries an :class:`EventState`: its own time (continuing across windows) and each event's
trigger value at that time.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

# the rules' and events' declarations live with the kinetics that carry them
from surrogate.ctmc.kinetics import (
    Event,
    Expr,
    Kinetics,
    SpeciesRule,
    call,
    scalar_code,
    scalar_locals,
    time_comparison,
    time_thresholds,
    torch_function,
)

__all__ = [
    "MAX_CASCADE",
    "WHOLE_TOLERANCE",
    "Event",
    "EventProgram",
    "EventState",
    "SpeciesRule",
    "numba_source",
    "right_limit",
    "start_events",
    "time_thresholds",
    "whole_counts",
]

#: rounds of events firing events at one instant before the simulation is stopped as endless
MAX_CASCADE = 1000
#: an assigned count must be within this relative distance (at least 1 molecule x this) of a
#: whole number >= 0 (rules and events compute in float64; 2 * X / 2 may round off)
WHOLE_TOLERANCE = 1e-9

#: a comparison with the time on the left, just after the instant: t > c holds from c on
#: (t >= c), t <= c stops holding at c (t < c); the other two are right-continuous already
_RIGHT_LIMIT = {"gt": "geq", "leq": "lt", "lt": "lt", "geq": "geq"}


def right_limit(e: Expr) -> Expr:
    """The condition just after each instant (see the module docstring): every time comparison
    replaced by its right-continuous form, ``t > c`` by ``t >= c`` and ``t <= c`` by ``t < c``.
    Equal to ``e`` except at its thresholds."""
    found = time_comparison(e)
    if found is not None:
        op, c = found
        return call(_RIGHT_LIMIT[op], e.args[0] if e.args[0].op == "time" else e.args[1], c)
    if not e.uses_time():
        return e
    return call(e.op, *(right_limit(arg) for arg in e.args))


@dataclass
class EventState:
    """Per-cell state of a network with events, carried from window to window.

    Attributes:
        time: ``(n,)`` float64: each cell's own network time.
        triggers: ``(n, E)`` bool: each event's trigger value at that time (just after it).
    """

    time: Tensor
    triggers: Tensor

    @classmethod
    def initial(cls, kinetics: Kinetics, n: int, device: torch.device | str = "cpu") -> EventState:
        """Time 0 and every trigger at its ``initial_value`` (before t = 0)."""
        values = [event.initial_value for event in kinetics.events]
        triggers = torch.tensor(values, dtype=torch.bool, device=device)
        return cls(
            torch.zeros(n, dtype=torch.float64, device=device),
            triggers.unsqueeze(0).expand(n, -1).clone(),
        )

    @property
    def n(self) -> int:
        """Number of cells."""
        return int(self.time.shape[0])

    def check(self, n: int, n_events: int, device: torch.device) -> None:
        """Raise ``ValueError`` unless this holds ``n`` cells' state of ``n_events`` events on
        ``device`` (float64 times, bool triggers)."""
        if tuple(self.time.shape) != (n,) or self.time.dtype != torch.float64:
            raise ValueError(
                f"clock.time must be ({n},) float64, got {tuple(self.time.shape)} {self.time.dtype}"
            )
        if tuple(self.triggers.shape) != (n, n_events) or self.triggers.dtype != torch.bool:
            raise ValueError(
                f"clock.triggers must be ({n}, {n_events}) bool, got "
                f"{tuple(self.triggers.shape)} {self.triggers.dtype}"
            )
        if self.time.device != device or self.triggers.device != device:
            raise ValueError(f"clock must be on {device} with the state")


def whole_counts(values: Tensor) -> tuple[Tensor, Tensor]:
    """``(counts int64, ok bool)``: ``values`` (float64, any shape) rounded, and where that
    is a whole number >= 0 within :data:`WHOLE_TOLERANCE` (counts 0 elsewhere)."""
    rounded = torch.floor(values + 0.5)
    close = (values - rounded).abs() <= WHOLE_TOLERANCE * values.abs().clamp_min(1.0)
    ok = close & (rounded >= 0) & torch.isfinite(values)
    return torch.where(ok, rounded, 0.0).to(torch.int64), ok


_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class EventProgram:
    """The rules and events of one :class:`~surrogate.ctmc.kinetics.Kinetics` as torch
    functions over many cells (any device); used by the batched SSA and :func:`start_events`.

    Args:
        kinetics: The kinetics whose ``rules`` and ``events`` to run.
    """

    def __init__(self, kinetics: Kinetics) -> None:
        self.kinetics = kinetics
        self.events = kinetics.events
        self.n_events = len(self.events)
        events, rules = self.events, kinetics.rules
        self._triggers: Callable[..., Tensor] | None = None
        self._exact: Callable[..., Tensor] | None = None
        self._thresholds: Callable[..., Tensor] | None = None
        self._rules: Callable[..., Tensor] | None = None
        if events:
            self._triggers = torch_function([right_limit(e.trigger) for e in events], time=True)
            self._exact = torch_function([e.trigger for e in events], time=True)
        thresholds = [c for event in events for c in event.thresholds]
        if thresholds:
            self._thresholds = torch_function(thresholds)
        self._values = [
            torch_function([expr for _, expr in e.assignments], time=True)
            if e.assignments
            else None
            for e in events
        ]
        self._columns = [torch.tensor([c for c, _ in e.assignments]) for e in events]
        if rules:
            self._rules = torch_function([rule.expr for rule in rules])
        self._rule_columns = torch.tensor([rule.column for rule in rules], dtype=torch.int64)

    @classmethod
    def of(cls, kinetics: Kinetics) -> EventProgram:
        """The program of ``kinetics`` (built once per kinetics object)."""
        program = _PROGRAMS.get(kinetics)
        if program is None:
            program = _PROGRAMS[kinetics] = cls(kinetics)
        return program

    def _species(self, column: int) -> str:
        return self.kinetics.network.species[column]

    def apply_rules(self, x: Tensor, p: Tensor) -> Tensor:
        """``x`` (``m x S`` int64) with every rule's column set to its value at ``(x, p)``.

        Raises:
            ValueError: a rule's value is not a whole number >= 0 (naming the species).
        """
        if self._rules is None:
            return x
        counts, ok = whole_counts(self._rules(x, p))
        if not bool(ok.all()):
            row, k = (int(v) for v in (~ok).nonzero()[0])
            value = float(self._rules(x, p)[row, k])
            raise ValueError(
                f"the rule for species {self._species(self.kinetics.rules[k].column)!r} gives "
                f"{value!r}, not a whole number of molecules >= 0 (state {x[row].tolist()})"
            )
        return x.index_copy(1, self._rule_columns.to(x.device), counts)

    def next_threshold(self, x: Tensor, p: Tensor, t: Tensor) -> Tensor:
        """``(m,)`` float64: the first time after ``t`` at which a trigger may switch (inf if
        none)."""
        if self._thresholds is None:
            return torch.full_like(t, math.inf)
        values = self._thresholds(x, p)
        later = torch.where(values > t.unsqueeze(1), values, math.inf)
        return later.min(dim=1).values

    def _assigned(self, e: int, x: Tensor, p: Tensor, t: Tensor) -> Tensor | None:
        fn = self._values[e]
        return None if fn is None else fn(x, p, t)

    def _store(self, e: int, x: Tensor, rows: Tensor, values: Tensor | None) -> Tensor:
        if values is None:
            return x
        counts, ok = whole_counts(values)
        bad = rows.unsqueeze(1) & ~ok
        if bool(bad.any()):
            row, k = (int(v) for v in bad.nonzero()[0])
            species = self._species(self.events[e].assignments[k][0])
            raise ValueError(
                f"event {self.events[e].name!r} assigns species {species!r} the value "
                f"{float(values[row, k])!r}, not a whole number of molecules >= 0 (state "
                f"{x[row].tolist()})"
            )
        new = x.index_copy(1, self._columns[e].to(x.device), counts)
        return torch.where(rows.unsqueeze(1), new, x)

    def check(
        self, x: Tensor, p: Tensor, t: Tensor, fired: Tensor, exact: bool = False
    ) -> tuple[Tensor, Tensor]:
        """Fire every event whose trigger rose since ``fired`` was recorded, then those their
        assignments make rise, at the cells' times ``t``.

        Args:
            x: ``m x S`` int64 counts.
            p: ``m x P`` float64 inputs.
            t: ``(m,)`` float64 times.
            fired: ``m x E`` bool: each trigger's last value.
            exact: Read the triggers at the instant itself (t = 0), not just after it.

        Returns:
            ``(x, triggers)``: the counts after the events and each trigger's value now.

        Raises:
            ValueError: an assignment that is not a whole number of molecules >= 0.
            RuntimeError: events still firing each other after :data:`MAX_CASCADE` rounds.
        """
        if self.n_events == 0:
            return x, fired
        triggers = self._exact if exact else self._triggers
        assert triggers is not None  # there are events
        for _ in range(MAX_CASCADE):
            now = triggers(x, p, t)
            pending = now & ~fired
            fired = now
            if not bool(pending.any()):  # one host sync per check
                return x, fired
            early = [
                self._assigned(e, x, p, t) if event.use_values_from_trigger_time else None
                for e, event in enumerate(self.events)
            ]
            for e, event in enumerate(self.events):
                rows = pending[:, e]
                if not event.persistent:
                    rows = rows & triggers(x, p, t)[:, e]
                values = early[e] if event.use_values_from_trigger_time else None
                if values is None:
                    values = self._assigned(e, x, p, t)
                x = self.apply_rules(self._store(e, x, rows, values), p)
        names = [event.name for event in self.events]
        raise RuntimeError(
            f"events {names} still fired each other after {MAX_CASCADE} rounds at one instant "
            "(an event whose assignments keep its own or another's trigger rising)"
        )


def start_events(kinetics: Kinetics, state: Tensor, inputs: Tensor) -> tuple[Tensor, EventState]:
    """The state at t = 0 and the cells' :class:`EventState`: rules applied, then the events
    whose trigger holds at t = 0 while its ``initial_value`` is False fired (at the instant,
    then just after it).

    Args:
        kinetics: The network with its rules and events.
        state: ``n x S`` integer counts (e.g. ``SbmlModel.initial_states(n)``).
        inputs: ``n x P`` (or ``(P,)``) float inputs at t = 0.

    Returns:
        ``(state, clock)``: ``n x S`` int64 counts and the clock to hand every window.

    Example:
        >>> state, clock = start_events(model.kinetics, model.initial_states(100), inputs)
        >>> state, _ = ssa.advance(state, inputs, 1.0, streams, clock=clock)
    """
    state, inputs = kinetics.check_inputs(state, inputs)
    program = EventProgram.of(kinetics)
    x = program.apply_rules(state, inputs.to(torch.float64))
    clock = EventState.initial(kinetics, x.shape[0], x.device)
    p = inputs.to(torch.float64)
    x, fired = program.check(x, p, clock.time, clock.triggers, exact=True)
    x, fired = program.check(x, p, clock.time, fired)
    clock.triggers = fired
    return x, clock


# ----------------------------------------------------------------------------------------------
# scalar (numba) code of the compiled SSA

_JIT = "@numba.njit(cache=True, error_model='numpy', inline='always')"


def _function(head: str, exprs: Sequence[Expr], body: list[str]) -> list[str]:
    return [_JIT, f"def {head}:", *scalar_locals(exprs), *(body or ["    pass"]), "", ""]


def numba_source(kinetics: Kinetics) -> str:
    """Scalar per-cell functions of the rules and events for the compiled SSA's kernel:
    ``triggers(x, p, t, out)`` (right limits, ``(E,)`` bool), ``thresholds(x, p, out)``
    (``(N_THRESHOLDS,)``), ``event_values(e, x, p, t, v)`` (event ``e``'s values into ``v``),
    ``apply_rules(x, p) -> int`` (-1, or the rule whose value is not a whole number), and the
    constant ``N_THRESHOLDS``. Uses ``store_whole`` of the kernel template."""
    events, rules = kinetics.events, kinetics.rules
    triggers = [right_limit(e.trigger) for e in events]
    thresholds = [c for e in events for c in e.thresholds]
    lines = [f"N_THRESHOLDS = {len(thresholds)}", "", ""]
    body = [f"    out[{k}] = {scalar_code(e)}" for k, e in enumerate(triggers)]
    lines += _function("triggers(x, p, t, out)", triggers, body)
    body = [f"    out[{k}] = {scalar_code(c)}" for k, c in enumerate(thresholds)]
    lines += _function("thresholds(x, p, out)", thresholds, body)
    body = []
    for e, event in enumerate(events):
        body.append(f"    {'if' if e == 0 else 'elif'} e == {e}:")
        body += [f"        v[{k}] = {scalar_code(expr)}" for k, (_, expr) in
                 enumerate(event.assignments)] or ["        pass"]  # fmt: skip
    values = [expr for event in events for _, expr in event.assignments]
    lines += _function("event_values(e, x, p, t, v)", values, body)
    body = []
    for k, rule in enumerate(rules):
        body += [
            f"    if not store_whole(x, {rule.column}, {scalar_code(rule.expr)}):",
            f"        return {k}",
        ]
    lines += _function("apply_rules(x, p)", [rule.expr for rule in rules], [*body, "    return -1"])
    return "\n".join(lines)
