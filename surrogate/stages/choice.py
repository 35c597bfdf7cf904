"""The measured choice of the chain kind (issue 52; ``gp=auto``, the default: docs/choice.md).

Fits the candidate kinds on one collection (the two-state chain, the switch clock at a few
``gp.choice.max_ages``, K lumps where the model declares classes, and every registered kind that
declares itself a :attr:`~surrogate.kinds.base.ChainKind.candidate` with its recipe), records a
held-out full-model run at the training inputs (every window of ``gp.choice.n_cells`` cells for
``gp.choice.t_end`` s, another seed than the collection's; in the fields ``gp.choice.fields``
names, the cells split among them, where it is set), scores each kind on it
(:func:`~surrogate.kinds.scoring.score_kind`: log-likelihood per window of the observed phi
sequences, simulated durations' KS and means) and picks the best that holds its durations
(:func:`~surrogate.kinds.scoring.choose`). The record (``choice.json``, ``scores.csv``, the
manifest) goes into ``data/choice/...`` and beside the chosen fit's files; from then on
``gp=auto`` on this collection *is* the chosen candidate
(:mod:`surrogate.stages.settings.choice`).

:func:`settle` is what the entries that train call: it checks every setting with the pending
choices resolved by the rule, makes the choices, and builds the settings again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import math
import time
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.reduction import ForkingPickler
from pathlib import Path
from typing import Any, TypeVar

import pandas as pd
import torch

from surrogate.config import build_field, field_config, seed_everything, to_dict
from surrogate.errors import NumericalError
from surrogate.gp.own_rows import largest_miss, summary
from surrogate.io import read_json, write_csv, write_json, write_manifest
from surrogate.kinds.base import LayerRequest
from surrogate.kinds.scoring import (
    FROM_START,
    Choice,
    KindScore,
    choose,
    grown_cells,
    memory_horizon,
    score_kind,
    screen_se,
)
from surrogate.processes import spawned_pool
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.sequences import phi_sequences
from surrogate.simulate.transitions import record_occupancy
from surrogate.stages.artefacts import FIT_METRICS
from surrogate.stages.collect import collect
from surrogate.stages.settings import CollectSettings, TrainSettings
from surrogate.stages.settings.choice import (
    CHOICE,
    FIT_THREADS,
    SCORES,
    PendingChoice,
    collecting_pending,
    largest_clock,
    stored_choice,
)
from surrogate.threads import one_thread

log = logging.getLogger(__name__)

#: a candidate's simulated durations' seed is the job's plus its name's hash modulo this
CANDIDATE_SEEDS = 100_003
#: the held-out run's seed is the job's plus this (its cells are not the collection's)
HELDOUT_SEED_OFFSET = 7_919
#: the cells a grown held-out run adds are drawn on the first run's seed plus this
GROWN_SEED_OFFSET = 104_729
#: fits a candidate's train settings (loads its transitions, fits or reuses), returns its fit
#: directory: the train stage's, passed in (this module sits below it)
Fitter = Callable[[TrainSettings], Path]
S = TypeVar("S")


def settle(validate: Callable[[Mapping[str, Any]], S], cfg: Mapping[str, Any], fitter: Fitter) -> S:
    """``validate(cfg)`` with every measured choice it needs made: the settings are checked
    first with the pending choices resolved by the rule (a bad setting anywhere is refused
    before any work), then each choice is made (:func:`make_choice`) and the settings built
    again, now resolving ``gp=auto`` to each chosen candidate. Built once where no choice is
    pending."""
    with collecting_pending() as plans:
        settings = validate(cfg)
    if not plans:
        return settings
    made: set[Path] = set()
    for plan in plans:
        if plan.directory not in made and stored_choice(plan) is None:
            make_choice(plan, fitter, cfg)
        made.add(plan.directory)
    return validate(cfg)


def make_choice(plan: PendingChoice, fitter: Fitter, config: Mapping[str, Any]) -> Path:
    """Fit and score ``plan``'s candidates, choose, write the record; return its directory."""
    first = next(iter(plan.candidates.values()))
    workers = plan.settings.worker_count(len(plan.candidates), first.job.device)
    with candidate_pool(workers, fitter, plan.candidates) as pool:  # starting while we collect
        return _make_choice(plan, fitter, config, pool)


