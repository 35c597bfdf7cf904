"""Transitions (x, phi, phi') recorded from full-model runs: training data and occupancy.

:func:`collect_transitions` runs the full model with sporadic perturbations (the body's: e.g.
jumps to random points of a disc around the field's peak) until enough transitions from each
origin state are recorded, the paper's micro-trajectory data. :func:`record_occupancy` runs it
unperturbed from a start and records where the population actually lives, the weights of the
abstraction's diagnostic.

Each row: the model's inputs (``x`` columns), its declared features, ``phi`` and ``phi_next``
(the property before and after the window), ``cell``, ``t`` (start of the window),
``since_jump`` (steps since the cell was last perturbed; -1 if never), ``phi_age`` (s since the
cell's phi last changed, at the window's start: the switch clock of
:mod:`surrogate.simulate.memory`) and ``phi_age_censored`` (true while the cell has not switched
since recording began: ``phi_age`` is then only a lower bound); with ``expected``,
``phi_next_expected``: the probability that phi is 1 after the window given the internal state at
its start (the internal model's ``expected_phi_next``). Its mean given x is psi(x), like the 0/1
outcome's, but without the window's own randomness: a Rao-Blackwellised label with a smaller
variance (measured for each model in docs/fidelity.md). Where the internal model declares K-lumps
classes (:mod:`surrogate.simulate.classes`), ``phi_class`` and ``phi_class_next``: the window's
class before and after; with ``expected`` and a model that gives it
(``expected_class_next``), ``phi_class_next_expected_<b>``: the law of the class after the window
given the internal state at its start.

With ``keep_switches`` (``collect.keep_switches``) a thinned collection also keeps every window
where phi changed, off the thinned steps too, and gives each row the :data:`WINDOWS` it stands
for: ``record_every`` for a window where phi held (one recorded of every ``record_every``), 1 for
one where it changed (all recorded). Weighting each row by them (inverse-probability weighting)
makes every sum over rows the sum over all windows in expectation, so psi's bins, the support
histograms and the after-jump rates read the rows as they read every window, with every switch
in them: the switches that psi rests on, at the rows of the thinned collection (a case-control
sample; docs/choice.md). Where the model declares classes, a window where the class changed is
kept as a switch is: the K-lumps chain's moves within a lump are as rare per window as a switch,
and a thinned table held one in ``record_every`` of them, each weighted ``record_every`` (on
the immigration-death network a mean sojourn of the fitted chain moved by 4-5 % at a given
input from that noise alone; docs/sbml.md). The weighting stays unbiased whatever the rule that
keeps a window (a window kept for itself counts once, one kept only on a thinned step
``record_every`` times), so this holds for phi's sums as well, and for bins chosen at train time.

No window within ``blackout`` steps after a perturbation is recorded: right after a jump the
internal network's hidden state (which motors are where, within the current lump) still belongs
to the old inputs, so those transitions are not draws of psi at the recorded inputs (measured:
the windows right after a jump alone bias the switching probability from TUMBLE by -42 %, and
recording them biased a learned psi by -2 %; a blackout of 1 s, ~3 motor relaxation times,
removes it).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor
from tqdm.auto import tqdm

from surrogate.errors import ConfigError, NumericalError
from surrogate.gp.windows import WINDOWS, origin_rows
from surrogate.models.base import Perturbation
from surrogate.models.capabilities import (
    ClassCount,
    class_count_of,
    expected_class_next_of,
    expected_phi_next_of,
    feature_names_of,
    features_of,
    lump_classes_of,
)
from surrogate.simulate.classes import (
    CLASS,
    CLASS_COUNT,
    CLASS_COUNT_NEXT,
    CLASS_NEXT,
    expected_class_column,
)
from surrogate.simulate.design import GuidedJump
from surrogate.simulate.loop import PopulationState, Simulator
from surrogate.simulate.memory import AGE, CENSORED, tick

#: column of the expected label: P(phi' = 1 | the internal state at the window's start, x)
EXPECTED = "phi_next_expected"
#: collect checks each origin's rate of rows once this share of ``max_time`` is recorded ...
EARLY_CHECK_SHARE = 0.05
#: ... and stops when the rows one origin would reach by ``max_time`` fall short of those
#: wanted by more than this factor (a lump almost never or always true where cells live: more
#: time would not help, a different lump would)
FAR_SHORT = 10.0
#: ... or, a lump common enough, when they fall short by more than this factor: more time or
#: cells would help, and waiting out ``max_time`` only to be told so would not (a collection
#: the inspector budgeted at the median inputs' occupancy, which collect's perturbed cells
#: need not share: StochSS's Tyson oscillator, 20 % of its rows at the end of 2,000 s)
SHORT = 4.0
#: a lump seen in fewer windows than this share is called rare in collect's messages
RARE = 0.05


@dataclass(frozen=True)
class CollectOptions:
    """How :func:`collect_transitions` records (every field has its default).

    Attributes:
        record_every: steps between recorded transitions per cell (thins autocorrelated rows).
        equilibration_time: internal dynamics before cells move (s).
        max_time: simulated seconds before giving up (ConfigError).
        blackout: steps after a jump during which a cell's windows are not recorded (see the
            module docstring).
        expected: also record each window's expected label (``phi_next_expected``).
        keep_switches: also record every window where phi (or, where the model declares
            classes, the class) changed, off the thinned steps, each row with the
            :data:`WINDOWS` it stands for (see the module docstring).
        classes_of_state: record the classes the internal model declares, read from the
            decision's state (False for a layer that does not carry the internal model's
            state: an abstraction's).
    """

    record_every: int = 1
    equilibration_time: float = 10.0
    max_time: float = 2000.0
    blackout: int = 0
    expected: bool = False
    keep_switches: bool = False
    classes_of_state: bool = True


def _count_columns(
    internal: Any,
    count: ClassCount | None,
    before: tuple[Tensor, ...],
    after: tuple[Tensor, ...],
    x: Tensor,
    rows: Tensor,
    expected: bool,
    dt: float,
) -> dict[str, np.ndarray]:
    """The recorded ``rows``' class columns beyond the classes: the count the bins read
    before and after the window (where the classes are bins of a count) and the expected
    class law (where asked and the model gives it)."""
    out: dict[str, np.ndarray] = {}
    if count is not None:
        out[CLASS_COUNT] = count.values(before)[rows].double().cpu().numpy()
        out[CLASS_COUNT_NEXT] = count.values(after)[rows].double().cpu().numpy()
    expected_class = expected_class_next_of(internal) if expected else None
    if expected_class is not None:
        law = expected_class(before, x, dt)[rows].float().cpu().numpy()
        for b in range(law.shape[1]):
            out[expected_class_column(b)] = law[:, b]
    return out


@dataclass(frozen=True)
class _Jumps:
    """The perturbation of :func:`_rows`: how cells jump, how often (per cell and second),
    and ``guide()``, the guided jumps of a sequential design at a step, if any (None: the
    perturbation as drawn)."""

    perturbation: Perturbation
    rate: float
    guide: Callable[[], GuidedJump | None] | None = None


def _rows(  # noqa: C901  # one step's rows: each optional column is a branch
    simulator: Simulator,
    n_cells: int,
    start: Sequence[float] | torch.Tensor,
    options: CollectOptions,
    max_steps: int,
    jumps: _Jumps | None = None,
    clock: bool = True,
    initialize: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> Iterator[dict[str, np.ndarray]]:
    """Yield recorded rows step by step (see the module docstring), at most ``max_steps``
    steps; ``jumps``: the perturbation (None: none; ``options.max_time`` is the caller's).
    ``clock``: keep the switch clocks (every step one call; without it and without jumps the
    unrecorded steps run in one call and the rows have no ``phi_age``). ``initialize``: the
    cells' first phi (:meth:`Simulator.initial_state`)."""
    record_every, blackout, expected = options.record_every, options.blackout, options.expected
    # every switch kept where the rows are thinned (one in record_every windows otherwise)
    keep_switches = options.keep_switches and record_every > 1
    perturbation = None if jumps is None else jumps.perturbation
    perturb_rate = 0.0 if jumps is None else jumps.rate
    guide = None if jumps is None else jumps.guide
    internal = simulator.decision.internal  # type: ignore[attr-defined]
    expected_phi = expected_phi_next_of(internal) if expected else None
    if expected and expected_phi is None:
        raise ConfigError(
            f"{type(internal).__name__} gives no expected labels (no expected_phi_next); "
            "collect them with collect.expected_labels=false"
        )
    names = (*internal.input_names, *feature_names_of(internal))
    # K lumps: each window's class before and after
    classes = lump_classes_of(internal) if options.classes_of_state else None
    # and, where the classes are bins of a count, the count: the bins are applied when read
    count = class_count_of(internal) if classes is not None else None
    device, dt = simulator.device, simulator.dt
    state = simulator.initial_state(n_cells, start, options.equilibration_time, initialize)
    jump_probability = perturb_rate * dt
    # steps since each cell's last jump (-1: never), on the device: no per-step host sync
    since = torch.full((n_cells,), -1, dtype=torch.int64, device=device)
    # switch clocks (steps since phi last changed, or since recording began while censored)
    age = torch.zeros(n_cells, dtype=torch.float32, device=device)
    censored = torch.ones(n_cells, dtype=torch.bool, device=device)
    k = 0

    def next_chunk() -> dict[str, np.ndarray] | None:
        """One step (or a run of unrecorded ones); its recorded rows, if any."""
        nonlocal k, since, age, censored
        if perturbation is None and not clock:  # unrecorded steps in one call
            skip = min(record_every - 1 - k % record_every, max_steps - k)
            if skip:
                simulator.advance(state, skip)
                k += skip
                return None
        k += 1
        if perturbation is not None:
            jump = torch.rand(n_cells, device=device) < jump_probability
            guided = guide() if guide is not None else None
            if guided is not None:
                state.body = guided.apply(state.body, jump, state.phi, state.step * dt)
            else:
                state.body = perturbation.apply(state.body, jump)
            since = torch.where(jump, 0, torch.where(since >= 0, since + 1, since))
        recorded = k % record_every == 0
        age_before, censored_before = age, censored
        # the internal state before the window, where a column reads it (a switch off the
        # thinned steps is known only after the step: kept for every step then)
        wanted = recorded or keep_switches
        before = (
            _internal_state(simulator) if wanted and (expected or classes is not None) else None
        )
        x, phi_before, phi_after = _one_step(simulator, state)
        age, censored = tick(age, phi_before, phi_after), censored & (phi_after == phi_before)
        if not wanted:
            return None
        # every cell on thinned steps (and, keeping switches, every switch on the others),
        # except those still inside the blackout after a jump
        settled = (since < 0) | (since >= blackout)
        changed = phi_after != phi_before
        class_before = class_after = after = None
        if classes is not None:
            assert before is not None  # kept on every step where a row may be recorded
            after = simulator.decision.fused_state()
            class_before, class_after = classes.classify(before), classes.classify(after)
            if keep_switches:  # a class move kept as a switch is (the module docstring)
                changed = changed | (class_after != class_before)
        rows = (settled if recorded else settled & changed).nonzero().squeeze(1)
        if rows.numel() == 0:
            return None
        values = features_of(internal, x[rows], names).float().cpu().numpy()
        # the rows are on the host already, so the check is free; NaN/inf must not reach
        # the table
        if not np.isfinite(values).all():
            raise NumericalError(
                f"NaN/inf in the recorded inputs at t={(k - 1) * dt:g} s; the field returned "
                f"NaN/inf values or the dynamics diverged"
            )
        chunk = {n: values[:, i] for i, n in enumerate(names)}
        chunk.update(
            phi=phi_before[rows].to(torch.int8).cpu().numpy(),
            phi_next=phi_after[rows].to(torch.int8).cpu().numpy(),
            cell=rows.cpu().numpy(),
            t=np.full(rows.numel(), (k - 1) * dt),
            since_jump=since[rows].cpu().numpy(),
        )
        if keep_switches:  # a held window stands for record_every, a change for itself
            chunk[WINDOWS] = torch.where(changed[rows], 1.0, float(record_every)).cpu().numpy()
        if clock:
            chunk[AGE] = (age_before[rows] * dt).cpu().numpy()
            chunk[CENSORED] = censored_before[rows].cpu().numpy()
        if expected_phi is not None:
            assert before is not None  # kept on recorded steps
            p_next = expected_phi(before, x, dt)[rows]
            chunk[EXPECTED] = p_next.float().cpu().numpy()
        if classes is not None:
            assert before is not None and after is not None
            assert class_before is not None and class_after is not None
            chunk[CLASS] = class_before[rows].to(torch.int16).cpu().numpy()
            chunk[CLASS_NEXT] = class_after[rows].to(torch.int16).cpu().numpy()
            chunk.update(_count_columns(internal, count, before, after, x, rows, expected, dt))
        return chunk

    while k < max_steps:
        # each step in inference mode (cheaper per op than no_grad), none held across the
        # yield: the caller runs outside it while this generator waits (e.g. a sequential
        # design fits psi between rounds), and a generator closed later (garbage collected)
        # must not switch the mode of whatever runs then
        with torch.inference_mode():
            chunk = next_chunk()
        if chunk is not None:
            yield chunk


def recorded_share(perturb_rate: float, blackout_time: float) -> float:
    """The share of a collected cell's windows outside the blackout once jumps are steady:
    the chance that the last jump (one per ``1 / perturb_rate`` s on average, a Bernoulli
    draw each window) came ``blackout_time`` s or more ago, ``exp(-rate x blackout)``. What
    the stages' cost estimates divide a collection's rows by (a cell never yet perturbed is
    recorded too, so the start's windows are a little cheaper).

    Example:
        >>> round(recorded_share(0.1, 1.0), 3), round(recorded_share(0.025, 20.0), 3)
        (0.905, 0.607)
    """
    return math.exp(-max(perturb_rate, 0.0) * max(blackout_time, 0.0))


def _internal_state(simulator: Simulator) -> tuple[Tensor, ...]:
    """A copy of the full decision layer's internal state (a kernel writes it in place)."""
    return tuple(t.clone() for t in simulator.decision.fused_state())


def can_expect(internal: object) -> bool:
    """Whether an internal model gives the expected label of a window
    (``expected_phi_next(state, x, dt)``, an optional capability of
    :class:`~surrogate.models.base.InternalModel`)."""
    return expected_phi_next_of(internal) is not None


def _one_step(simulator: Simulator, state: PopulationState) -> tuple[Tensor, Tensor, Tensor]:
    """One step of every cell by :meth:`Simulator.advance` (the model's per-cell kernel where
    the simulator has one, else the torch step): (its inputs x, phi before, phi after). The
    kernel writes the state in place, so phi before is a copy."""
    phi_before = state.phi.clone()
    simulator.advance(state, 1)
    assert state.inputs is not None  # set by every step
    return state.inputs, phi_before, state.phi


def _table(chunks: list[dict[str, np.ndarray]]) -> pd.DataFrame:
    table = pd.DataFrame({k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]})
    table["phi"] = table["phi"].astype(np.int8)
    table["phi_next"] = table["phi_next"].astype(np.int8)
    return table


