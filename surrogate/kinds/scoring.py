"""The measured choice of a chain kind (issue 52): each fitted kind scored on held-out
full-model phi sequences, and the best one picked.

* :func:`score_kind`: a kind's held-out score: the log-likelihood per window of the observed phi
  sequences given their inputs, over every window or after each one's first switch
  (:meth:`ChainKind.window_log_likelihoods
  <surrogate.kinds.base.ChainKind.window_log_likelihoods>`, :func:`scored_windows`), and its
  layer driven by the same input traces: the two-sample KS and the mean's relative difference of the simulated segment
  durations per lump against the observed ones (:func:`duration_scores`).
* :func:`choose`: the best kind by log-likelihood per window among those whose simulated
  durations hold (:func:`holds_durations`: every lump's mean within a tolerance; where none
  does, the one closest to holding them, :func:`duration_miss`); a candidate within the
  standard error of that best (of the paired difference over held-out cells) is a tie, which
  goes to the simplest (:attr:`ChainKind.complexity
  <surrogate.kinds.base.ChainKind.complexity>`).

These take plain values (layers, tensors, scores); the train stage fits the candidates and
records the held-out run (:mod:`surrogate.stages.choice`), read as sequences by
:func:`~surrogate.simulate.sequences.phi_sequences`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.evaluate.statistics import compare_samples
from surrogate.gp.diagnostics import cluster_se
from surrogate.kinds.base import ChainKind
from surrogate.simulate.decision import DecisionLayer


def segment_durations(phi: np.ndarray, dt: float) -> dict[int, np.ndarray]:
    """The complete phi segments' durations (s) per lump: those that start and end inside the
    sequences (the first and last of each cell are censored and dropped).

    Args:
        phi: ``n x (T + 1)`` phi (0/1).
        dt: the window (s).
    """
    lengths, lump, _ = _segments(phi, dt)
    return {p: lengths[lump == bool(p)] for p in (0, 1)}


def _segments(phi: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every complete segment of ``phi`` (``n x (T + 1)``): its duration (s), its lump (bool)
    and its cell."""
    phi = np.asarray(phi) > 0.5
    cell, t = np.nonzero(phi[:, 1:] != phi[:, :-1])  # a change in window t; by cell, then t
    same = cell[1:] == cell[:-1]
    lengths = (t[1:] - t[:-1])[same] * dt
    lump = phi[cell[:-1][same], t[:-1][same] + 1]
    return lengths, lump, cell[:-1][same]


#: the share of a lump's segments a clock's cap should reach past (the inspector's hazard cap
#: reads the same 90th percentile)
HORIZON_QUANTILE = 0.9
#: complete segments a lump needs for its horizon to be read
HORIZON_MIN_SEGMENTS = 50
#: a candidate whose held-out log-likelihood is below the best's by at most this many nats over
#: all the held-out windows ties it, whatever the paired SE: a likelihood ratio under e is no
#: evidence either way (Jeffreys' "barely worth mentioning" is under 3.2), while two nearly
#: identical fits (the two-state chain and one hidden phase per lump) differ per cell so
#: steadily that their SE shrinks with the gap (memoryless telegraph: 6.6e-9 a window, 0.007
#: nats over 1e6 windows, beyond 1 SE; a clock 5.7e-7 lower tied within its larger SE)
TIE_NATS = 1.0

#: ``gp.choice.likelihood_from``: the windows after each held-out cell's first switch, or
#: every window (the default)
FIRST_SWITCH, FROM_START = "first_switch", "start"
LIKELIHOOD_FROM = (FIRST_SWITCH, FROM_START)


def memory_horizon(phi: np.ndarray, dt: float) -> float | None:
    """How far back phi's switching remembers, read from observed sequences: the largest over
    the lumps of the :data:`HORIZON_QUANTILE` quantile of the segments' durations (s).

    Only complete segments are seen, and a segment of length L lies whole inside a sequence of
    length T in proportion to T - L, so each is weighted by 1 / (T - L) to undo the window's
    bias towards short ones. None where a lump has fewer than :data:`HORIZON_MIN_SEGMENTS`
    complete segments (phi too slow for these sequences to tell).

    Args:
        phi: ``n x (T + 1)`` phi (0/1).
        dt: the window (s).

    Example:
        >>> phi = np.tile(np.r_[np.zeros(10), np.ones(30)], 60)[None, :]  # 0.5 s and 1.5 s
        >>> memory_horizon(phi, 0.05)
        1.5
    """
    length = (np.asarray(phi).shape[1] - 1) * dt
    horizon = 0.0
    for durations in segment_durations(phi, dt).values():
        if durations.size < HORIZON_MIN_SEGMENTS:
            return None
        order = np.sort(durations)
        weights = 1.0 / np.maximum(length - order, dt)
        cumulative = np.cumsum(weights) / weights.sum()
        at = min(int(np.searchsorted(cumulative, HORIZON_QUANTILE)), order.size - 1)
        horizon = max(horizon, float(order[at]))
    return horizon


