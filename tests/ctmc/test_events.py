"""Species assignment rules and events on both SSAs (compiled numba kernel, batched torch):
closed forms of an immigration-death process reset by a time-triggered event, identities that
hold in every cell (a rule's value, one firing per upward crossing, a trigger on an input),
SBML's semantics of simultaneous events, and the clear errors of what is refused."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import pytest
import torch

from surrogate.ctmc import CellStreams, CompiledSSA, ReactionNetwork, gillespie
from surrogate.ctmc.events import (
    Event,
    EventProgram,
    EventState,
    SpeciesRule,
    right_limit,
    start_events,
    time_thresholds,
)
from surrogate.ctmc.kinetics import Expr, Kinetics, call, const, input_ref, species_ref, time_ref

BACKENDS = ("compiled", "batched")
#: |Z| of a sample mean against its closed form: P(|N(0, 1)| > 4) = 6.3e-5 per check
Z_BOUND = 4.0


def c(value: float) -> Expr:
    return const(float(value))


def t_geq(value: float) -> Expr:
    return call("geq", time_ref(), c(value))


def run(
    kinetics: Kinetics,
    state: torch.Tensor,
    windows: Sequence[float],
    backend: str,
    inputs: Sequence[Sequence[float]] | None = None,
    seed: int = 0,
) -> list[torch.Tensor]:
    """States after each window (``inputs[k]``: the inputs of window k; the first also at
    t = 0), every cell on its own clock."""
    n = state.shape[0]
    inputs = inputs or [[]] * len(windows)
    p = [torch.tensor(v, dtype=torch.float64).expand(n, -1) for v in inputs]
    state, clock = start_events(kinetics, state, p[0])
    if backend == "compiled":
        ssa, streams = CompiledSSA(kinetics, parallel=False), CellStreams.from_seed(seed, n)
    else:
        generator, program = torch.Generator().manual_seed(seed), EventProgram.of(kinetics)
    out = []
    for dt, pk in zip(windows, p, strict=True):
        if backend == "compiled":
            state, _ = ssa.advance(state, pk, dt, streams, clock=clock)
        else:
            state = gillespie(kinetics.network, state, pk, dt, generator,
                              propensity=kinetics.torch_propensity, events=program,
                              clock=clock)  # fmt: skip
        out.append(state)
    assert torch.equal(clock.time, torch.full((n,), float(sum(windows)), dtype=torch.float64))
    return out


# ----------------------------------------------------------------------------------------------
# an immigration-death process reset at a time T (DSMTS 002-09 in small)

ALPHA, MU, RESET = 2.0, 0.5, 20


def immigration_death(at: float) -> Kinetics:
    """0 -> X at ALPHA, X -> 0 at MU X, and X := RESET at t = ``at``."""
    network = ReactionNetwork.from_reactions(
        ["X"], [("immigration", {}, {"X": 1}), ("death", {"X": 1}, {})]
    )
    x = species_ref(0, "X")
    reset = Event("reset", t_geq(at), ((0, c(RESET)),), initial_value=False)
    return Kinetics(network, (), (c(ALPHA), call("times", c(MU), x)), events=(reset,))


def law(t: float, at: float) -> tuple[float, float]:
    """Mean and variance of X(t): Poisson from X(0) = 0 before ``at``; after it the RESET
    molecules survive independently (binomial) beside a Poisson of new ones."""
    stationary = ALPHA / MU
    if t < at:
        mean = stationary * (1 - math.exp(-MU * t))
        return mean, mean
    p = math.exp(-MU * (t - at))
    return RESET * p + stationary * (1 - p), RESET * p * (1 - p) + stationary * (1 - p)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_time_event_inside_a_window_resets_the_count_at_its_instant(backend: str) -> None:
    """The reset at 2.5 falls inside the window (2, 3]: the mean at 3 is the closed form half a
    second after it (16.5); fired at the window's end it would be 20 with no spread, skipped
    it would be 3.1. Sample means of 4,000 cells within Z_BOUND of the closed form."""
    n, at = 4000, 2.5
    states = run(immigration_death(at), torch.zeros(n, 1, dtype=torch.int64), [1.0] * 5, backend)
    for t in (2, 3, 5):
        mean, variance = law(float(t), at)
        z = (states[t - 1][:, 0].double().mean().item() - mean) / math.sqrt(variance / n)
        assert abs(z) < Z_BOUND, (t, z)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_time_event_at_a_window_end_fires_in_that_window(backend: str) -> None:
    states = run(immigration_death(2.0), torch.zeros(50, 1, dtype=torch.int64), [1.0] * 3, backend)
    assert (states[1][:, 0] == RESET).all()  # t = 2: every cell just reset
    assert not (states[2][:, 0] == RESET).all()


# ----------------------------------------------------------------------------------------------
# identities that hold in every cell


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_rule_equals_its_formula_after_every_event(backend: str) -> None:
    """y = 2 X + 3 over a birth-death X reset to 7 at t = 0.5; windows of 0.01 (about one
    reaction each) show the rule after every reaction and the event."""
    network = ReactionNetwork.from_reactions(
        ["X", "y"], [("birth", {"X": 1}, {"X": 2}), ("death", {"X": 1}, {})]
    )
    x = species_ref(0, "X")
    kinetics = Kinetics(
        network,
        (),
        (call("times", c(1.0), x), call("times", c(1.1), x)),
        rules=(SpeciesRule(1, call("plus", call("times", c(2.0), x), c(3.0))),),
        events=(Event("reset", t_geq(0.5), ((0, c(7.0)),)),),
    )
    state = torch.tensor([[5, 0]] * 200)
    states = run(kinetics, state, [0.01] * 100, backend)
    for s in states:
        assert torch.equal(s[:, 1], 2 * s[:, 0] + 3)
    assert (states[49][:, 0] == 7).all()  # t = 0.5: just reset
    changed = sum(int((a[:, 0] != b[:, 0]).sum()) for a, b in itertools.pairwise(states))
    assert changed > 1000  # the windows did see reactions


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_state_event_fires_once_per_upward_crossing(backend: str) -> None:
    """Birth-death X with the birth at X = 4 a reaction of its own that also makes W: W counts
    the upward crossings of X >= 5; the event (C := C + 1 when X >= 5, X untouched, so the
    trigger stays true after it fires) must count the same in every cell."""
    network = ReactionNetwork.from_reactions(
        ["X", "W", "C"],
        [
            ("birth_below", {}, {"X": 1}),
            ("birth_at_4", {}, {"X": 1, "W": 1}),
            ("death", {"X": 1}, {}),
        ],
    )
    x = species_ref(0, "X")
    at_4 = call("eq", x, c(4.0))
    propensities = (
        call("piecewise", c(0.0), at_4, c(3.0)),
        call("piecewise", c(3.0), at_4, c(0.0)),
        call("times", c(0.5), x),
    )
    count = Event(
        "count", call("geq", x, c(5.0)), ((2, call("plus", species_ref(2, "C"), c(1.0))),)
    )
    kinetics = Kinetics(network, (), propensities, events=(count,))
    states = run(kinetics, torch.zeros(300, 3, dtype=torch.int64), [1.0] * 10, backend)
    for s in states:
        assert torch.equal(s[:, 1], s[:, 2])
    assert states[-1][:, 2].double().mean() > 3  # many crossings per cell


def no_reactions(species: Sequence[str]) -> ReactionNetwork:
    return ReactionNetwork.from_reactions(list(species), [("none", {}, {species[0]: 1})])


def plus_one(column: int, name: str) -> Expr:
    return call("plus", species_ref(column, name), c(1.0))


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_trigger_on_an_input_fires_where_the_input_rises_and_a_rule_follows_it(
    backend: str,
) -> None:
    """C counts the rises of the input L above 0.5 (at t = 0 and at the start of the 4th
    window); y = C + L is recomputed at every window's start although no reaction runs."""
    network = no_reactions(["C", "y"])
    level = input_ref(0, "L")
    rises = Event("rises", call("gt", level, c(0.5)), ((0, plus_one(0, "C")),), False)
    rule = SpeciesRule(1, call("plus", species_ref(0, "C"), level))
    kinetics = Kinetics(network, ("L",), (c(0.0),), rules=(rule,), events=(rises,))
    levels = [[1.0], [1.0], [0.0], [1.0], [3.0]]
    states = run(kinetics, torch.zeros(3, 2, dtype=torch.int64), [1.0] * 5, backend, levels)
    assert [int(s[0, 0]) for s in states] == [1, 1, 1, 2, 2]
    assert [int(s[0, 1]) for s in states] == [2, 2, 1, 3, 5]