class TransitionCollector:
    """The perturbed full-model population of :func:`collect_transitions`, kept between calls:
    each :meth:`take` goes on simulating it, so a sequential design collects in rounds (and may
    set :attr:`guide` between them) without equilibrating a new population each time.

    Args: as :func:`collect_transitions`.

    Example:
        >>> collector = TransitionCollector(simulator, perturbation, 500, 0.1)  # doctest: +SKIP
        >>> first = collector.take(10_000)          # 10,000 rows per origin state
        >>> collector.guide = GuidedJump(...)        # later jumps guided
        >>> more = collector.take(10_000)            # the same cells, simulated on
    """

    def __init__(
        self,
        simulator: Simulator,
        perturbation: Perturbation,
        n_cells: int,
        perturb_rate: float,
        options: CollectOptions | None = None,
        progress: bool = True,
    ) -> None:
        options = options or CollectOptions()
        self.max_time = float(options.max_time)
        self.progress = progress
        self.n_cells, self.dt = int(n_cells), float(simulator.dt)
        self.lump_names = tuple(simulator.decision.internal.lump_names)  # type: ignore[attr-defined]
        #: guided jumps of a sequential design (None: the perturbation as drawn)
        self.guide: GuidedJump | None = None
        self.kept = np.zeros(2, dtype=np.int64)
        self.record_every = int(options.record_every)
        start = perturbation.start(n_cells, simulator.device)
        max_steps = math.ceil(self.max_time / simulator.dt)
        self._rows = _rows(simulator, n_cells, start, options, max_steps,
                           _Jumps(perturbation, perturb_rate, lambda: self.guide))  # fmt: skip

    def take(self, n_per_state: int) -> pd.DataFrame:
        """Simulate on until ``n_per_state`` more transitions from each origin state are
        recorded; return a random (seeded) subsample of exactly ``n_per_state`` per origin (the
        rest of the last steps' rows is dropped; keeping switches, rows counted as
        :func:`origin_rows` counts them, ``n_per_state`` in expectation)."""
        chunks: list[dict[str, np.ndarray]] = []
        counts = np.zeros(2, dtype=np.float64)
        bar = tqdm(total=2 * n_per_state, desc="collect transitions", disable=not self.progress,
                   mininterval=1.0)  # fmt: skip
        first = now = None
        for chunk in self._rows:
            chunks.append(chunk)
            new = origin_rows(chunk, self.record_every)
            bar.update(int(np.minimum(counts + new, n_per_state).sum()
                           - np.minimum(counts, n_per_state).sum()))  # fmt: skip
            counts += new
            now = float(chunk["t"][0]) + self.dt  # the end of the window just recorded
            first = now - self.dt if first is None else first
            if (counts >= n_per_state).all():
                break
            if now - first >= EARLY_CHECK_SHARE * self.max_time:
                projected = counts * (self.max_time - first) / (now - first)
                if (projected * SHORT < n_per_state).any():
                    bar.close()
                    never = bool((projected * FAR_SHORT < n_per_state).any())
                    raise ConfigError(self._shortfall(counts, n_per_state, first, now, early=True,
                                                      never=never))  # fmt: skip
        bar.close()
        if not (counts >= n_per_state).all():
            raise ConfigError(self._shortfall(counts, n_per_state, first, now, early=False))
        table = _table(chunks)
        # a random (seeded) subsample per origin spreads the kept rows over the whole take;
        # keeping switches, the same share of each origin's switches and held rows (each row's
        # windows then stand as they were, n_per_state x record_every per origin within one)
        gen = np.random.default_rng(int(torch.randint(0, 2**31 - 1, (1,)).item()))
        phi = table["phi"].to_numpy()
        windows = table[WINDOWS].to_numpy() if WINDOWS in table else np.ones(len(table))
        keep = np.concatenate([
            np.sort(gen.choice(rows, round(rows.size * min(1.0, n_per_state / counts[p])),
                               replace=False))
            for p in (0, 1) for w in np.unique(windows[phi == p])
            if (rows := np.flatnonzero((phi == p) & (windows == w))).size
        ])  # fmt: skip
        self.kept += n_per_state
        return table.iloc[np.sort(keep)].reset_index(drop=True)

    def _shortfall(
        self,
        counts: np.ndarray,
        wanted: int,
        first: float | None,
        now: float | None,
        early: bool,
        never: bool = True,
    ) -> str:
        """Why collect stops short of ``wanted`` rows per origin (``counts`` so far, recorded
        from ``first`` to ``now`` s), with the occupancy measured and the fix that fits: a lump
        almost never (or always) true (``never``, of an ``early`` stop) is changed or inspected;
        a slow but steady rate is given time or cells."""
        counts = np.rint(counts).astype(np.int64)  # thinned rows (fractional keeping switches)
        lumps, total = self.lump_names, int(counts.sum())
        start = first if first is not None else 0.0
        span = max((now if now is not None else start) - start, self.dt)
        short = int(np.argmin(counts))
        name, share = lumps[short], counts[short] / max(total, 1)
        # rows of each origin grow in proportion to the recorded time and to the cells
        projected = counts[short] * (self.max_time - start) / span
        measured = (f"phi = {lumps[1]} in {counts[1] / max(total, 1):.3%} of the {total} "
                    f"windows recorded in {span:g} s (rows from {lumps[0]}, {lumps[1]}: "
                    f"{counts.tolist()}; {wanted} wanted from each)")  # fmt: skip
        if counts[short] == 0:
            need = f"{name} was never recorded"
        else:
            time = start + wanted * span / counts[short]
            need = (f"at the measured rate {name} would reach them at collect.max_time ~ "
                    f"{time:.3g} s, or with collect.n_cells ~ "
                    f"{self.n_cells * wanted / projected:.3g}")  # fmt: skip
        inspect = ("`python3 scripts/inspect_model.py` with the same model settings measures "
                   "phi's occupancy across the inputs the fields give")  # fmt: skip
        if early and not never:
            return (f"collect stopped early: {measured}. By collect.max_time={self.max_time:g} s "
                    f"{name} would give ~{projected:.3g} rows, less than 1/{SHORT:g} of those "
                    f"wanted: {need} (or lower collect.n_per_state). {inspect}")  # fmt: skip
        if early:
            return (f"collect stopped early: {measured}. By collect.max_time={self.max_time:g} s "
                    f"{name} would give ~{projected:.3g} rows, less than 1/{FAR_SHORT:g} of those "
                    f"wanted ({need}): the lump is (almost) never {name} where cells live. "
                    f"Change the lump (model.lump) so that both lumps are common; "
                    f"{inspect}")  # fmt: skip
        rare = (f" {name} is rare ({share:.3%} of the windows): if it is so where cells live, "
                f"change the lump (model.lump) instead;" if share < RARE else "")  # fmt: skip
        return (f"collect reached collect.max_time={self.max_time:g} s short of the rows wanted: "
                f"{measured}; {need} (or lower collect.n_per_state).{rare} {inspect}")  # fmt: skip