@dataclass(frozen=True)
class DurationScore:
    """One lump's simulated segment durations against the observed: the two-sample KS, its 5 %
    critical value, and the means' relative difference with its standard error (NaN where a
    side has fewer than two segments)."""

    ks: float
    ks_critical_05: float
    mean_rel_diff: float
    mean_rel_se: float
    n_observed: int
    n_simulated: int


def duration_scores(
    observed: np.ndarray, simulated: np.ndarray, dt: float, lump_names: Sequence[str]
) -> dict[str, DurationScore]:
    """Per lump, the simulated segment durations against the observed ones
    (:func:`segment_durations` of each; KS by
    :func:`~surrogate.evaluate.statistics.compare_samples`; the means' standard error with
    each sequence, not each segment, an independent unit).

    Args:
        observed: ``n x (T + 1)`` phi sequences.
        simulated: ``m x (T + 1)`` phi sequences (any number of them: e.g. several draws
            of each observed cell).
        dt: the window (s).
        lump_names: the two lumps' names (keys of the result).
    """
    obs, sim = _segments(observed, dt), _segments(simulated, dt)
    out = {}
    for p, name in enumerate(lump_names):
        on_a, on_b = obs[1] == bool(p), sim[1] == bool(p)
        a, b = obs[0][on_a], sim[0][on_b]
        if a.size < 2 or b.size < 2:
            out[name] = DurationScore(math.nan, math.nan, math.nan, math.nan, a.size, b.size)
            continue
        ks = compare_samples(b, a, name=f"{name} durations")
        mean = float(a.mean())
        # cells as clusters: a cell's segments share its inputs; counted one by one the SE
        # was about half the true one where cells differ (tests/kinds/test_scoring.py)
        se = math.hypot(cluster_se(a, obs[2][on_a]), cluster_se(b, sim[2][on_b])) / mean
        out[name] = DurationScore(ks["ks"], ks["ks_critical_05"], float(b.mean()) / mean - 1.0,
                                  se, int(a.size), int(b.size))  # fmt: skip
    return out


#: the spread's block, in mean segment durations (both lumps' observed segments together)
SPREAD_SEGMENTS = 5.0
#: blocks per held-out cell the spread's block length leaves at least
SPREAD_MIN_BLOCKS = 5


@dataclass(frozen=True)
class SpreadScore:
    """How far a kind's simulated occupancy fluctuates from the observed at a few seconds: the
    variance of each cell's share of time in lump 1 over blocks of ``block_s`` s (simulated
    over observed, minus 1) and its standard error."""

    block_s: float
    rel_diff: float
    rel_se: float