@pytest.mark.parametrize("backend", BACKENDS)
def test_initial_value_and_the_instant_t0(backend: str) -> None:
    """A trigger true at t = 0 fires there iff its initial value is False; ``t <= 0`` holds
    at the instant t = 0 only, and fires there (read just after 0 it would be false)."""
    network = no_reactions(["A", "B", "D"])
    always = call("geq", species_ref(0, "A"), c(0.0))
    events = (
        Event("from_false", always, ((0, plus_one(0, "A")),), initial_value=False),
        Event("from_true", always, ((1, plus_one(1, "B")),), initial_value=True),
        Event("instant", call("leq", time_ref(), c(0.0)), ((2, c(1.0)),), initial_value=False),
    )
    kinetics = Kinetics(network, (), (c(0.0),), events=events)
    states = run(kinetics, torch.zeros(2, 3, dtype=torch.int64), [1.0, 1.0], backend)
    assert states[-1].tolist() == [[1, 0, 1]] * 2


@pytest.mark.parametrize("backend", BACKENDS)
def test_simultaneous_events_persistence_values_and_cascades(backend: str) -> None:
    """Five pairs of events at t = 1, each pair on species of its own, run in order:
    persistent False drops B1 (A1 made its trigger false), persistent True keeps B2; B3 takes
    its value before A3 runs (useValuesFromTriggerTime), B4 after; A5's assignment raises B5's
    trigger, which fires at the same instant."""
    names = ["X1", "C1", "X2", "C2", "X3", "Y3", "X4", "Y4", "X5", "C5"]
    network = no_reactions(names)
    s = {name: species_ref(k, name) for k, name in enumerate(names)}
    col = {name: k for k, name in enumerate(names)}
    at_1 = t_geq(1.0)
    still = {k: call("and", at_1, call("gt", s[f"X{k}"], c(0.0))) for k in (1, 2)}
    events = (
        Event("A1", at_1, ((col["X1"], c(0.0)),)),
        Event("A2", at_1, ((col["X2"], c(0.0)),)),
        Event("A3", at_1, ((col["X3"], plus_one(col["X3"], "X3")),)),
        Event("A4", at_1, ((col["X4"], plus_one(col["X4"], "X4")),)),
        Event("A5", at_1, ((col["X5"], c(10.0)),)),
        Event("B1", still[1], ((col["C1"], c(1.0)),), persistent=False),
        Event("B2", still[2], ((col["C2"], c(1.0)),), persistent=True),
        Event("B3", at_1, ((col["Y3"], s["X3"]),), use_values_from_trigger_time=True),
        Event("B4", at_1, ((col["Y4"], s["X4"]),), use_values_from_trigger_time=False),
        Event("B5", call("geq", s["X5"], c(10.0)), ((col["C5"], plus_one(col["C5"], "C5")),)),
    )
    kinetics = Kinetics(network, (), (c(0.0),), events=events)
    start = torch.tensor([[5, 0, 5, 0, 5, 0, 5, 0, 0, 0]])
    final = dict(zip(names, run(kinetics, start, [2.0], backend)[-1][0].tolist(), strict=True))
    assert final == {"X1": 0, "C1": 0, "X2": 0, "C2": 1, "X3": 6, "Y3": 5, "X4": 6, "Y4": 6,
                     "X5": 10, "C5": 1}  # fmt: skip