def _make_choice(
    plan: PendingChoice, fitter: Fitter, config: Mapping[str, Any], pool: ProcessPoolExecutor | None
) -> Path:
    t0 = time.perf_counter()
    first = next(iter(plan.candidates.values()))
    if isinstance(first.source, CollectSettings):
        collect(first.source)  # one collection for every candidate (reused where it exists)
    log.info("gp=auto: choosing the chain by measurement among %s (docs/choice.md; "
             "gp.choice.by=rule or a named kind skips it)", list(plan.candidates))  # fmt: skip
    for name, candidate in plan.candidates.items():
        if candidate.kind.relaxation:  # the one candidate whose fit simulates the full model
            log.info("choice: %s fits on a stationary sample of %d full-model cells burned in "
                     "and held %g s at their inputs (the auto-regulatory network's 2,400: 16-32 "
                     "min of one core); gp.choice.kinds without relaxation leaves it out", name,
                     candidate.relaxation_cells, candidate.relaxation_lags[-1])  # fmt: skip
    heldout, heldout_seconds = _heldout_run(plan)
    fits, failed, scored = fit_candidates(plan.candidates, fitter, heldout=heldout, pool=pool,
                                          ahead=plan.ahead() if pool is not None else None)  # fmt: skip
    made = _Fitted(plan, fitter, heldout, failed, scored, fits)
    for name in list(failed):  # L-BFGS diverged: the recipe's own optimiser
        made.retry(name)
    if not made.fits:
        raise NumericalError(f"gp=auto: every candidate's fit failed: {failed}")
    made.extend()
    heldout, heldout_seconds = made.grow(pool, heldout, heldout_seconds)
    choice = choose(
        made.scores,
        plan.settings.tie_se,
        plan.settings.duration_tolerance,
        plan.settings.spread_tolerance,
    )
    # each row names its candidate's overrides: a name (``clock log max_age=20``) cannot say
    # its knee and bins, and a remedy that names a candidate must run as scored
    table = [{**row, "overrides": " ".join(made.trained(str(row["kind"])).gp_overrides())}
             for row in choice.table]  # fmt: skip
    overrides = next(r["overrides"] for r in table if r["kind"] == choice.chosen)
    _log(choice, overrides)
    out = plan.directory
    # what gp=auto trains: the chosen as scored, or refitted with its recipe's own optimiser
    record = {"chosen": choice.chosen, "gp": made.finals[choice.chosen], "reason": choice.reason,
              "overrides": overrides, "failed": made.failed,
              "fit": str(made.fits[choice.chosen][0]), "scores": table,
              "heldout": {"cells": int(heldout.inputs.shape[0]),
                          "windows": int(heldout.inputs.shape[1]),
                          "seconds": heldout_seconds,
                          **({"fields": list(plan.settings.fields or ()),
                              "cells_per_field": list(heldout.groups)}
                             if heldout.groups else {})}}  # fmt: skip
    write_csv(out / SCORES, pd.DataFrame(table))
    write_json(made.fits[choice.chosen][0] / CHOICE, record)  # beside the chosen fit's files
    write_manifest(out, stage="choice", config=to_dict(config), seed=first.seed,
                   settings={"choice": plan.settings.identity(),
                             "candidates": {n: t.fit_identity() for n, t in made.trains.items()}},
                   chosen=choice.chosen, reason=choice.reason, fit=record["fit"],
                   scores=table, wall_time_s=time.perf_counter() - t0)  # fmt: skip
    write_json(out / CHOICE, record)  # last: its presence is what settles gp=auto
    log.info("choice: record in %s", out)
    return out