def collect_transitions(
    simulator: Simulator,
    perturbation: Perturbation,
    n_cells: int,
    n_per_state: int,
    perturb_rate: float,
    options: CollectOptions | None = None,
    progress: bool = True,
) -> pd.DataFrame:
    """Simulate the full model with perturbations until ``n_per_state`` transitions from each
    origin state are recorded; return a random (seeded) subsample of exactly ``n_per_state``
    per origin state.

    Args:
        simulator: a simulator whose decision layer is the full internal model.
        perturbation: the body's perturbation (where cells start, how they jump).
        n_cells: cells simulated in parallel.
        n_per_state: transitions kept per origin state.
        perturb_rate: jumps per cell and second.
        options: the thinning, equilibration, time limit, blackout and expected labels
            (:class:`CollectOptions`; default its defaults).
        progress: show a progress bar.
    """
    collector = TransitionCollector(simulator, perturbation, n_cells, perturb_rate, options,
                                    progress)  # fmt: skip
    return collector.take(n_per_state)


def record_stationary_bins(
    simulator: Simulator,
    perturbation: Perturbation,
    n_cells: int,
    lags: Sequence[float],
    names: Sequence[str],
    class_bins: Sequence[int],
    chunk: float = 10.0,
) -> pd.DataFrame:
    """Burned-in full-model cells where collect starts them, held at their inputs: each cell's
    inputs ``names`` and the bin of its class (``class_bins``) now and after each lag (the
    stationary sample of :mod:`surrogate.gp.class_relaxation`).

    Args:
        simulator: a simulator whose decision layer is the full internal model.
        perturbation: the body's perturbation (its ``start`` places the cells).
        n_cells: cells.
        lags: increasing lags (s) after which the bins are read again, inputs held fixed.
        names: the abstraction's inputs to record.
        class_bins: the bin of each class.
        chunk: seconds per call of the internal model's ``advance`` (bounds one call's work).

    Returns:
        ``n_cells`` rows: the ``names`` columns and ``bin_0 .. bin_L``.
    """
    internal = simulator.model.internal
    declared = lump_classes_of(internal)
    if declared is None:
        raise ConfigError(f"{type(internal).__name__} declares no classes")
    if any(b <= a for a, b in zip([0.0, *lags], lags, strict=False)):
        raise ConfigError(f"the lags must be positive and increase, got {list(lags)}")
    device = simulator.device
    to_bin = torch.tensor(list(class_bins), dtype=torch.int64, device=device)
    state = simulator.initial_state(n_cells, perturbation.start(n_cells, device))
    x = state.inputs
    assert x is not None
    internal_state = simulator.decision.fused_state()
    out = {n: features_of(internal, x, names)[:, i].float().cpu().numpy()
           for i, n in enumerate(names)}  # fmt: skip
    out["bin_0"] = to_bin[declared.classify(internal_state).to(device)].cpu().numpy()
    now = 0.0
    for j, lag in enumerate(lags, start=1):
        while now < lag - 1e-9:
            step = min(chunk, lag - now)
            internal_state = internal.advance(internal_state, x, step)
            now += step
        out[f"bin_{j}"] = to_bin[declared.classify(internal_state).to(device)].cpu().numpy()
    return pd.DataFrame(out)