def test_time_thresholds_and_right_limits() -> None:
    x = species_ref(0, "X")
    nested = call(
        "and",
        call("gt", call("piecewise", c(1.0), call("gt", time_ref(), c(5.0)), c(0.0)), c(0.0)),
        call("lt", x, time_ref()),
    )
    assert time_thresholds(nested) == (c(5.0), x)
    limit = right_limit(nested)
    # just after t = 5: t > 5 reads as t >= 5; X < t (t > X) as X <= t
    assert limit.evaluate([5.0], [], 5.0) is True and nested.evaluate([5.0], [], 5.0) is False
    assert right_limit(call("leq", time_ref(), c(3.0))).evaluate([], [], 3.0) is False


# ----------------------------------------------------------------------------------------------
# what is refused, and errors at run time


@pytest.mark.parametrize(
    ("trigger", "message"),
    [
        (call("eq", time_ref(), c(5.0)), "only be compared"),
        (call("gt", call("times", c(2.0), time_ref()), c(5.0)), "only be compared"),
        (call("gt", time_ref(), call("plus", time_ref(), c(1.0))), "only be compared"),
        (c(1.0), "must be a condition"),
    ],
)
def test_an_event_with_a_trigger_that_is_not_piecewise_constant_in_time_is_refused(
    trigger: Expr, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        Event("E", trigger, ((0, c(1.0)),))


def test_malformed_rules_and_events_are_refused_by_name() -> None:
    network = ReactionNetwork.from_reactions(["X", "y"], [("death", {"X": 1}, {})])
    x, y = species_ref(0, "X"), species_ref(1, "y")
    law = (call("times", c(1.0), x),)

    def kinetics(**kwargs) -> Kinetics:
        return Kinetics(network, (), kwargs.pop("laws", law), **kwargs)

    with pytest.raises(ValueError, match="'death': propensity depends on the time"):
        kinetics(laws=(call("times", time_ref(), x),))
    with pytest.raises(ValueError, match="may not read the time"):
        SpeciesRule(1, time_ref())
    with pytest.raises(ValueError, match="rule for species 'X': the species is also changed"):
        kinetics(rules=(SpeciesRule(0, c(1.0)),))
    with pytest.raises(ValueError, match=r"reads \['y'\]"):
        kinetics(rules=(SpeciesRule(1, y),))
    with pytest.raises(ValueError, match="event 'E': assigns species 'y', which a rule"):
        kinetics(rules=(SpeciesRule(1, x),), events=(Event("E", t_geq(1.0), ((1, c(0.0)),)),))


@pytest.mark.parametrize("backend", BACKENDS)
def test_errors_at_run_time_name_the_event_or_rule(backend: str) -> None:
    """Inside a window (the kernels' own checks): a count of 2.5 assigned, a rule X / 2 at an
    odd X after a birth, two events that undo each other without end after a death."""
    x = species_ref(0, "X")

    def kinetics(change: tuple[str, dict, dict], **kwargs) -> Kinetics:
        network = ReactionNetwork.from_reactions(["X", "y"], [change])
        return Kinetics(network, (), (call("times", c(10.0), x),), **kwargs)

    birth, death = ("birth", {"X": 1}, {"X": 2}), ("death", {"X": 1}, {})
    half = kinetics(death, events=(Event("half", t_geq(0.5), ((0, c(2.5)),)),))
    with pytest.raises(ValueError, match="event 'half' assigns"):
        run(half, torch.tensor([[3, 0]]), [1.0], backend)
    halves = kinetics(birth, rules=(SpeciesRule(1, call("divide", x, c(2.0))),))
    with pytest.raises(ValueError, match="rule for species 'y'"):
        run(halves, torch.tensor([[2, 0]]), [1.0], backend)
    flip = kinetics(
        death,
        events=(
            Event("up", call("eq", x, c(0.0)), ((0, c(1.0)),)),
            Event("down", call("eq", x, c(1.0)), ((0, c(0.0)),)),
        ),
    )
    with pytest.raises(RuntimeError, match="fired each other"):
        run(flip, torch.tensor([[3, 0]]), [1.0], backend)
    with pytest.raises(ValueError, match="pass each cell's clock"):
        if backend == "compiled":
            CompiledSSA(half, parallel=False).advance(
                torch.tensor([[3, 0]]), torch.zeros(0), 1.0, CellStreams.from_seed(0, 1)
            )
        else:
            gillespie(half.network, torch.tensor([[3, 0]]), torch.zeros(1, 0, dtype=torch.float64),
                      1.0, propensity=half.torch_propensity, events=EventProgram.of(half))  # fmt: skip


def test_the_clock_is_checked() -> None:
    kinetics = immigration_death(1.0)
    clock = EventState.initial(kinetics, 3)
    with pytest.raises(ValueError, match=r"clock.time must be \(2,\)"):
        CompiledSSA(kinetics, parallel=False).advance(
            torch.zeros(2, 1, dtype=torch.int64), torch.zeros(0), 1.0,
            CellStreams.from_seed(0, 2), clock=clock,
        )  # fmt: skip