def _heldout_run(
    plan: PendingChoice, base: HeldOut | None = None, n_cells: int | None = None
) -> tuple[HeldOut, float]:
    """The full model's held-out run the candidates are scored on (``gp.choice.n_cells`` x
    ``gp.choice.t_end``, every window recorded, another seed than the collection's) and the
    seconds it took; with ``base``, that run grown to ``n_cells``: its cells kept and the rest
    drawn on a seed of their own, each field's after its own (a grown run is the first one and
    more, so what it read is not drawn again)."""
    first = next(iter(plan.candidates.values()))
    setup, settings = first.setup, plan.settings
    n_cells = settings.n_cells if n_cells is None else n_cells
    start = time.perf_counter()
    seed_everything(first.seed + HELDOUT_SEED_OFFSET + (0 if base is None else GROWN_SEED_OFFSET))
    # the training field, or gp.choice.fields: the cells split evenly, the first takes the rest
    fields = heldout_fields(setup, settings.fields)
    cells = [n_cells // len(fields)] * len(fields)
    cells[0] += n_cells - sum(cells)
    had = [0] * len(fields) if base is None else list(base.groups or (base.inputs.shape[0],))
    cells = [max(n, old) for n, old in zip(cells, had, strict=True)]
    inputs, phi = [], []
    offsets = [0, *itertools.accumulate(had)]
    for j, (field, n, old) in enumerate(zip(fields, cells, had, strict=True)):
        if base is not None:  # each field's first cells, then its added ones
            inputs.append(base.inputs[offsets[j] : offsets[j + 1]])
            phi.append(base.phi[offsets[j] : offsets[j + 1]])
        if n <= old:
            continue
        simulator = Simulator(setup.model, FullDecision(setup.model.internal), field, setup.dt,
                              first.job.device, backend="auto")  # fmt: skip
        run = record_occupancy(simulator, n - old, settings.t_end,
                               torch.tensor(first.diagnostic["start"]), record_every=1,
                               equilibration_time=settings.equilibration_time)  # fmt: skip
        part = phi_sequences(run, setup.model.internal.input_names)
        inputs.append(part[0].to(torch.float32))  # the layers read float32, as simulate gives
        phi.append(part[1])
    seconds = time.perf_counter() - start
    held = HeldOut(torch.cat(inputs), torch.cat(phi), first.seed,
                   () if settings.fields is None else tuple(cells), settings.likelihood_from,
                   settings.draws,
                   ClosedLoop(tuple(cells), settings.fields, settings.t_end,
                              settings.equilibration_time, settings.draws)
                   if settings.closed_loop else None)  # fmt: skip
    log.info("choice: held-out full-model run, %d cells x %d windows%s%s, in %.1f s",
             held.inputs.shape[0], held.inputs.shape[1],
             "" if settings.fields is None else f" in fields {list(settings.fields)}",
             "" if base is None else f" ({base.inputs.shape[0]} of them the first run's)",
             seconds)  # fmt: skip
    return held, seconds


class _Fitted:
    """The candidates fitted and scored so far, by name: their train settings (``trains``),
    gp groups as scored (``groups``) and as gp=auto trains them once chosen (``finals``),
    fits, scores, and those that failed, with why; it retries a failed fit with its recipe
    and adds the candidates the choice adds (a longer clock, a log clock)."""

    def __init__(
        self,
        plan: PendingChoice,
        fitter: Fitter,
        heldout: HeldOut,
        failed: dict[str, str],
        scored: Mapping[str, KindScore],
        fits: dict[str, tuple[Path, float]],
    ) -> None:
        self.plan, self.fitter, self.heldout, self.failed, self.fits = (
            plan, fitter, heldout, failed, fits)  # fmt: skip
        self.trains = {n: t for n, t in plan.candidates.items() if n in fits}
        self.groups = {n: g for n, g in plan.groups.items() if n in fits}
        self.finals = {n: plan.finals.get(n, g) for n, g in self.groups.items()}
        self.scores = list(scored.values())

    def _keep(self, name: str, made: tuple[Any, dict[str, Any], tuple[Path, float], KindScore],
              final: dict[str, Any]) -> None:  # fmt: skip
        self.trains[name], self.groups[name], self.fits[name], score = made
        self.finals[name] = final
        self.scores.append(score)

    def grow(
        self, pool: ProcessPoolExecutor | None, heldout: HeldOut, seconds: float
    ) -> tuple[HeldOut, float]:
        """Where the screen's standard error (:func:`~surrogate.kinds.scoring.screen_se`) is
        over half the duration tolerance, a held-out run of the cells that bring it there (at
        most ``gp.choice.max_cells``, :func:`~surrogate.kinds.scoring.grown_cells`) and every
        candidate scored on it again, its fit reused; the held-out run and its seconds (with
        the first run's)."""
        settings = self.plan.settings
        se = screen_se(self.scores)
        n_cells = grown_cells(int(heldout.inputs.shape[0]), se, settings.duration_tolerance,
                              settings.max_cells)  # fmt: skip
        if n_cells <= heldout.inputs.shape[0]:
            return heldout, seconds
        log.info("choice: the held-out means' SE, %.1f %%, is over half the duration tolerance "
                 "(%g %%), where the screen would read 2 SE: the held-out run grown to %d cells "
                 "(gp.choice.max_cells=%d) and every candidate scored again on it", 100 * se,
                 100 * settings.duration_tolerance, n_cells, settings.max_cells)  # fmt: skip
        grown, more = _heldout_run(self.plan, heldout, n_cells)
        _, failed, scored = fit_candidates(self.trains, self.fitter, heldout=grown, pool=pool)
        for name, why in failed.items():  # a fit reused scores as before; a new failure drops
            self.failed[name] = why
            for table in (self.trains, self.groups, self.finals, self.fits):
                table.pop(name, None)
        self.heldout, self.scores = grown, list(scored.values())
        return grown, seconds + more

    def retry(self, name: str) -> None:
        """Fit failed candidate ``name`` with its recipe's optimiser and score it: kept where
        that fit holds, left among the failed otherwise."""
        final = self.plan.finals.get(name)
        retried = _with_recipe(self.fitter, self.plan, name, final, self.heldout.task(name))
        if retried is not None:
            assert final is not None  # _with_recipe fits none without it
            self._keep(name, retried, final)
            del self.failed[name]

    def best(self) -> str:
        """The name of the candidate with the highest held-out log-likelihood so far with
        each kind's state before the record marginalised (``marginal_log_likelihood``, over
        the windows ``gp.choice.likelihood_from`` says): what the added clocks follow. Read
        settled at the cap, a held-out cell's unknown first sojourn made each doubling of
        Vilar's cap the best by 10-40 SE with no memory behind it (docs/choice.md)."""
        return max(self.scores, key=_marginal).name

    def extend(self) -> None:
        """Add the clocks the held-out run and the scores ask for: one at the run's memory
        horizon where it reaches past twice the largest cap
        (:meth:`~surrogate.stages.settings.choice.PendingChoice.reach_clock`), a clock at twice
        the cap while the best is the clock at the largest (``gp.choice.extend`` times), then
        one on a log axis where the best is a clock in seconds; each fitted and scored here."""
        dt = next(iter(self.plan.candidates.values())).setup.dt
        reached = 0
        horizon = memory_horizon(self.heldout.phi.cpu().numpy(), dt)
        if (reach := self.plan.reach_clock(horizon, self.groups)) is not None:
            name, gp = reach
            log.info("choice: the held-out cells' segments reach %.3g s (90 %% of them, the "
                     "longest lump's), past twice the largest cap; adding %s", horizon, name)  # fmt: skip
            base = largest_clock(self.groups)  # what reach_clock widened
            assert base is not None
            reached = int(self._add(name, gp, {**self.finals[base], **_clock_axis(gp)}))
        while (longer := self.plan.longer_clock(best := self.best(), self.groups,
                                                reached)) is not None:  # fmt: skip
            # the likelihood's best is the clock at the largest cap: its memory may reach past it
            name, gp = longer
            log.info("choice: the best is the clock at its largest cap; adding %s", name)
            if not self._add(name, gp, {**self.finals[best], **_clock_axis(gp)}):
                break  # named among the failed; no longer clock after it
        best = self.best()
        # the best is a clock in seconds: one on a log axis reaches twice as far
        if (logged := self.plan.log_clock(best, self.groups, dt)) is not None:
            name, gp = logged
            log.info("choice: the best is a clock; adding %s (knee %g s, %d bins)", name,
                     gp["clock_knee"], gp["clock_bins"])  # fmt: skip
            axis = _clock_axis(gp, ("max_age", "clock_knee", "clock_bins"))
            self._add(name, gp, {**self.finals[best], **axis})

    def _add(self, name: str, gp: dict[str, Any], final: dict[str, Any]) -> bool:
        """Fit and score added candidate ``name`` (gp group ``gp``; ``final`` as gp=auto trains
        it); whether it was kept (else it is named among the failed)."""
        added = _fit_added(self.fitter, self.plan, name, gp, final, self.heldout)
        if isinstance(added, str):
            self.failed[name] = added
            return False
        self._keep(name, added, final)
        return True

    def trained(self, name: str) -> Any:
        """What gp=auto trains were candidate ``name`` chosen: its recipe's settings with
        ``finals[name]``, else (no recipe to make them) the settings it was scored with."""
        make = self.plan.make
        return make(self.finals[name]) if make is not None else self.trains[name]


def _marginal(score: KindScore) -> float:
    """A score's ``marginal_log_likelihood``, or its ranked one where it has none."""
    m = score.marginal_log_likelihood
    return m if math.isfinite(m) else score.log_likelihood


@dataclasses.dataclass(frozen=True)
class HeldOut:
    """The held-out run the candidates are scored on (``n x T`` inputs, ``n x (T + 1)`` phi)
    and the seed its simulated durations start from (candidate ``name``'s:
    :func:`candidate_seed`)."""

    inputs: torch.Tensor
    phi: torch.Tensor
    seed: int
    #: the cells of each field in order (``gp.choice.fields``; empty: one field)
    groups: tuple[int, ...] = ()
    #: the windows the likelihood ranks by (``gp.choice.likelihood_from``)
    likelihood_from: str = FROM_START
    #: simulated sequences per held-out cell (``gp.choice.draws``)
    draws: int = 1
    #: how the held-out run was made, for each candidate's own population (closed loop)
    closed: ClosedLoop | None = None

    def task(self, name: str) -> Task:
        """What scoring candidate ``name`` needs."""
        return (name, self.inputs, self.phi, candidate_seed(self.seed, name), self.groups,
                self.likelihood_from, self.draws, self.closed)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ClosedLoop:
    """The held-out run's design, which each candidate's own population repeats closed loop,
    ``draws`` times over: its cells per field (``fields`` by name, None: the training field),
    the seconds recorded after ``equilibration_time`` s, from the diagnostic's start."""

    cells: tuple[int, ...]
    fields: tuple[str, ...] | None
    t_end: float
    equilibration_time: float
    draws: int = 1

    def run(self, tr: Any, layer: Any, seed: int, phi0: torch.Tensor) -> torch.Tensor:
        """``(draws n) x (T + 1)`` phi of ``tr``'s model with decision ``layer`` (its cells
        moved by their own phi), draw after draw, each draw's cells field after field as the
        held-out run's, seeded with ``seed``. Each cell starts from the first phi of a
        held-out cell (``phi0``, ``(n,)``), the layer at its own start there
        (:meth:`~surrogate.kinds.base.ChainKind.start_sequences`), not from the internal
        model's stationary law: that burn-in cost Tyson's oscillator 22 s a candidate, the
        rest of its population under 3 s."""
        setup = tr.setup
        fields = heldout_fields(setup, self.fields)
        seed_everything(seed)
        parts, offset = [], 0
        for field, n in zip(fields, self.cells, strict=True):  # every draw of a field at once
            first = phi0[offset : offset + n].float().repeat(self.draws)
            offset += n

            def initialize(x: torch.Tensor, first: torch.Tensor = first) -> torch.Tensor:
                tr.kind.start_sequences(layer, x, first)
                return first.bool()

            simulator = Simulator(setup.model, layer, field, setup.dt, "cpu", backend="auto")
            run = record_occupancy(simulator, self.draws * n, self.t_end,
                                   torch.tensor(tr.diagnostic["start"]), record_every=1,
                                   equilibration_time=self.equilibration_time,
                                   classes_of_state=False, initialize=initialize)  # fmt: skip
            phi = phi_sequences(run, setup.model.internal.input_names)[1]
            parts.append(phi.reshape(self.draws, n, -1))
        return torch.cat(parts, dim=1).reshape(-1, parts[0].shape[-1])


def heldout_fields(setup: Any, names: Sequence[str] | None) -> list[Any]:
    """The fields the held-out cells move in: ``setup``'s training field, or those named
    (``gp.choice.fields``)."""
    return [setup.field] if names is None else [build_field(field_config(n)) for n in names]


def candidate_seed(seed: int, name: str) -> int:
    """The seed candidate ``name``'s simulated durations start from: ``seed`` plus a hash of
    the name (CRC-32, stable across processes and runs), so a candidate draws the same
    sequences whichever others are scored beside it. Numbered by place, the three phases'
    spread on CERENA's network read +4.6 % in one candidate list and +5.0 % in another
    (docs/choice.md).

    Example:
        >>> candidate_seed(0, "phases") == candidate_seed(0, "phases")
        True
    """
    return seed + zlib.crc32(name.encode()) % CANDIDATE_SEEDS


def _clock_axis(
    gp: Mapping[str, Any], keys: tuple[str, ...] = ("max_age", "clock_bins")
) -> dict[str, Any]:
    """An added clock's axis in its gp group ``gp`` (its cap and bins; a log clock's knee
    too): what it changes in the recipe of the clock it was made from."""
    return {k: gp[k] for k in keys if k in gp}


Outcome = tuple[str | None, float, str | None, KindScore | None]
#: a candidate's scoring: its name, the held-out inputs and phi, its seed, the cells' groups,
#: the windows its likelihood sums, the draws per cell and the closed loop's design (or None)
Task = tuple[str, torch.Tensor, torch.Tensor, int, tuple[int, ...], str, int, "ClosedLoop | None"]


@contextlib.contextmanager
def candidate_pool(
    workers: int, fitter: Fitter, candidates: Mapping[str, Any]
) -> Iterator[ProcessPoolExecutor | None]:
    """``workers`` spawned processes of :data:`FIT_THREADS` torch thread(s) each
    (:func:`~surrogate.processes.spawned_pool`) to fit ``candidates`` with ``fitter`` (None
    where one is asked, there is one candidate, or their settings cannot cross to a process),
    each started at once and importing the fitter's modules while this process collects and
    records the held-out run. A fit in a worker therefore sees one core: it does not spread its
    classifiers over processes of its own."""
    if workers <= 1 or len(candidates) < 2 or not _crosses_processes(fitter, candidates):
        yield None
        return
    log.info("choice: %d processes to fit the %d candidates in, one thread each", workers,
             len(candidates))  # fmt: skip
    with spawned_pool(workers, threads=FIT_THREADS) as pool:
        for _ in range(workers):  # one process each (spawned as tasks find none idle)
            pool.submit(_ready, fitter)
        yield pool


def _ready(fitter: Fitter) -> None:
    """Nothing: unpickling ``fitter`` imported its modules (what every fit needs)."""


def fit_candidates(
    candidates: Mapping[str, Any],
    fitter: Fitter,
    workers: int = 1,
    heldout: HeldOut | None = None,
    ahead: tuple[str, Any] | None = None,
    pool: ProcessPoolExecutor | None = None,
) -> tuple[dict[str, tuple[Path, float]], dict[str, str], dict[str, KindScore]]:
    """Fit (or reuse) each candidate and, given the ``heldout`` run, score it: its fit directory
    and seconds by name, the reasons of those whose fit failed numerically (left out, named,
    not the whole choice) and the scores, each in the candidates' order.

    With ``workers > 1`` or a ``pool`` (:func:`candidate_pool`), in its processes, the
    dearest-looking first (the candidates come simplest first); each fit is the one made in
    this process (its seed and thread count are its settings'), each score too (one thread, its
    seed), and candidates sharing a fit (the two-state psi) wait for it under the artefact's
    lock. The workers' log records go through this process's handlers. ``ahead`` (a name and
    train settings; only in processes) is fitted too, first and unscored, and waited for: the
    final fit of K lumps, made while the others are scored
    (``gp.choice.ahead``); its numerical failure is logged, not raised.
    """
    outcomes: dict[str, Outcome] = {}
    tasks = {name: (tr, heldout.task(name) if heldout is not None else None)
             for name, tr in candidates.items()}  # fmt: skip
    with contextlib.ExitStack() as stack:
        if pool is None:
            pool = stack.enter_context(candidate_pool(workers, fitter, candidates))
        if pool is None:
            for name, (tr, task) in tasks.items():
                outcomes[name] = _fit_one(fitter, tr, task)
                _log_outcome(name, outcomes[name])
        else:
            early = pool.submit(_fit_one, fitter, _quiet(ahead[1])) if ahead else None
            futures = {name: pool.submit(_fit_one, fitter, _quiet(tr), task)
                       for name, (tr, task) in reversed(list(tasks.items()))}  # fmt: skip
            for name, future in futures.items():
                outcomes[name] = future.result()
                _log_outcome(name, outcomes[name])
            if ahead is not None and early is not None:
                _log_ahead(ahead[0], early.result())
    fits, failed, scores = {}, {}, {}
    for name in candidates:
        path, seconds, error, score = outcomes[name]
        if error is not None:
            failed[name] = error
        else:
            assert path is not None
            fits[name] = (Path(path), seconds)
            if score is not None:
                scores[name] = score
    return fits, failed, scores


def _crosses_processes(fitter: Fitter, candidates: Mapping[str, Any]) -> bool:
    """Whether the fitter and every candidate's settings pickle (a spawned worker rebuilds them
    by import: a model class defined in an interactive session does not); where one does not,
    say so: the candidates are then fitted in this process."""
    try:  # serialised as the pool will, never read back here
        ForkingPickler.dumps((fitter, list(candidates.values())))
    except Exception as error:  # any object the pickler refuses, whatever its error
        log.info("choice: fitting the candidates in this process, one after the other: their "
                 "settings cannot go to a worker process (%s)", error)  # fmt: skip
        return False
    return True


def _log_outcome(name: str, outcome: Outcome) -> None:
    _, seconds, error, score = outcome
    if error is not None:
        log.warning("choice: %s left out: its fit failed: %s", name, error)
    else:
        log.info("choice: %s fitted (or reused) in %.1f s%s", name, seconds,
                 f", scored in {score.score_seconds:.1f} s" if score is not None else "")  # fmt: skip


def _log_ahead(name: str, outcome: Outcome) -> None:
    _, seconds, error, _ = outcome
    if error is not None:  # the train after the choice fits it again, and says why, if chosen
        log.warning("choice: %s with its recipe, fitted ahead, failed: %s", name, error)
    else:
        log.info("choice: %s trained ahead with its recipe in %.1f s (gp.choice.ahead: the "
                 "fit gp=auto trains where it is chosen)", name, seconds)  # fmt: skip


def _quiet(tr: Any) -> Any:
    """``tr`` without progress bars (processes side by side would interleave them)."""
    return dataclasses.replace(tr, job=dataclasses.replace(tr.job, progress=False))


def _fit_one(fitter: Fitter, tr: Any, task: Task | None = None) -> Outcome:
    """One candidate's fit and, given its scoring ``task``, its score on one thread: (its
    directory, seconds, None, the score), or (None, seconds, the reason, None) where the fit
    failed numerically (a NumericalError carries a model, which need not cross processes)."""
    start = time.perf_counter()
    try:
        path = fitter(tr)
    except NumericalError as error:
        return None, time.perf_counter() - start, str(error), None
    seconds = time.perf_counter() - start
    if task is None:
        return str(path), seconds, None, None
    name, inputs, phi, seed, groups, likelihood_from, draws, closed = task
    with one_thread(True):
        score = _score(name, tr, (path, seconds), tr.setup.model, inputs, phi, seed, groups,
                       likelihood_from, draws, closed)  # fmt: skip
    return str(path), seconds, None, score


def _fit_added(
    fitter: Fitter,
    plan: PendingChoice,
    name: str,
    gp: dict[str, Any],
    final: dict[str, Any],
    heldout: HeldOut,
) -> tuple[Any, dict[str, Any], tuple[Path, float], KindScore] | str:
    """A candidate the choice adds (a longer clock, a log clock), the gp group ``gp``, fitted
    here and scored, or as its recipe trains it (``final``) where that fit fails numerically
    (:func:`_with_recipe`): its train settings, group, fit and score, or why it failed."""
    assert plan.make is not None  # the choice adds none without it
    added = plan.make(gp)
    path, seconds, error, score = _fit_one(fitter, added, heldout.task(name))
    _log_outcome(name, (path, seconds, error, score))
    if error is None and path is not None and score is not None:
        return added, gp, (Path(path), seconds), score
    retried = _with_recipe(fitter, plan, name, final, heldout.task(name))
    return str(error) if retried is None else retried


def _with_recipe(
    fitter: Fitter,
    plan: PendingChoice,
    name: str,
    final: dict[str, Any] | None,
    task: Task,
) -> tuple[Any, dict[str, Any], tuple[Path, float], KindScore] | None:
    """Candidate ``name`` fitted (in this process) and scored as its recipe trains it, the gp
    group ``final``, where its scoring fit failed numerically and that group differs from the
    scoring one (L-BFGS's line search can leave the region where the covariances are positive
    definite in its first step: Tyson's clock at 10 s on one collection of two): its train
    settings, group, fit and score; None where there is no such group or it fails too."""
    if final is None or plan.make is None or final == plan.groups.get(name):
        return None
    log.info("choice: %s: fitting it with its recipe's optimiser instead", name)
    tr = plan.make(final)
    path, seconds, error, score = _fit_one(fitter, tr, task)
    _log_outcome(name, (path, seconds, error, score))
    if error is not None or path is None or score is None:
        return None
    return tr, final, (Path(path), seconds), score


def _score(  # noqa: PLR0913  # a Task's parts, as the workers receive them
    name: str,
    tr: TrainSettings,
    fit: tuple[Path, float],
    model: Any,
    inputs: torch.Tensor,
    phi: torch.Tensor,
    seed: int,
    groups: tuple[int, ...] = (),
    likelihood_from: str = FROM_START,
    draws: int = 1,
    closed: ClosedLoop | None = None,
) -> KindScore:
    """Candidate ``name``'s held-out score (its layer from its fit directory, as simulate builds
    it; its durations per group of cells, ``groups``, from ``draws`` simulated sequences per
    cell; its likelihood over the windows ``likelihood_from`` says; its own population's
    durations where ``closed`` says how the held-out run was made), with its fit's and its
    score's seconds."""
    start = time.perf_counter()
    fit_dir, fit_seconds = fit
    request = LayerRequest.of_fit(model, tr, "lookup", None, torch.device("cpu"))
    layer, _ = tr.kind.decision_layer(request, fit_dir)
    # its own population, run as the held-out cells were (another seed than its draws')
    loop_phi = None if closed is None else closed.run(tr, layer, seed + 1, phi[:, 0])
    s = score_kind(name, tr.kind, layer, inputs, phi, tr.setup.dt, model.internal.lump_names,
                   seed=seed, groups=groups, likelihood_from=likelihood_from, draws=draws,
                   closed=loop_phi)  # fmt: skip
    own = largest_miss(own_rows_of(read_json(fit_dir / FIT_METRICS,
                                             made_by="python scripts/train.py")))  # fmt: skip
    return dataclasses.replace(
        s, fit_seconds=fit_seconds, score_seconds=time.perf_counter() - start, own_rows=own
    )


def own_rows_of(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """The own-rows summaries (:func:`surrogate.gp.own_rows.summary`) of the classifiers a
    fit's layer draws from, by name: a K-lumps chain's class classifiers (``class a->b``)
    where its metrics hold them, else psi_0 and psi_1 (each None for a fit made before they
    were recorded, or with too few switches to check)."""
    chain = metrics.get("class_chain") or {}
    classes = {f"class {a}->{b}": s for a, m in chain.items() if isinstance(m, dict)
               for b, s in (m.get("own_rows") or {}).items()}  # fmt: skip
    if classes:
        return classes
    return {n: summary((metrics.get(n) or {}).get("own_rows")) for n in ("psi_0", "psi_1")}


def _log(choice: Choice, overrides: str) -> None:
    """The score table and the reason, in the log."""
    for row in choice.table:
        on = [k for k in row if k.endswith("_ks") and not k.startswith("closed_")]
        spread = (f"  spread {row['spread_rel_diff']:+.1%} (SE {row['spread_rel_se']:.1%}, "
                  f"{row['spread_block_s']:g}-s blocks)"
                  if math.isfinite(row.get("spread_rel_diff", math.nan)) else "")  # fmt: skip
        lumps = [k[: -len("_ks")] for k in on]
        means = "  means " + " ".join(f"{lump} {row[f'{lump}_mean_rel_diff']:+.1%}"
                                      for lump in lumps)  # fmt: skip
        if lumps and f"closed_{lumps[0]}_mean_rel_diff" in row:
            means += "; closed loop " + " ".join(
                f"{lump} {row[f'closed_{lump}_mean_rel_diff']:+.1%}" for lump in lumps
            ) + (f", spread {row['closed_spread_rel_diff']:+.1%}"
                 if math.isfinite(row.get("closed_spread_rel_diff", math.nan)) else "")  # fmt: skip
        own = (
            f"  own rows {row['own_rows_ratio'] - 1:+.1%} ({row['own_rows_z']:.1f} SE"
            f"{', off' if row['own_rows_off'] else ''})"
            if "own_rows_ratio" in row
            else ""
        )
        log.info("choice: %-18s log-lik/window %.5f (%+.2e, SE %.1e)  %s%s%s%s  fit %.1f s, "
                 "score %.1f s", row["kind"], row["log_likelihood_per_window"],
                 row["diff_from_best"], row["diff_se"],
                 "  ".join(f"{k} {row[k]:.3f} (crit {row[k + '_critical_05']:.3f})" for k in on),
                 spread, means, own,
                 row["fit_seconds"], row["score_seconds"])  # fmt: skip
    log.info("choice: %s, because %s; simulate with `%s`", choice.chosen, choice.reason,
             overrides)  # fmt: skip