def record_occupancy(  # noqa: PLR0913  # a run's design, each optional with its default
    simulator: Simulator,
    n_cells: int,
    t_end: float,
    start: Sequence[float] | torch.Tensor,
    record_every: int = 5,
    equilibration_time: float = 10.0,
    clock: bool = False,
    classes_of_state: bool = True,
    initialize: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> pd.DataFrame:
    """Where an unperturbed population lives: every ``record_every``-th step of every cell
    from ``start`` for ``t_end`` seconds (the weights of the abstraction's diagnostic);
    ``clock``: with the switch clocks (``phi_age``; every step one call);
    ``classes_of_state``: with the classes the model declares (False: an abstraction's
    population, whose decision does not carry the internal model's state); ``initialize``:
    the cells' first phi (:meth:`Simulator.initial_state`)."""
    steps = max(1, round(t_end / simulator.dt))
    options = CollectOptions(record_every=record_every, equilibration_time=equilibration_time,
                             classes_of_state=classes_of_state)  # fmt: skip
    chunks = list(_rows(simulator, n_cells, start, options, steps, clock=clock,
                        initialize=initialize))  # fmt: skip
    if not chunks:
        raise ConfigError(
            f"gp.diagnostic: t_end={t_end:g} s records no step (record_every={record_every})"
        )
    return _table(chunks)