def occupancy_spread(observed: np.ndarray, simulated: np.ndarray, dt: float) -> SpreadScore:
    """The variance of the share of time in lump 1 over blocks of several sojourns
    (:data:`SPREAD_SEGMENTS` observed mean segment durations, at most a
    :data:`SPREAD_MIN_BLOCKS`-th of a cell's windows), simulated against observed: what a body
    that integrates phi (a walker's distance) weighs, and what a kind that draws successive
    sojourns independently misses where the network's state carries across a switch
    (CERENA's gene-expression network: every clock +3.6 to +13 % at 2.5-10 s, the hidden
    phases +0.5 to +2.7 %; docs/choice.md). Each side's blocks are centred on its own mean
    occupancy; the standard error is the delta method's over the cells (independent).

    Args:
        observed: ``n x (T + 1)`` phi sequences (0/1).
        simulated: ``(r n) x (T + 1)``: ``r >= 1`` draws of the same cells, draw after draw
            (each cell's simulated deviations are its draws' mean).
        dt: the window (s).

    Returns:
        NaN ``rel_diff`` and ``rel_se`` where there are no complete segments to size the
        block, fewer than two blocks per cell, or no variance observed.
    """
    nan = SpreadScore(math.nan, math.nan, math.nan)
    segments = np.concatenate(list(segment_durations(observed, dt).values()))
    n, windows = np.asarray(observed).shape
    if segments.size == 0 or n < 2:
        return nan
    block = max(1, min(round(SPREAD_SEGMENTS * float(segments.mean()) / dt),
                       windows // SPREAD_MIN_BLOCKS))  # fmt: skip
    k = windows // block
    if k < 2:
        return nan

    def per_cell(phi: np.ndarray) -> np.ndarray:
        shares = np.asarray(phi, dtype=np.float64)[:, : k * block].reshape(n, k, block).mean(2)
        return ((shares - shares.mean()) ** 2).sum(1)  # each cell's squared deviations

    simulated = np.asarray(simulated)
    check_draws(simulated, (n, windows), "simulated phi", f"{n} observed cells")
    obs = per_cell(observed)
    sim = np.stack([per_cell(d) for d in np.split(simulated, simulated.shape[0] // n)]).mean(0)
    total_obs, total_sim = float(obs.sum()), float(sim.sum())
    if not total_obs > 0:
        return SpreadScore(block * dt, math.nan, math.nan)
    ratio = total_sim / total_obs
    se = ratio * math.sqrt(n * obs.var(ddof=1) / total_obs**2
                           + n * sim.var(ddof=1) / max(total_sim, 1e-300) ** 2)  # fmt: skip
    return SpreadScore(block * dt, ratio - 1.0, se)


def simulate_sequences(
    kind: ChainKind, layer: DecisionLayer, inputs: Tensor, phi0: Tensor, dt: float, seed: int
) -> Tensor:
    """The kind's ``layer`` driven by the recorded input traces ``inputs`` (``n x T x d``) from
    the observed first phi ``phi0`` (``(n,)``): simulated phi ``n x (T + 1)`` (float32).
    ``seed`` seeds torch's generator (the layers draw from it)."""
    torch.manual_seed(seed)
    kind.start_sequences(layer, inputs[:, 0], phi0)
    out = torch.empty(inputs.shape[0], inputs.shape[1] + 1)
    phi = phi0.bool()
    out[:, 0] = phi0
    for t in range(inputs.shape[1]):  # over windows: cells in the batch
        phi = layer.step(phi, inputs[:, t], dt).bool()
        out[:, t + 1] = phi.float()
    return out


@dataclass(frozen=True)
class KindScore:
    """A candidate's held-out score: its ``name`` (the recipe, e.g. ``clock max_age=2``), its
    :attr:`~surrogate.kinds.base.ChainKind.complexity`, the log-likelihood per window (mean
    over held-out cells of each cell's mean) and per-cell values (for paired differences), the
    durations' scores per lump, and the fit's and the score's seconds."""

    name: str
    complexity: int
    log_likelihood: float
    per_cell: tuple[float, ...] = field(repr=False)
    durations: dict[str, DurationScore]
    fit_seconds: float = math.nan
    score_seconds: float = math.nan
    #: the occupancy's spread over blocks of a few sojourns (:func:`occupancy_spread`)
    spread: SpreadScore | None = None
    #: the durations and the spread of the kind's own population, closed loop (its cells'
    #: inputs follow their own phi), against the held-out cells' (None: not scored)
    closed_durations: dict[str, DurationScore] | None = None
    closed_spread: SpreadScore | None = None
    #: the windows each held-out cell's mean is over (0: unknown, no :data:`TIE_NATS` floor)
    windows_per_cell: int = 0
    #: the scored fit against its own rows (:func:`surrogate.gp.own_rows.largest_miss`)
    own_rows: dict[str, Any] | None = None
    #: the log-likelihood per window over the windows after each cell's first switch, where a
    #: clock's age is known (:data:`FIRST_SWITCH`), beside the ranking's whatever
    #: ``likelihood_from`` is: how much of a lead is the censored first sojourn's
    known_age_log_likelihood: float = math.nan
    #: the log-likelihood per window over the same windows with each kind's state before the
    #: record marginalised over its stationary law (:meth:`ChainKind.
    #: marginal_window_log_likelihoods`: a clock's unknown first age; the others' as ranked):
    #: what the choice's added clocks follow
    marginal_log_likelihood: float = math.nan

    def row(self) -> dict[str, Any]:
        """The score as a flat row for the table (no per-cell values)."""
        out: dict[str, Any] = {"kind": self.name, "complexity": self.complexity,
                               "log_likelihood_per_window": self.log_likelihood,
                               "known_age_log_likelihood": self.known_age_log_likelihood,
                               "marginal_log_likelihood": self.marginal_log_likelihood}  # fmt: skip
        for lump, d in self.durations.items():
            for key, value in asdict(d).items():
                out[f"{lump}_{key}"] = value
        if self.spread is not None:
            out.update({f"spread_{k}": v for k, v in asdict(self.spread).items()})
        for lump, d in (self.closed_durations or {}).items():
            out.update({f"closed_{lump}_{k}": v for k, v in asdict(d).items()})
        if self.closed_spread is not None:
            out.update({f"closed_spread_{k}": v for k, v in asdict(self.closed_spread).items()})
        if self.own_rows is not None:  # the scored fit's largest miss of its own rows
            out.update({"own_rows_ratio": self.own_rows["ratio"], "own_rows_z": self.own_rows["z"],
                        "own_rows_off": self.own_rows["off"]})  # fmt: skip
        out["fit_seconds"], out["score_seconds"] = self.fit_seconds, self.score_seconds
        return out


def score_kind(  # noqa: PLR0913  # the scoring's entry: seed and groups keyword-only
    name: str,
    kind: ChainKind,
    layer: DecisionLayer,
    inputs: Tensor,
    phi: Tensor,
    dt: float,
    lump_names: Sequence[str],
    *,
    seed: int = 0,
    groups: Sequence[int] = (),
    likelihood_from: str = FROM_START,
    draws: int = 1,
    closed: Tensor | None = None,
) -> KindScore:
    """A fitted kind's held-out score (:class:`KindScore`).

    Args:
        name: the candidate's name in the table.
        kind: the kind (its likelihood and start, :meth:`ChainKind.window_log_likelihoods`).
        layer: its decision layer of the fit (:meth:`ChainKind.decision_layer`).
        inputs: ``n x T x d`` the held-out cells' recorded inputs.
        phi: ``n x (T + 1)`` their phi.
        dt: the window (s).
        lump_names: the two lumps' names.
        seed: the simulated durations' seed.
        groups: the cells' groups in order, by their sizes (summing to ``n``; the held-out
            cells of each field, ``gp.choice.fields``): each lump's durations are scored per
            group and the group farthest off (the largest relative difference of the means)
            stands for the lump, so a kind off in one field is not averaged away by another
            (the dimerisation's phases: -0.2 % over two fields, +4.3 % on L2 alone).
            Empty or one group: all cells together.
        likelihood_from: the windows the likelihood sums (:func:`scored_windows`):
            :data:`FROM_START` (every window) or :data:`FIRST_SWITCH` (those after each
            cell's first switch, where a clock's age is known); the latter's is kept too,
            ``known_age_log_likelihood``.
        draws: the simulated sequences per held-out cell its durations and spread are
            scored from (more draws, less of the simulation's own noise in the screens).
        closed: ``(r n) x (T + 1)`` phi of the kind's own population, closed loop (its
            cells moved by their own phi, as the held-out cells were run: ``r`` draws of the
            same count, fields and times, draw after draw), scored against the held-out phi
            as the durations and spread are (``closed_durations``, ``closed_spread``); None:
            not scored.

    Raises:
        ValueError: the shapes disagree, ``draws`` is not a positive integer, a phi is not 0
            or 1, an input is not finite, or the groups do not add up to the cells.
    """
    if isinstance(draws, bool) or not isinstance(draws, int) or draws < 1:
        raise ValueError(f"draws must be an integer >= 1, got {draws!r}")
    if groups and (sum(groups) != inputs.shape[0] or any(g < 1 for g in groups)):
        raise ValueError(f"groups {list(groups)} must be positive cell counts adding up to the "
                         f"{inputs.shape[0]} held-out cells")  # fmt: skip
    if inputs.ndim != 3 or phi.shape != (inputs.shape[0], inputs.shape[1] + 1):
        raise ValueError(f"inputs must be n x T x d and phi n x (T + 1), got "
                         f"{tuple(inputs.shape)} and {tuple(phi.shape)}")  # fmt: skip
    bad = ~((phi == 0) | (phi == 1))
    if bool(bad.any()):
        # a likelihood masks states by phi's lump: another value would score as neither lump
        raise ValueError(f"phi must be 0 or 1 (each window's lump), got {phi[bad][:3].tolist()} "
                         f"in {int(bad.sum())} place(s): pass (phi > 0) for a 0/1 phi")  # fmt: skip
    if not bool(torch.isfinite(inputs).all()):
        # a table reads NaN as its first node, a classifier returns NaN: either scores garbage
        cells = torch.nonzero(~torch.isfinite(inputs).all(-1).all(-1)).flatten()
        raise ValueError(f"inputs must be finite: held-out cell(s) {cells[:5].tolist()} have NaN "
                         f"or infinite inputs; drop them before scoring")  # fmt: skip
    with torch.no_grad():
        terms = kind.window_log_likelihoods(layer, inputs, phi, dt)
        ranked = scored_windows(phi, likelihood_from)
        ll, windows = _per_window(terms, ranked)
        known, _ = _per_window(terms, scored_windows(phi, FIRST_SWITCH))
        # a kind whose likelihood starts from its stationary law gives its ranked terms back
        marginal, _ = _per_window(
            kind.marginal_window_log_likelihoods(layer, inputs, phi, dt, ranked=terms), ranked
        )
        # draw after draw: the batch holds every draw of every cell
        simulated = simulate_sequences(kind, layer, inputs.repeat(draws, 1, 1),
                                       phi[:, 0].repeat(draws), dt, seed)  # fmt: skip
    per_cell = ll.cpu().numpy()
    observed, sims = phi.cpu().numpy(), simulated.cpu().numpy()
    durations = grouped_durations(observed, sims, dt, lump_names, groups)
    closed_durations, closed_spread = None, None
    if closed is not None:
        own = closed.cpu().numpy()
        check_draws(own, observed.shape, "the closed-loop phi", "held-out cells")
        closed_durations = grouped_durations(observed, own, dt, lump_names, groups)
        closed_spread = occupancy_spread(observed, own, dt)
    return KindScore(name, kind.complexity, float(per_cell.mean()),
                     tuple(float(v) for v in per_cell), durations,
                     spread=occupancy_spread(observed, sims, dt),
                     closed_durations=closed_durations, closed_spread=closed_spread,
                     windows_per_cell=round(windows),
                     known_age_log_likelihood=float(known.mean()),
                     marginal_log_likelihood=float(marginal.mean()))  # fmt: skip


def check_draws(simulated: np.ndarray, observed: tuple[int, ...], what: str, cells: str) -> None:
    """Refuse ``simulated`` phi that are not ``r >= 1`` draws of the ``observed`` (``n x
    (T + 1)``) cells, ``(r n) x (T + 1)``, naming it ``what`` and the cells ``cells``."""
    n, windows = observed
    if simulated.ndim != 2 or simulated.shape[1] != windows or simulated.shape[0] % n:
        raise ValueError(f"{what} must be draws of the {cells}, (r * {n}) x {windows}, got "
                         f"{simulated.shape}")  # fmt: skip


def grouped_durations(
    observed: np.ndarray,
    simulated: np.ndarray,
    dt: float,
    lump_names: Sequence[str],
    groups: Sequence[int] = (),
) -> dict[str, DurationScore]:
    """:func:`duration_scores` per group of cells, each lump's the group farthest off.

    Args:
        observed: ``n x (T + 1)`` phi of the held-out cells.
        simulated: ``(r n) x (T + 1)``: ``r >= 1`` simulated draws of the same cells, draw
            after draw.
        dt: the window (s).
        lump_names: the two lumps' names.
        groups: the cells' groups in order, by their sizes (summing to ``n``); empty or one
            group: all cells together.
    """
    if len(groups) < 2:
        return duration_scores(observed, simulated, dt, lump_names)
    by_draw = simulated.reshape(-1, *observed.shape)
    edges = np.cumsum([0, *groups])
    parts = [duration_scores(observed[a:b], by_draw[:, a:b].reshape(-1, observed.shape[1]), dt,
                             lump_names)
             for a, b in itertools.pairwise(edges)]  # fmt: skip
    return {lump: max((part[lump] for part in parts), key=_farthest) for lump in lump_names}


def scored_windows(phi: Tensor, likelihood_from: str = FIRST_SWITCH) -> Tensor:
    """The windows a held-out likelihood sums (``n x T`` bool for ``phi`` ``n x (T + 1)``).

    :data:`FIRST_SWITCH`: those after each cell's first switch. Before it, what the cell
    has been doing since its last switch is unknown: a clock starts settled at its cap, a
    hidden-state chain from its stationary law, and the windows of that first, censored
    sojourn score how a kind guesses an unknown past, not the memory it simulates. On
    Vilar's oscillator (1,000 held-out cells x 50 s, segments of 6-17 s) those 15 % of the
    windows made every doubling of the clock's cap past its segments score higher
    (22 -> 44 -> 88 s: -0.00841, -0.00713, -0.00643 per window over them) while the windows
    after the first switch scored the three alike (-0.01395, -0.01396, -0.01396): the choice
    took a log clock at 176 s whose recipe fit took 11 min (docs/choice.md, session 35). A
    cell that never switches contributes no window (to every kind alike). Opt-in
    (``gp.choice.likelihood_from=first_switch``).
    :data:`FROM_START`: every window (the default: ranked after the first switch, the
    dimerisation's clock at 2 s tied its hidden phases and was chosen, 20 of 24 at scale where
    the phases pass 24; Tyson's added clocks judged after it alone, its clock at 10 s was
    chosen, 23 of 24 where the log clock at 20 s passed 24; docs/choice.md).

    Example:
        >>> scored_windows(torch.tensor([[0, 0, 1, 1, 0]])).tolist()
        [[False, False, True, True]]
    """
    if likelihood_from not in LIKELIHOOD_FROM:
        raise ValueError(f"likelihood_from must be one of {list(LIKELIHOOD_FROM)}, got "
                         f"{likelihood_from!r}")  # fmt: skip
    steps = phi.shape[1] - 1
    if likelihood_from == FROM_START:
        return torch.ones(phi.shape[0], steps, dtype=torch.bool, device=phi.device)
    changed = phi[:, 1:] != phi[:, :-1]
    first = torch.where(changed.any(1), changed.to(torch.int64).argmax(1),
                        torch.full((phi.shape[0],), steps, device=phi.device))  # fmt: skip
    return torch.arange(steps, device=phi.device)[None, :] > first[:, None]


def _per_window(terms: Tensor, scored: Tensor) -> tuple[Tensor, float]:
    """Each cell's log-likelihood over its ``scored`` windows, over the mean number of scored
    windows a cell (a constant denominator: the cells' mean is the log-likelihood per scored
    window, and the per-cell values stay paired across kinds), and that mean."""
    windows = max(float(scored.sum()) / terms.shape[0], 1.0)
    return (terms * scored.to(terms.device)).sum(1).cpu() / windows, windows


def _farthest(score: DurationScore) -> float:
    """How far a group's simulated mean is off (a group too small to compare, NaN, farthest)."""
    return math.inf if math.isnan(score.mean_rel_diff) else abs(score.mean_rel_diff)


#: how the name of a clock on a log axis begins (``clock log max_age=20``)
LOG_CLOCK = "clock log "
_CLOCK = "clock "
_CAP = "max_age="


def clock_name(age: float, log_axis: bool = False) -> str:
    """The candidate name of the switch clock at cap ``age`` (s), in seconds or on a log axis
    (``gp.clock_knee``): the one spelling of a clock's name in the choice's table
    (:func:`candidate_cap` reads it back).

    Example:
        >>> clock_name(20.0, log_axis=True)
        'clock log max_age=20'
    """
    return f"{LOG_CLOCK if log_axis else _CLOCK}{_CAP}{age:g}"


def candidate_cap(name: str) -> float | None:
    """The switch clock's cap (s) of a candidate named by :func:`clock_name`; None for
    another candidate.

    Example:
        >>> candidate_cap("clock log max_age=20"), candidate_cap("phases")
        (20.0, None)
    """
    for head in (_CLOCK + _CAP, LOG_CLOCK + _CAP):
        if name.startswith(head):
            return float(name.removeprefix(head))
    return None


@dataclass(frozen=True)
class Choice:
    """The measured choice: the chosen candidate's name, why, and every candidate's row with
    its difference from the best and that difference's standard error."""

    chosen: str
    reason: str
    table: list[dict[str, Any]]


#: the standard errors a candidate's mean duration may be off by, where more than the
#: tolerance (the spread's rule): a miss the held-out cells cannot tell from none is no
#: evidence of a bias. Where segments are long and few per cell the means' SE is as large as
#: the tolerance (the immigration-death network: 2.5 % against 3 %) and the tolerance alone
#: turned away the likelihood's best, a K-lumps chain whose fitted sojourns are within 2 % of
#: the exact ones, on the draw; its own population's mean moves from draw to draw by several
#: points against 1,000 held-out cells (CERENA's network: up to 5, docs/choice.md)
MEANS_SE = 2.0


def holds_spread(score: KindScore, tolerance: float | None) -> bool:
    """Whether ``score``'s occupancy spread (:func:`occupancy_spread`; its own population's,
    closed loop, where it was run: what a walker's moves see) holds: within ``tolerance`` of the
    observed, or within two standard errors of it (a difference the held-out cells cannot tell
    from none); True where no tolerance is asked or nothing was measured."""
    spread = score.closed_spread if score.closed_spread is not None else score.spread
    if tolerance is None or spread is None or not math.isfinite(spread.rel_diff):
        return True
    return spread_within(spread.rel_diff, spread.rel_se, tolerance)


def spread_within(rel_diff: float, rel_se: float, tolerance: float) -> bool:
    """The spread's rule: a relative difference within ``tolerance`` or two standard errors."""
    return abs(rel_diff) <= max(tolerance, 2.0 * rel_se)


def holds_durations(score: KindScore, tolerance: float) -> bool:
    """Whether ``score``'s simulated durations hold on every lump: the means' relative
    difference within ``tolerance`` or :data:`MEANS_SE` standard errors (:func:`means_within`;
    a lump with too few segments to compare, NaN, does not hold), open loop and, where it was
    run, in its own population (closed loop). Not the KS: at 1,000
    held-out cells its critical value (~0.008) sees shape differences of a fraction of a
    percent that the population checks do not (E. coli's K lumps, at the noise floor at 1e5
    cells, miss it by 0.003 on tumbles), and the likelihood already weighs the durations'
    shape."""
    closed = score.closed_durations or {}
    return (
        bool(score.durations)
        and all(means_within(d, tolerance) for d in score.durations.values())
        and all(means_within(d, tolerance) for d in closed.values())
    )


def screen_se(scores: Sequence[KindScore]) -> float:
    """The standard error the duration screen reads its candidates' means with: per
    candidate the largest over its lumps (finite ones), the median over the candidates (one
    odd candidate, a two-state chain far off, does not set it); NaN where none has one."""
    per_kind = [max(ses) for s in scores
                if (ses := [d.mean_rel_se for d in (s.durations or {}).values()
                            if math.isfinite(d.mean_rel_se)])]  # fmt: skip
    return float(np.median(per_kind)) if per_kind else math.nan


def grown_cells(n_cells: int, se: float, tolerance: float, max_cells: int) -> int:
    """The held-out cells that bring the screen's standard error ``se`` (at ``n_cells``) to
    half the ``tolerance``, where it is over (the SE falls as one over the root of the
    cells), at most ``max_cells``; ``n_cells`` where it is not over, or is not finite. At
    half the tolerance 2 SE is the tolerance: the screen (:func:`means_within`) reads it.

    Example:
        >>> grown_cells(1000, 0.025, 0.03, 4000)
        2778
        >>> grown_cells(1000, 0.012, 0.03, 4000)
        1000
    """
    target = tolerance / 2.0
    if not (math.isfinite(se) and se > target):
        return n_cells
    return min(max_cells, math.ceil(n_cells * (se / target) ** 2))


def means_within(duration: DurationScore, tolerance: float) -> bool:
    """The means' rule: a relative difference within ``tolerance`` or :data:`MEANS_SE`
    standard errors (NaN compares false; an SE that is NaN leaves the tolerance alone)."""
    se = duration.mean_rel_se if math.isfinite(duration.mean_rel_se) else 0.0
    return abs(duration.mean_rel_diff) <= max(tolerance, MEANS_SE * se)


def farthest_lump(mean_rel_diffs: Mapping[str, float]) -> tuple[str, float] | None:
    """The lump whose simulated mean duration is farthest from the observed one, and its
    relative difference, among the lumps with a finite one; None where none has.

    Example:
        >>> farthest_lump({"low": 0.012, "high": -0.034})
        ('high', -0.034)
    """
    finite = {k: v for k, v in mean_rel_diffs.items() if math.isfinite(v)}
    if not finite:
        return None
    lump = max(finite, key=lambda k: abs(finite[k]))
    return lump, finite[lump]


def duration_miss(score: KindScore) -> float:
    """How far ``score``'s simulated durations are from holding: the largest relative
    difference of the means over its lumps (:func:`farthest_lump`; inf where a lump has too
    few segments to compare, or there are none), open loop and in its own population where it
    was run."""
    misses = []
    for loop in (score.durations, score.closed_durations):
        if loop is None:
            continue
        diffs = {k: d.mean_rel_diff for k, d in loop.items()}
        far = farthest_lump(diffs)
        if far is None or not all(math.isfinite(v) for v in diffs.values()):
            return math.inf
        misses.append(abs(far[1]))
    return max(misses)


def choose(
    scores: Sequence[KindScore],
    tie_se: float = 1.0,
    duration_tolerance: float | None = None,
    spread_tolerance: float | None = None,
) -> Choice:
    """The best candidate by held-out log-likelihood per window among those that hold their
    durations (:func:`holds_durations`, where ``duration_tolerance`` is given), their clocks
    narrowed to the marginal score's best (:func:`one_clock`); one within
    ``tie_se`` standard errors of that best (the SE of the paired per-cell difference), or
    within :data:`TIE_NATS` of it over all the held-out windows, ties it, and a tie goes to the
    simplest (smallest complexity, then the higher likelihood).

    Where none holds them, the candidate closest to holding them (the smallest
    :func:`duration_miss`; the likelihood breaks an exact tie): the check at scale asks for
    the means, and the likelihood's best may be the farthest off (the dimerisation's held-out
    cells on L2, docs/choice.md: K lumps +6.8 %, the clock at 5 s 3.4 %). Where no candidate
    has durations to compare (too few segments), the likelihood alone.

    Args:
        scores: the candidates' scores, on the same held-out cells.
        tie_se: how many standard errors make a tie (> 0).
        duration_tolerance: the means' relative difference a candidate must hold on every lump
            (with its KS) to be chosen; None: the likelihood alone.
        spread_tolerance: with ``duration_tolerance``, the occupancy spread's relative
            difference a candidate holding its durations must also hold (:func:`holds_spread`)
            where one of them does; None: not asked.

    Raises:
        ConfigError: no candidate, a non-positive ``tie_se`` or two candidates of one name.
        ValueError: the scores are not over the same held-out cells, or one is NaN.
    """
    if not scores:
        raise ConfigError("gp.choice: no candidate kind to choose from")
    if isinstance(tie_se, bool) or not isinstance(tie_se, int | float) or not tie_se > 0:
        raise ConfigError(f"gp.choice.tie_se must be a number of standard errors > 0, "
                          f"got {tie_se!r}")  # fmt: skip
    names = [s.name for s in scores]
    if len(set(names)) != len(names):
        raise ConfigError(f"gp.choice: candidates named twice in {names}")
    if len({len(s.per_cell) for s in scores}) != 1:
        raise ValueError("the candidates were scored on different held-out cells")
    broken = [s.name for s in scores if math.isnan(s.log_likelihood)]
    if broken:
        # max() over NaN keys returns whichever came first: the choice would be arbitrary
        raise ValueError(f"candidate(s) {broken} have a NaN held-out log-likelihood: their "
                         f"layers give NaN laws on the held-out inputs; leave them out of the "
                         f"choice or refit them")  # fmt: skip
    holding = {s.name: duration_tolerance is not None and holds_durations(s, duration_tolerance)
               for s in scores}  # fmt: skip
    spread_held = {s.name: holding[s.name] and holds_spread(s, spread_tolerance) for s in scores}
    # the spread screens the candidates that hold their durations where one of them holds it
    # too; where none does, it is not asked (the durations' rule alone)
    spread_asked = spread_tolerance is not None and any(spread_held.values())
    if spread_asked:
        holding = spread_held
    pool = [s for s in scores if holding[s.name]]
    closest = min(scores, key=lambda s: (duration_miss(s), -s.log_likelihood))
    # none holds: the closest to holding (where one has durations to compare), else all
    nearest = (duration_tolerance is not None and not pool
               and math.isfinite(duration_miss(closest)))  # fmt: skip
    pool = [closest] if nearest else pool or list(scores)
    pool, aside = one_clock(pool)
    best = max(pool, key=lambda s: s.log_likelihood)
    top = max(scores, key=lambda s: s.log_likelihood)
    rows, tied = [], []
    for s in scores:
        gap, se = _paired(s, top)
        pool_gap, pool_se = _paired(s, best)
        tie = s in pool and (
            s is best
            or (math.isfinite(pool_se) and -pool_gap <= tie_se * pool_se)
            or 0 < -pool_gap * _windows(s) <= TIE_NATS
        )
        if tie:
            tied.append(s)
        rows.append({**s.row(), "diff_from_best": gap, "diff_se": se, "tied_with_best": tie,
                     "holds_durations": holding[s.name]})  # fmt: skip
    chosen = min(tied, key=lambda s: (s.complexity, -s.log_likelihood))
    if chosen is best:
        others = [r for r in rows if r["kind"] != best.name and r["kind"] in
                  {p.name for p in pool}]  # fmt: skip
        reason = f"{best.name} has the highest held-out log-likelihood per window " + (
            f"({best.log_likelihood:.5f})"
        )
        if others:
            runner = max(others, key=lambda r: r["diff_from_best"])
            reason += f"; the next, {runner['kind']}, is {_gap(runner)} lower"
    else:
        gap, se = _paired(chosen, best)
        within = (f"within {tie_se:g} SE" if -gap <= tie_se * se else
                  f"{-gap * _windows(chosen):.2g} nats over the {_windows(chosen):,} held-out "
                  f"windows (at most {TIE_NATS:g}) from")  # fmt: skip
        reason = (f"{chosen.name} is {within} the best, {best.name} "
                  f"({_gap({'diff_from_best': gap, 'diff_se': se})} lower), and simpler "
                  f"(complexity {chosen.complexity} < {best.complexity})")  # fmt: skip
    reason += _clocks_aside(pool, aside)
    if duration_tolerance is not None:
        left = [s.name for s in scores if not holding[s.name]]
        rule = f"every lump's mean within {duration_tolerance:.0%} or {MEANS_SE:g} SE" + (
            f", the occupancy's spread within {spread_tolerance:.0%} or 2 SE" if spread_asked
            else "")  # fmt: skip
        if nearest:
            reason = (f"none holds its durations ({rule}): {best.name} is the closest to "
                      f"holding them, its farthest lump {_miss(best)}" + (
                          "" if top is best else
                          f" (the likelihood's best, {top.name}: {_miss(top)})"))  # fmt: skip
        elif len(pool) < len(scores):
            gap, se = _paired(top, best)
            reason += (f"; chosen among the {len(pool)} that hold their durations ({rule}), not "
                       f"{left}" + ("" if top is best else
                                    f" (the likelihood's best alone, {top.name}, is {gap:.2e} "
                                    f"higher, SE {se:.1e})"))  # fmt: skip
        elif left:
            reason += (f" (none holds its durations, {rule}, nor has durations to compare: "
                       f"chosen on the likelihood alone)")  # fmt: skip
        else:
            reason += f"; every candidate holds its durations ({rule})"
    return Choice(chosen.name, reason, rows)


def one_clock(pool: Sequence[KindScore]) -> tuple[list[KindScore], list[str]]:
    """``pool`` with one switch clock left among its clocks: the best by the marginal score
    (``marginal_log_likelihood``, the clock's unknown first age marginalised), and the names
    of those set aside; ``pool`` as it is where it holds fewer than two clocks or one has no
    marginal score. Ranked, each clock reads a held-out cell's unknown first sojourn settled
    at its own cap, a guess that differs from clock to clock with no memory behind it: Tyson's
    log clock at 10 s led the marginal score (-0.07888 per window against the clock at 10
    s's -0.07946) and trailed ranked (-0.08218 against -0.08030), and passed 24 of 24 checks
    at scale where the clock at 10 s passed 23 (docs/choice.md). The clock left meets the
    other kinds on the ranked score, as before: marginalised against the dimerisation's
    phases its clock at 2 s ties them and fails at scale."""
    clocks = [s for s in pool if candidate_cap(s.name) is not None]
    if len(clocks) < 2 or not all(math.isfinite(c.marginal_log_likelihood) for c in clocks):
        return list(pool), []
    keep = max(clocks, key=lambda c: c.marginal_log_likelihood)
    return ([s for s in pool if s is keep or s not in clocks],
            [c.name for c in clocks if c is not keep])  # fmt: skip


def _clocks_aside(pool: Sequence[KindScore], aside: Sequence[str]) -> str:
    """The reason's words for the clocks :func:`one_clock` set aside (empty where none)."""
    if not aside:
        return ""
    clock = next(s for s in pool if candidate_cap(s.name) is not None)
    return (f"; of the clocks, {clock.name} alone, the best by the marginal score "
            f"({clock.marginal_log_likelihood:.5f}; not {list(aside)}: a clock's ranked score "
            f"reads its unknown first age settled at its own cap)")  # fmt: skip


def _windows(score: KindScore) -> int:
    """The held-out windows ``score`` is over, all cells together (0 where unknown)."""
    return len(score.per_cell) * score.windows_per_cell


def _paired(score: KindScore, ref: KindScore) -> tuple[float, float]:
    """The mean per-cell difference of ``score`` from ``ref`` and its standard error."""
    diff = np.asarray(score.per_cell) - np.asarray(ref.per_cell)
    se = float(diff.std(ddof=1) / math.sqrt(diff.size)) if diff.size > 1 else math.nan
    return float(diff.mean()), se


def _miss(score: KindScore) -> str:
    """:func:`duration_miss` in words: ``6.8% off`` (or ``too few segments to compare``)."""
    miss = duration_miss(score)
    return f"{miss:.1%} off" if math.isfinite(miss) else "too few segments to compare"


def _gap(row: dict[str, Any]) -> str:
    """A row's shortfall from the best in words: ``1.2e-03 (SE 1.0e-04, 12.0 SE)``."""
    gap, se = -row["diff_from_best"], row["diff_se"]
    ratio = f", {gap / se:.1f} SE" if se > 0 else ""
    return f"{gap:.2e} (SE {se:.1e}{ratio})"
