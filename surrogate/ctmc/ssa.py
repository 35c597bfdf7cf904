"""Exact batched Gillespie SSA (direct method) over one window of fixed rate constants.

Many independent chains (cells) advance together in *rounds*: each round every still-active cell
draws its next waiting time and, if the event falls inside its window, fires one reaction. Cells
whose next event would fall after the window end are finished; since rates are fixed over the
window the exponential waiting time is memoryless, so the state at that moment is the exact state
at the window end. Finished cells are dropped from the working set (compaction), so the cost of a
round is proportional to the number of cells still active and a few fast cells do not slow the
bulk. Each round costs exactly one host-device sync (the count of active cells).

Networks with species assignment rules or events (:mod:`surrogate.ctmc.events`) run the same
rounds with each cell's own time: a cell whose trigger may switch before its next reaction stops
there, fires its events and draws afresh (one more sync per round, for the events).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from surrogate.ctmc.events import EventProgram, EventState
from surrogate.ctmc.network import PropensityFn, ReactionNetwork, make_propensity_fn
from surrogate.errors import EventCapError

__all__ = ["gillespie"]

# Compact the working set once fewer than this fraction of its cells are still active. Just below
# 1 because carrying a finished cell through a round (~15 kernels) costs more than gathering an
# active one (~5 index_selects), while compacting for a single finished cell is pure overhead.
_COMPACT_BELOW = 0.9


def _check_dt(dt: float | Tensor, n: int, device: torch.device) -> Tensor:
    """Return the window lengths as a ``(n,)`` float64 tensor; ``ValueError`` unless all > 0."""
    if isinstance(dt, Tensor):
        if dt.dim() > 1 or (dt.dim() == 1 and dt.shape[0] != n):
            raise ValueError(f"dt must be a scalar or have shape ({n},), got {tuple(dt.shape)}")
        window = dt.to(device=device, dtype=torch.float64).expand(n).clone()
        if n and not bool(((window > 0) & torch.isfinite(window)).all()):
            raise ValueError("dt must be finite and > 0 for every cell")
        return window
    if isinstance(dt, bool) or not isinstance(dt, (int, float)):
        raise ValueError(f"dt must be a float or a tensor, got {type(dt).__name__}")
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0, got {dt}")
    return torch.full((n,), float(dt), dtype=torch.float64, device=device)


def gillespie(  # noqa: PLR0913  # the public SSA: its options are keyword-only
    network: ReactionNetwork,
    state: Tensor,
    rate_constants: Tensor,
    dt: float | Tensor,
    generator: torch.Generator | None = None,
    *,
    max_rounds: int | None = None,
    propensity: PropensityFn | None = None,
    events: EventProgram | None = None,
    clock: EventState | None = None,
) -> Tensor:
    """Sample the states of ``n`` independent chains after a window of length ``dt``.

    Exact Gillespie direct method with rate constants held fixed over the window. All work is
    vectorised over cells; the only Python loop is over event rounds (one event per active cell
    per round), so the number of rounds is the largest number of events any cell makes.

    Args:
        network: The reaction network.
        state: ``(n, S)`` non-negative integer counts at the window start.
        rate_constants: ``(n, R)`` non-negative rate constants per cell (``(R,)`` is shared by
            all cells).
        dt: Window length (> 0), a float or a ``(n,)`` tensor of per-cell lengths.
        generator: Random generator on the device of ``state`` (for reproducibility).
        max_rounds: If given, raise :class:`~surrogate.errors.EventCapError` (a
            ``RuntimeError``) when cells are still active after this many rounds (guards
            against unexpectedly stiff rates).
        propensity: Optional general kinetics ``f(state (m, S) int64, params (m, P)) -> (m, R)
            float64`` (e.g. ``Kinetics.torch_propensity``), called on the active cells' rows.
            ``rate_constants`` is then the ``(n, P)`` (or ``(P,)``) float tensor of per-cell
            parameters handed to it instead of mass-action rate constants; it must be finite
            but may have any width ``P``. Propensities that are negative or not finite, and
            events that drive a count negative, raise ``ValueError`` after the window (checked
            without extra host syncs per round).
        events: The rules and events of the kinetics
            (:meth:`~surrogate.ctmc.events.EventProgram.of`), if it has any; ``rate_constants``
            are then its inputs.
        clock: The cells' :class:`~surrogate.ctmc.events.EventState` on the device of
            ``state``, required with events (from :func:`~surrogate.ctmc.events.start_events`);
            advanced in place by ``dt``.

    Returns:
        ``(n, S)`` int64 counts at the window end, on the device of ``state``. A cell in an
        absorbing state (total propensity 0) stays where it is.
    """
    if propensity is None:
        state, rates = network.check_inputs(state, rate_constants)
    else:
        state, rates = _check_params(network, state, rate_constants)
    device = state.device
    if generator is not None and generator.device.type != device.type:
        raise ValueError(f"generator is on {generator.device} but state on {device}")
    if max_rounds is not None and max_rounds < 1:
        raise ValueError(f"max_rounds must be >= 1 or None, got {max_rounds}")
    n = state.shape[0]
    remaining = _check_dt(dt, n, device)
    out = state.clone()
    if n == 0:
        return out

    if events is not None:
        return _gillespie_events(network, state, rates, remaining, generator, max_rounds,
                                 propensity, (events, clock))  # fmt: skip
    general = propensity is not None
    if propensity is None:
        propensity = make_propensity_fn(network.reactants, device)
    invalid = torch.zeros((), dtype=torch.bool, device=device)  # general kinetics only
    stoich = network.stoichiometry.to(device)

    # Working set: states, rates, time left and original row of the cells still active.
    x = state.clone()
    c = rates.to(torch.float64)
    index = torch.arange(n, device=device)
    rounds = 0
    while True:
        a = propensity(x, c)
        if general:
            # Accumulated on the device: one check (and one sync) after the window.
            invalid = invalid | ~((a >= 0) & (a < math.inf)).all()
        tau, chosen = _draw(a, generator)
        fire = tau < remaining
        x = x + stoich.index_select(0, chosen) * fire.unsqueeze(1)
        if general:
            invalid = invalid | (x < 0).any()
        # A finished cell gets zero time left, so it can never fire again (tau >= 0).
        remaining = torch.where(fire, remaining - tau, 0.0)
        rounds += 1

        active = fire.nonzero().squeeze(1)  # the one host sync of the round
        n_active = active.shape[0]
        if n_active == 0:
            break
        if max_rounds is not None and rounds >= max_rounds:
            raise EventCapError(
                f"gillespie: {n_active} of {n} cells still active after max_rounds={max_rounds} "
                "event rounds; the rate constants are too large for this window (or raise "
                "max_rounds)"
            )
        if n_active < _COMPACT_BELOW * x.shape[0]:
            out.index_copy_(0, index, x)  # commit finished cells (active ones are rewritten)
            x = x.index_select(0, active)
            c = c.index_select(0, active)
            remaining = remaining.index_select(0, active)
            index = index.index_select(0, active)
    out.index_copy_(0, index, x)
    if general and bool(invalid):
        raise ValueError(
            "gillespie: the propensity function returned a negative or non-finite value, or a "
            "reaction fired that drove a count negative, during the window (check the kinetic "
            "laws: a reaction's propensity must be 0 when it lacks the molecules it consumes)"
        )
    return out


def _draw(a: Tensor, generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """``(tau, chosen)``: each row's waiting time (inf when its total propensity is 0) and
    reaction, drawn by the direct method from propensities ``a`` (``m x R``)."""
    cum = a.cumsum(dim=1)
    total = cum[:, -1]
    u = torch.rand((a.shape[0], 2), generator=generator, device=a.device, dtype=torch.float64)
    # 1 - u lies in (0, 1]: finite waiting times, and a threshold > 0 that never selects
    # a reaction of zero propensity (see below).
    tau = torch.where(total > 0, -torch.log1p(-u[:, 0]) / total, math.inf)
    # First reaction whose cumulative propensity reaches the threshold in (0, total]: this
    # has probability a_r / total, and a zero-propensity reaction r never wins because
    # cum[r] == cum[r - 1] then. cum is non-decreasing even in floating point.
    threshold = (1.0 - u[:, 1]) * total
    chosen = (cum < threshold.unsqueeze(1)).sum(dim=1).clamp_max(a.shape[1] - 1)
    return tau, chosen


def _gillespie_events(
    network: ReactionNetwork,
    state: Tensor,
    rates: Tensor,
    window: Tensor,
    generator: torch.Generator | None,
    max_rounds: int | None,
    propensity: PropensityFn | None,
    program: tuple[EventProgram, EventState | None],
) -> Tensor:
    """:func:`gillespie`'s rounds with rules and events, each cell on its own clock
    (``program``: :func:`gillespie`'s ``events`` and ``clock``; ``propensity`` None: mass
    action)."""
    device, n = state.device, state.shape[0]
    events, clock = program
    general = propensity is not None
    if propensity is None:
        propensity = make_propensity_fn(network.reactants, device)
    if clock is None:
        if events.n_events:
            names = [e.name for e in events.events]
            raise ValueError(
                f"the kinetics have events {names}: pass each cell's clock (state, clock = "
                "start_events(kinetics, state, inputs); then gillespie(..., clock=clock))"
            )
        clock = EventState.initial(events.kinetics, n, device)  # rules only: time not read
    clock.check(n, events.n_events, device)
    invalid = torch.zeros((), dtype=torch.bool, device=device)
    stoich = network.stoichiometry.to(device)
    c = rates.to(torch.float64)
    t, end = clock.time.clone(), clock.time + window
    # inputs may have changed since the last window: rules and triggers read them
    x = events.apply_rules(state.clone(), c)
    x, fired = events.check(x, c, t, clock.triggers.clone())
    out, out_fired = x.clone(), fired.clone()
    index = torch.arange(n, device=device)
    rounds = 0
    while True:
        a = propensity(x, c)
        if general:
            invalid = invalid | ~((a >= 0) & (a < math.inf)).all()
        tau, chosen = _draw(a, generator)
        reaction_time = t + tau
        switch = events.next_threshold(x, c, t)
        # a trigger may switch first: stop there, the next waiting time drawn afresh from
        # there (exact: it is memoryless)
        at_switch = (switch <= end) & (switch <= reaction_time)
        fire = ~at_switch & (reaction_time < end)
        x = x + stoich.index_select(0, chosen) * fire.unsqueeze(1)
        if general:
            invalid = invalid | (x < 0).any()
        # a finished cell is put at its window's end: no switch or reaction is left before it
        t = torch.where(at_switch, switch, torch.where(fire, reaction_time, end))
        x = events.apply_rules(x, c)
        x, fired = events.check(x, c, t, fired)
        rounds += 1
        active = (fire | at_switch).nonzero().squeeze(1)
        n_active = active.shape[0]
        if n_active == 0:
            break
        if max_rounds is not None and rounds >= max_rounds:
            raise EventCapError(
                f"gillespie: {n_active} of {n} cells still active after max_rounds={max_rounds} "
                "event rounds; the rate constants are too large for this window (or raise "
                "max_rounds)"
            )
        if n_active < _COMPACT_BELOW * x.shape[0]:
            out.index_copy_(0, index, x)
            out_fired.index_copy_(0, index, fired)
            x, c, fired = x.index_select(0, active), c.index_select(0, active), fired[active]
            t, end, index = t.index_select(0, active), end[active], index.index_select(0, active)
    out.index_copy_(0, index, x)
    out_fired.index_copy_(0, index, fired)
    if general and bool(invalid):
        raise ValueError(
            "gillespie: the propensity function returned a negative or non-finite value, or a "
            "reaction fired that drove a count negative, during the window (check the kinetic "
            "laws: a reaction's propensity must be 0 when it lacks the molecules it consumes)"
        )
    clock.time.add_(window)
    clock.triggers.copy_(out_fired)
    return out


def _check_params(network: ReactionNetwork, state: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Validate a ``(n, S)`` state and ``(n, P)`` (or ``(P,)``) finite float parameters."""
    if not isinstance(state, Tensor) or not isinstance(params, Tensor):
        raise ValueError("state and rate_constants (the propensity's parameters) must be tensors")
    if state.dim() != 2 or state.shape[1] != network.n_species:
        raise ValueError(
            f"state must have shape (n, S) with S = {network.n_species} species "
            f"{network.species}, got {tuple(state.shape)}"
        )
    if state.dtype.is_floating_point or state.dtype.is_complex or state.dtype == torch.bool:
        raise ValueError(f"state must hold integer counts, got dtype {state.dtype}")
    n = state.shape[0]
    if params.dim() == 1:
        params = params.unsqueeze(0).expand(n, -1)
    if params.dim() != 2 or params.shape[0] != n:
        raise ValueError(
            f"with a propensity function, rate_constants holds its per-cell parameters and "
            f"must have shape (n, P) with n = {n}, or (P,); got {tuple(params.shape)}"
        )
    if not params.dtype.is_floating_point:
        raise ValueError(f"rate_constants must be floating point, got dtype {params.dtype}")
    if params.device != state.device:
        raise ValueError(f"state is on {state.device} but rate_constants on {params.device}")
    bad = torch.stack([(state < 0).any(), ~torch.isfinite(params).all()]).tolist()
    if bad[0]:
        raise ValueError("state must hold non-negative counts")
    if bad[1]:
        raise ValueError("rate_constants (the propensity's parameters) must be finite")
    return state.to(torch.int64), params
