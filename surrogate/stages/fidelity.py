"""The fidelity stage: is the abstraction indistinguishable from the full model at scale, for
every training seed?

``python scripts/fidelity.py`` trains one abstraction per training seed (and per input choice:
the model's signal and the paper's raw inputs), then simulates, in batches (replicates in one
population), on every field: the full model (the reference), a second full run with another
seed (the noise floor), the chain driven by the exact lumped psi (the psi of cells adapted to
their current input, where the model has one; moving cells are not adapted, so a learned psi
can do better) and every abstraction. It checks, per field and candidate (the exact chain and
every abstraction; the second full run is the floor the checks are measured against, not a
candidate: compared with itself it could not fail):

* the KS distance between the observable (distance from the peak) of the abstraction and of the
  full model at each evaluation time is at most ``max(ks_factor x the full-vs-full KS at that
  time, the KS critical value at alpha)`` and at most ``ks_max``;
* the mean duration of each phi segment (run, tumble) is within ``duration_tolerance`` of the
  full model's,

and writes ``fidelity.csv`` (one row per field, candidate and quantity), ``fidelity.md`` (the
table, pass/fail per check, the count of passing checks), ``summary.json`` and a figure of the
KS distances over time against the noise floor.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from surrogate.config import (
    build_field,
    field_config,
    grid_size,
    non_negative,
    positive,
    seed_everything,
    to_dict,
    validate_start,
)
from surrogate.errors import ArtefactError, ConfigError
from surrogate.evaluate.report import format_markdown_table, write_report
from surrogate.evaluate.statistics import KS_C_ALPHA_05, ks_critical_value, noise_threshold
from surrogate.io import (
    MANIFEST,
    artefact_dir,
    make_once,
    read_manifest,
    save_figure,
    write_csv,
    write_json,
    write_manifest,
)
from surrogate.kinds import (
    LayerRequest,
    exact_class_decision,
    exact_clock_decision,
    exact_decision,
    mode_kind,
)
from surrogate.models.capabilities import (
    exact_class_step_of,
    has_exact_psi,
    signal_bounds_of,
    start_size_of,
)
from surrogate.simulate.batch import Replicate
from surrogate.simulate.classes import can_classify
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import use_compile_cache
from surrogate.simulate.memory import can_age
from surrogate.simulate.paired import paired_starts
from surrogate.simulate.population import steps_between
from surrogate.simulate.precompile import kernel_wanted, precompile_in_background
from surrogate.simulate.support import describe_sparse_where, sparse_share, warn_outside
from surrogate.stages import reference
from surrogate.stages.artefacts import SUMMARY
from surrogate.stages.check_history import (
    PREVIOUS,
    REMEDY_KEYS,
    compare_with_previous,
    describe_not_advised,
    tried_in_vain,
    warn_followed_for_worse,
)
from surrogate.stages.check_history import describe as describe_previous
from surrogate.stages.choice import settle
from surrogate.stages.collect import collect
from surrogate.stages.reference import (
    FIELD_SEED_STRIDE,
    ReferenceSettings,
    field_seed,
    streams_of,
)
from surrogate.stages.runs import RunPlan, RunResult, mean_observables, simulate_runs
from surrogate.stages.settings import (
    FIDELITY_CMD,
    Job,
    ModelSetup,
    TrainSettings,
    group_overrides,
    resolve_start,
    validate_backend,
)
from surrogate.stages.simulate import COMPILE_CACHE, learned_decision
from surrogate.stages.train import (
    class_diagnostic_by_lump,
    fit_candidate,
    read_metrics,
    resolve_abstraction,
    train,
)

log = logging.getLogger(__name__)

TABLE = "fidelity"
FIGURE = "ks_over_time.png"
#: the drift itself: each run's mean observable over time on the full model's noise band
DRIFT_FIGURE = "drift.png"
#: c(alpha) of the asymptotic two-sample KS critical value, by alpha
KS_C = {0.05: KS_C_ALPHA_05, 0.01: 1.628, 0.001: 1.949}


@dataclass(frozen=True, eq=False)
class Candidate:
    """One abstraction under test: its input choice and training seed (and its settings)."""

    inputs: str
    train_seed: int
    train: TrainSettings
    #: where its cells start (``fidelity.initial`` resolved, :func:`resolve_start`)
    start: str = "internal"
    #: its chains' stream past ``sim_seed + 3 x offset``: its training seed, plus
    #: :data:`INPUTS_SEED_STRIDE` per input choice before its own (:func:`chain_stream`)
    stream: int = 0

    @property
    def label(self) -> str:
        """e.g. ``dG seed 1``."""
        return f"{'+'.join(self.train.inputs)} seed {self.train_seed}"


@dataclass(frozen=True, eq=False)
class FidelitySettings:
    """Everything the fidelity stage runs and checks, validated up front."""

    setup: ModelSetup
    fields: tuple[str, ...]
    candidates: tuple[Candidate, ...]
    exact_psi: bool
    options: dict[str, Any]
    times: tuple[float, ...]
    compile: bool
    job: Job
    backend: str = "auto"
    #: the clocks' caps (s) of an exact psi with a switch clock beside candidates with one
    exact_clocks: tuple[float, ...] = ()
    #: the exact K-lumps chain beside candidates with gp.lumps=classes
    exact_classes: bool = False
    #: the full model and its noise floor read from stored references (fidelity.reference=stored)
    references: ReferenceSettings | None = None

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> FidelitySettings:
        """Validate the fidelity group and every abstraction's training settings."""
        c = to_dict(cfg)
        f = dict(c["fidelity"])
        fields = tuple(str(x) for x in f.get("fields") or [])
        if not fields:
            raise ConfigError("fidelity.fields must list at least one field")
        for name in fields:
            field_config(name)
        seeds = [int(s) for s in f.get("train_seeds") or []]
        if not seeds or min(seeds) < 0:
            raise ConfigError("fidelity.train_seeds must list non-negative training seeds")
        if len(set(seeds)) < len(seeds):
            raise ConfigError(f"fidelity.train_seeds lists a seed twice, {seeds}: the same seed "
                              f"trains the same abstraction")  # fmt: skip
        choices = f.get("inputs") or ["signal"]
        candidates = []
        for j, choice in enumerate(choices):
            for seed in seeds:
                tc = {**c, "seed": seed, "gp": {**c["gp"], "inputs": choice}}
                train = TrainSettings.from_config(tc)
                start = resolve_start(f.get("initial", "internal"), train, "fidelity.initial")
                candidates.append(Candidate(str(choice), seed, train, start,
                                            chain_stream(j, seed)))  # fmt: skip
        setup = candidates[0].train.setup
        positive(f, "n_cells", "fidelity.", integer=True)
        t_end = float(positive(f, "t_end", "fidelity."))
        try:
            steps_between(t_end, setup.dt, "fidelity.t_end")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        times = _times(f.get("times"), t_end, setup.dt)
        _check_run_and_checks(f, start_size_of(setup.model.body))
        _check_streams(f, candidates)
        for cand in candidates:
            if not mode_kind(str(f.get("mode", "lookup"))).table:  # validated just above
                continue
            if len(cand.train.inputs) > 3:
                raise ConfigError(
                    f"fidelity.mode=lookup tabulates at most 3 inputs, {cand.label} has "
                    f"{list(cand.train.inputs)}: use fidelity.mode=classifier"
                )
            grid_size(f.get("lookup_size"), "fidelity.lookup_size", len(cand.train.inputs))
        exact = bool(f.get("exact_psi", True)) and has_exact_psi(setup.model.internal)
        if exact and signal_bounds_of(setup.model.internal) is None:
            exact = False
        if "exact_psi" in f:  # what runs: "also the exact chain where the model has one"
            f = {**f, "exact_psi": exact}
        clocks: tuple[float, ...] = ()
        if exact and can_age(setup.model.internal):
            ages = sorted({c.train.max_age for c in candidates if c.train.kind.clock})
            clocks = tuple(ages[:1])  # one reference row: the candidates share gp.max_age
        internal = setup.model.internal
        exact_classes = (exact and any(c.train.kind.classes for c in candidates)
                         and can_classify(internal) and exact_class_step_of(internal) is not None
                         and len(internal.signal_names) == 1)  # fmt: skip
        references = _stored_references(c, f, times)
        return cls(setup, fields, tuple(candidates), exact, f, times,
                   bool(c.get("compile", False)), Job.from_config(cfg),
                   validate_backend(c), clocks, exact_classes, references)  # fmt: skip

    def identity(self) -> dict[str, Any]:
        """The candidates' training identities, the fields and the run and check settings."""
        return {
            "model": self.setup.model_config,
            "dt": self.setup.dt,
            "fields": {name: field_config(name) for name in self.fields},
            "candidates": [c.train.identity() for c in self.candidates],
            # checks whose candidates start as before keep the identity they had
            **({"initial": [c.start for c in self.candidates]}
               if any(c.start != "internal" for c in self.candidates) else {}),
            "exact_psi": self.exact_psi,
            # chains keyed by training seed (chain_stream); where that differs from the old
            # rule (the i-th listed drew + i), a check made before is not read as this one
            **({"chain_streams": [c.stream for c in self.candidates]}
               if any(c.stream != i for i, c in enumerate(self.candidates)) else {}),
            **({"exact_clocks": list(self.exact_clocks)} if self.exact_clocks else {}),
            **({"exact_classes": True} if self.exact_classes else {}),
            # checks from independent starts keep the identity they had before the key
            "fidelity": {**{k: v for k, v in self.options.items() if k != "initial"
                            and not (k == "starts" and v == "independent")
                            and not (k == "chain_repeats" and v == 1)},
                         "times": list(self.times)},
            "compile": self.compile,
            "backend": self.backend,
            "device": self.job.device_type,
            **({"references": [r.directory.name for r in self.references.runs]}
               if self.references is not None else {}),
        }  # fmt: skip

    @functools.cached_property
    def directory(self) -> Path:
        """``data/fidelity/model=..._n=..._T=..._seeds=...-<hash>``."""
        seeds = sorted({c.train_seed for c in self.candidates})
        label = {"model": self.setup.model.name, "n": self.options["n_cells"],
                 "T": self.options["t_end"], "seeds": "+".join(map(str, seeds))}  # fmt: skip
        return artefact_dir(self.job.data_dir, "fidelity", label, self.identity())

    def command(self) -> str:
        """The command that makes this artefact."""
        return " ".join([FIDELITY_CMD, *group_overrides("model", self.setup.model_config)])


#: the candidate row of the exact psi with a switch clock
EXACT_CLOCK = "exact+clock"
#: the candidate row of the exact K-lumps chain
EXACT_CLASSES = "exact+classes"
#: reference rows (not learned abstractions): not counted in the summary's checks
REFERENCES = ("exact", EXACT_CLOCK, EXACT_CLASSES)
#: ``fidelity.chain_repeats``: repeat r of abstraction i runs at its seed + r x this stride
#: (far from every other run's sim_seed + k x offset + i), labelled ``<label>|<field>|repeat<r>``
REPEAT_SEED_STRIDE = 100_000
REPEAT = "repeat"
#: the chains of the j-th ``fidelity.inputs`` choice run past those of the first by j x this
INPUTS_SEED_STRIDE = 10_000


def chain_stream(choice_index: int, train_seed: int) -> int:
    """The stream of an abstraction's chains past ``sim_seed + 3 x noise_seed_offset``.

    Keyed by what the abstraction is (its input choice and training seed), not by where it
    stands in the run's list: a training seed's check draws the same chains whether it is run
    alone or beside others, and two runs that list different seeds first do not share a stream
    (they did until 2026-12-01, session 28: abstraction i drew ``+ i``; with the default
    ``train_seeds=[0,1]`` and one input choice, the two rules agree).
    """
    return choice_index * INPUTS_SEED_STRIDE + train_seed


def chain_seed(options: Mapping[str, Any], candidate: Candidate, repeat: int = 0) -> int:
    """The seed of ``candidate``'s chains (its ``repeat``-th run) under the fidelity
    ``options``: ``sim_seed + 3 x noise_seed_offset + stream + repeat x``
    :data:`REPEAT_SEED_STRIDE`."""
    base = int(options["sim_seed"]) + 3 * int(options.get("noise_seed_offset", 1000))
    return base + candidate.stream + repeat * REPEAT_SEED_STRIDE


#: decision.mode of the abstractions under test
MODES = ("lookup", "classifier")
#: fidelity.reference: simulate the full model beside the candidates, or read stored runs
REFERENCE_CHOICES = ("run", "stored")
#: fidelity.starts: each run's cells from their own internal draw (burn-in), or every run of
#: a field from the same one (:mod:`surrogate.simulate.paired`)
STARTS = ("independent", "paired")


def _times(value: Any, t_end: float, dt: float) -> tuple[float, ...]:
    """``fidelity.times``: multiples of dt in (0, t_end] (null: the quarters of t_end)."""
    if value is None:
        return tuple(t_end * (k + 1) / 4 for k in range(4))
    try:
        times = tuple(float(t) for t in value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"fidelity.times must be a list of times in s (or null: the quarters of t_end), "
            f"got {value!r}"
        ) from None
    if not times:
        raise ConfigError("fidelity.times must list at least one time (or be null)")
    for t in times:
        if not 0 < t <= t_end:
            raise ConfigError(f"fidelity.times {t:g} outside (0, t_end={t_end:g}]")
        try:
            steps_between(t, dt, "fidelity.times")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    return times


def _stored_references(
    c: Mapping[str, Any], f: Mapping[str, Any], times: Sequence[float]
) -> ReferenceSettings | None:
    """``fidelity.reference=stored``: the stored runs the check reads, each present and
    keeping ``times`` (refused now, before any training, naming the command that makes them or
    the settings that differ); None for ``run``."""
    choice = f.get("reference", "run")
    if choice not in REFERENCE_CHOICES:
        raise ConfigError(f"fidelity.reference must be one of {list(REFERENCE_CHOICES)}, got "
                          f"{choice!r}")  # fmt: skip
    if choice == "run":
        return None
    settings = ReferenceSettings.from_config(c)
    for r in settings.runs:
        reference.load(r, settings.command, times)  # present, and at these times
    return settings


def field_stream(options: Mapping[str, Any], run_seed: int, field: str) -> int:
    """The seed a run whose stream is ``run_seed`` (the full model, its floor, a chain) draws
    from on ``field``, under the fidelity ``options``: moved by the field's place in
    ``fidelity.fields`` where ``fidelity.streams`` is ``per_field``
    (:func:`~surrogate.stages.reference.field_seed`, the rule stored references are made by)."""
    fields = [str(x) for x in options["fields"]]
    return field_seed(run_seed, fields.index(field), streams_of(options))


def _chain_seeds(settings: FidelitySettings) -> str:
    """Each abstraction's chain seed, e.g. ``seed 0: 8000, seed 1: 8001``."""
    return ", ".join(f"{c.label}: {chain_seed(settings.options, c)}" for c in settings.candidates)


def _check_streams(f: Mapping[str, Any], candidates: list[Candidate]) -> None:
    """Every run of the check on its own stream: the full model, its floor, the exact chains
    and each abstraction's chains (and repeats) at distinct, non-negative seeds."""
    seed, offset = int(f["sim_seed"]), int(f.get("noise_seed_offset", 1000))
    streams, fields = streams_of(f), [str(x) for x in f.get("fields") or []]
    runs: dict[int, str] = {}
    most_repeats = FIELD_SEED_STRIDE // REPEAT_SEED_STRIDE
    for name in fields if streams == "per_field" else fields[:1]:
        where = f" on {name}" if streams == "per_field" else ""
        for s, what in ((seed, "the full model"), (seed + offset, "the noise floor"),
                        (seed + 2 * offset, "the exact chain")):  # fmt: skip
            runs[field_stream(f, s, name)] = what + where
        for c in candidates:
            for again in range(int(f.get("chain_repeats", 1))):
                s = field_stream(f, chain_seed(f, c, again), name)
                what = c.label + (f" (repeat {again})" if again else "")
                if s < 0 or s in runs:
                    raise ConfigError(
                        f"fidelity: {what} would draw its chains{where} from seed {s}, "
                        + ("negative" if s < 0 else f"the seed of {runs[s]}")
                        + ": choose a fidelity.sim_seed or noise_seed_offset that keeps sim_seed "
                        "+ 3 x offset + training seed apart from sim_seed, + offset and + 2 x "
                        f"offset (and at most {most_repeats} chain_repeats: each field's "
                        f"streams start {FIELD_SEED_STRIDE:,} past the last's)"
                    )
                runs[s] = what + where


def _check_run_and_checks(f: Mapping[str, Any], start_size: int | None) -> None:
    """The run settings (seeds, start, mode) and the check thresholds of the fidelity group,
    all read only after training and simulation: refused now, by name."""
    validate_start(f, "start", "fidelity.", start_size)
    non_negative(f, "equilibration_time", "fidelity.")
    seed = f.get("sim_seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"fidelity.sim_seed must be a non-negative integer, got {seed!r}")
    offset = f.get("noise_seed_offset", 1000)
    # the noise floor, the exact chain and abstraction i use sim_seed + offset, 2 x offset and
    # 3 x offset + i; offset 0 would compare the full run with itself (a noise floor of zero)
    lowest = seed + min(offset, 3 * offset) if isinstance(offset, int) else -1
    if isinstance(offset, bool) or not isinstance(offset, int) or offset == 0 or lowest < 0:
        raise ConfigError(
            f"fidelity.noise_seed_offset must be a non-zero integer with sim_seed + k x offset "
            f">= 0 for k = 1, 2, 3 (the noise floor, the exact chain and the abstractions use "
            f"those seeds), got {offset!r}"
        )
    repeats = f.get("chain_repeats", 1)
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ConfigError(f"fidelity.chain_repeats must be an integer >= 1 (each abstraction's "
                          f"runs per field; the check reads the first, the table the spread of "
                          f"all), got {repeats!r}")  # fmt: skip
    streams_of(f)
    starts = f.get("starts", "independent")
    if starts not in STARTS:
        raise ConfigError(f"fidelity.starts must be one of {list(STARTS)}, got {starts!r}")
    if starts == "paired" and f.get("reference", "run") != "run":
        raise ConfigError(
            "fidelity.starts=paired needs the full model run beside the candidates from the "
            "same starts: stored references drew their own; use fidelity.reference=run"
        )
    if f.get("mode", "lookup") not in MODES:
        raise ConfigError(f"fidelity.mode must be one of {list(MODES)}, got {f['mode']!r}")
    if not isinstance(f.get("exact_psi", True), bool):
        raise ConfigError(f"fidelity.exact_psi must be true or false, got {f['exact_psi']!r}")
    positive(f, "ks_factor", "fidelity.")
    positive(f, "ks_max", "fidelity.")
    positive(f, "duration_tolerance", "fidelity.")
    alpha = f.get("alpha", 0.05)
    if isinstance(alpha, bool) or not isinstance(alpha, int | float) or alpha not in KS_C:
        raise ConfigError(f"fidelity.alpha must be one of {sorted(KS_C)}, got {alpha!r}")


def validate(cfg: Mapping[str, Any]) -> FidelitySettings:
    """All checks of a fidelity config, before any work starts."""
    return FidelitySettings.from_config(cfg)


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Train, simulate and check (reusing what exists); return the artefact directory."""
    settings = settle(validate, cfg, fit_candidate)
    out, config = settings.directory, to_dict(cfg)
    make_once(
        out,
        settings.identity(),
        settings.command(),
        lambda _: _fidelity(settings, out, config),
        what="fidelity check",
        force=force,
    )
    # a check reused here may be one whose advice a later check followed for fewer passes:
    # say so (a check just made has no later one naming it, so this logs nothing then)
    warn_followed_for_worse(out, config, int(read_manifest(out).get("passed", 0)))
    return out


def _fidelity(settings: FidelitySettings, out: Path, config: Mapping[str, Any]) -> None:  # noqa: C901  # the stage's steps in order
    t0 = time.perf_counter()
    setup, o, job = settings.setup, settings.options, settings.job
    model = setup.model
    if settings.compile:
        use_compile_cache(job.data_dir / COMPILE_CACHE)
    if kernel_wanted(settings.backend, settings.compile):
        precompile_in_background(model, job.device)  # overlaps collect and train
    # 1. the abstractions (collect and train reuse what exists)
    psis = {}
    for c in settings.candidates:
        collect(c.train.source)  # type: ignore[arg-type]
        train(c.train)
        psis[c.label] = c
    train_s = time.perf_counter() - t0
    # 2. every run, in batches (decision-major, so same-kind layers merge)
    fields = {name: build_field(field_config(name)) for name in settings.fields}
    n = int(o["n_cells"])
    start = tuple(float(v) for v in o["start"])
    seed = int(o["sim_seed"])
    offset = int(o.get("noise_seed_offset", 1000))
    at_field = functools.partial(field_stream, o)  # each field its own stream (per_field)
    t1 = time.perf_counter()
    reps, labels = [], []
    stored: dict[str, RunResult] = {}
    if settings.references is not None:  # the full model and its floor, made once
        refs = settings.references
        for r in refs.runs:
            stored[f"{r.which}|{r.field_name}"] = reference.load(r, refs.command, settings.times)
            log.info("fidelity: the %s read from %s", r.describe(), r.directory)
    else:
        for which, s in (("full", seed), ("full_repeat", seed + offset)):
            for name in settings.fields:
                reps.append(Replicate(FullDecision(model.internal), fields[name], n,
                                      at_field(s, name), start))  # fmt: skip
                labels.append(f"{which}|{name}")
    if settings.exact_psi:
        exact, _ = exact_decision(model, setup.dt, "lookup", None, job.device)
        for name in settings.fields:
            reps.append(Replicate(exact, fields[name], n, at_field(seed + 2 * offset, name),
                                  start))  # fmt: skip
            labels.append(f"exact|{name}")
    for max_age in settings.exact_clocks:
        # the exact psi with a switch clock: the limit of the candidates with gp.history=age
        clocked = exact_clock_decision(model, setup.dt, max_age, job.device, EXACT_CLOCK)
        for name in settings.fields:
            reps.append(Replicate(clocked, fields[name], n, at_field(seed + 2 * offset, name),
                                  start))  # fmt: skip
            labels.append(f"{EXACT_CLOCK}|{name}")
    if settings.exact_classes:
        # the exact K-lumps chain: the limit of the candidates with gp.lumps=classes
        classed = exact_class_decision(model, setup.dt, job.device, EXACT_CLASSES)
        for name in settings.fields:
            reps.append(Replicate(classed, fields[name], n, at_field(seed + 2 * offset, name),
                                  start))  # fmt: skip
            labels.append(f"{EXACT_CLASSES}|{name}")
    for c in settings.candidates:
        request = LayerRequest.of_fit(model, c.train, str(o.get("mode", "lookup")),
                                      o.get("lookup_size"), job.device, c.start)  # fmt: skip
        decision, _ = learned_decision(request, c.train, resolve_abstraction(c.train),
                                       job.support_min_rows)  # fmt: skip
        for name in settings.fields:
            reps.append(Replicate(decision, fields[name], n, at_field(chain_seed(o, c), name),
                                  start))  # fmt: skip
            labels.append(f"{c.label}|{name}")
            for again in range(1, int(o.get("chain_repeats", 1))):  # the chain's own spread
                reps.append(Replicate(decision, fields[name], n,
                                      at_field(chain_seed(o, c, again), name), start))  # fmt: skip
                labels.append(f"{c.label}|{name}|{REPEAT}{again}")
    seed_everything(seed)
    info: dict[str, Any] = {}
    paired = o.get("starts", "independent") == "paired"
    with paired_starts(model.internal) if paired else contextlib.nullcontext() as starts:
        plan = RunPlan(setup.dt, settings.times, float(o["t_end"]),
                       float(o["equilibration_time"]), job.device, settings.compile,
                       settings.backend)  # fmt: skip
        results = simulate_runs(model, reps, labels, plan=plan, progress=job.progress,
                                desc="fidelity", info=info)  # fmt: skip
    if starts is not None:
        log.info("fidelity: paired starts, %d internal draws shared by %d runs", starts.drawn,
                 starts.drawn + starts.reused)  # fmt: skip
    results.update(stored)
    outside = {k: v for k, v in info.get("outside_training", {}).items() if v is not None}
    for label, report in outside.items():
        warn_outside(report, job.outside_warning, f"fidelity run {label}")
    sim_s = time.perf_counter() - t1
    # 3. the checks
    table = check(settings, results)
    (out / MANIFEST).unlink(missing_ok=True)
    write_csv(out / f"{TABLE}.csv", table)
    summary = summarise(table, settings)
    # the drift itself: each run's mean observable per check time, with its standard error
    summary["mean_observable"] = mean_observables(
        {k: r for k, r in results.items() if f"|{REPEAT}" not in k}
    )  # one run per chain drawn
    metrics = {c.label: read_metrics(c.train.directory) for c in settings.candidates}
    summary["diagnostics"] = {label: m.get("diagnostic") for label, m in metrics.items()}
    # the K-lumps chain's own switching, class-weighted where cells live (the two-state psi
    # fitted beside it is not what it simulates)
    summary["class_diagnostics"] = {
        label: class_diagnostic_by_lump(m["class_diagnostic"], settings.setup.model.internal)
        for label, m in metrics.items() if m.get("class_diagnostic")}  # fmt: skip
    summary["outside_training"] = outside
    # advice a check of the model followed from settings like these for fewer passes is not
    # printed again (surrogate/stages/check_history.py)
    tried = tried_in_vain(out, config)
    summary["wider_collection"] = wider_collection(settings, outside, config)
    summary["settled_collection"] = settled_collection(settings, summary, config)
    summary["wider_choice"] = wider_choice(settings, summary, config)
    not_advised = [" ".join(summary[k]) for k in REMEDY_KEYS
                   if summary[k] and " ".join(summary[k]) in tried]  # fmt: skip
    for key in ("wider_collection", "settled_collection"):
        if summary[key] and " ".join(summary[key]) in tried:
            summary[key] = None
    if summary["wider_choice"] and " ".join(summary["wider_choice"]) in tried:
        summary["wider_choice"] = wider_choice(settings, summary, config, tried)
    summary["not_advised"] = {r: tried[r] for r in not_advised}
    summary["settled_kept"] = settled_kept(settings) if summary["settled_collection"] else None
    summary["draw_again"] = draw_again(settings, summary, config)
    summary[PREVIOUS] = compare_with_previous(out, config, summary["passed"], summary["checks"])
    write_json(out / SUMMARY, summary)
    save_figure(out / FIGURE, plot_ks(table, settings))
    save_figure(out / DRIFT_FIGURE, plot_drift(summary["mean_observable"], settings))
    write_report(out / f"{TABLE}.md", report_sections(table, summary, settings), [
        ("KS distance of the observable over time: candidates vs the noise floor", out / FIGURE),
        ("The drift: mean observable over time, candidates on the full model's noise band",
         out / DRIFT_FIGURE)],
        title=f"Fidelity at scale: {model.describe()}")  # fmt: skip
    write_manifest(out, stage="fidelity", config=dict(config), seed=seed,
                   settings=settings.identity(), wall_time_s=time.perf_counter() - t0,
                   train_s=train_s, simulate_s=sim_s, cells=len(reps) * n,
                   passed=summary["passed"], checks=summary["checks"])  # fmt: skip
    log.info("fidelity: %d of %d checks pass; artefacts in %s", summary["passed"],
             summary["checks"], out)  # fmt: skip


def _refusal(config: Mapping[str, Any], overrides: list[str]) -> str | None:
    """Why this stage's own settings refuse the same command with ``overrides`` (a new
    collection, whose measured choices are not made yet), or None where they accept it."""
    from surrogate.stages.advice_check import apply_overrides
    from surrogate.stages.settings.choice import collecting_pending

    try:
        with collecting_pending():
            validate(apply_overrides(config, overrides))
    except (ConfigError, ArtefactError) as error:
        return str(error)
    return None


def wider_collection(
    settings: FidelitySettings, outside: Mapping[str, Mapping[str, Any]], config: Mapping[str, Any]
) -> list[str] | None:
    """Where a learned run's share of cell-steps outside its trained inputs is above
    ``outside_warning``: the overrides that send collect's jumps twice as far
    (:meth:`~surrogate.models.base.Model.wider_collection`), checked by this stage's own
    settings on ``config`` first; None where no run left them, the model has no such key, or
    the check refuses them (logged)."""
    away = sorted(label for label, r in outside.items()
                  if float(r.get("share_outside") or 0.0) > settings.job.outside_warning)  # fmt: skip
    wider = list(settings.setup.model.wider_collection())
    if not away or not wider:
        return None
    refused = _refusal(config, wider)  # e.g. a stored reference of the old radius
    if refused is not None:
        log.warning("fidelity: %s would reach the inputs of %s, but is refused: %s",
                    " ".join(wider), ", ".join(away), refused)  # fmt: skip
        return None
    log.warning("fidelity: runs %s left the collection's inputs; the same command with `%s` "
                "collects further from the field's peak", ", ".join(away), " ".join(wider))  # fmt: skip
    return wider


def settled_collection(
    settings: FidelitySettings, summary: Mapping[str, Any], config: Mapping[str, Any]
) -> list[str] | None:
    """Where a check failed and a candidate's collection lagged its jumps (collect's warning):
    the blackout collect advised (:func:`~surrogate.stages.reproduce.collection_blackout`, the
    union over the candidates), checked by this stage's own settings on ``config`` first;
    None where every check passed, no collection lagged, or the check refuses it (logged).
    CERENA's gene-expression network, training seeds 0-3: 38 of 48 on its default collection's
    settled rows (``gp.jump_rows=auto``), 42 of 48 with the blackout (docs/choice.md)."""
    from surrogate.stages.reproduce import collection_blackout

    if summary["passed"] >= summary["checks"]:
        return None
    # named whether or not the fits left the lagging rows out (gp.jump_rows): then it records
    # more of the rows they read (CERENA's seed 0, the log clock on L2: `high` / `low` +7.9 /
    # -10.6 % on 16 % of the default collection's rows, +3.5 / -2.6 % on the blackout's)
    named = (collection_blackout(c.train, unless_left_out=False) for c in settings.candidates)
    advice = list(dict.fromkeys(o for overrides in named for o in overrides))
    if not advice:
        return None
    refused = _refusal(config, advice)
    if refused is not None:
        log.warning("fidelity: the collection's rows lagged its jumps; %s would keep them out, "
                    "but is refused: %s", " ".join(advice), refused)  # fmt: skip
        return None
    log.warning("fidelity: checks failed and the collection's rows lagged its jumps (collect's "
                "warning); the same command with `%s` records rows only once a jump has "
                "settled", " ".join(advice))  # fmt: skip
    return advice


#: the choice's remedies the fidelity report names where checks fail (in this order):
#: candidates the choice lacked, then more held-out cells where it was a tie
CHOICE_REMEDIES = ("wider_kinds", "more_cells")


def wider_choice(
    settings: FidelitySettings,
    summary: Mapping[str, Any],
    config: Mapping[str, Any],
    tried: Collection[str] = (),
) -> list[str] | None:
    """Where a check failed and a candidate's chain was chosen by measurement (``gp=auto``):
    the first of its choice's own remedies that widen or sharpen it
    (:func:`~surrogate.diagnosis.remedies.choice_remedies`: K lumps over
    ``++model.classes=auto`` for a network that declares no classes, the memory families
    ``gp.choice.kinds`` left out; then four times the held-out cells where the choice was a
    tie) that this stage's own settings accept on ``config`` and that is not among ``tried``
    (overrides joined by spaces: followed before for fewer passes,
    :func:`~surrogate.stages.check_history.tried_in_vain`); None where every check passed,
    no chain was measured, or none applies. Wilkinson's immigration-death network: 17 of 24
    without K lumps, 22 of 24 with ``++model.classes=auto
    collect.keep_switches=true`` (its collection thinned; docs/sbml.md)."""
    from surrogate.diagnosis.remedies import choice_remedies
    from surrogate.models.network import NetworkInternalModel
    from surrogate.stages.reproduce import measured_choice

    if summary["passed"] >= summary["checks"]:
        return None
    for candidate in settings.candidates:
        choice = measured_choice(candidate.train)
        if choice is None:
            continue
        network = isinstance(candidate.train.setup.model.internal, NetworkInternalModel)
        remedies = {r.kind: r for r in choice_remedies(choice, None, network)}
        for kind in CHOICE_REMEDIES:
            if kind in remedies:
                advice = list(remedies[kind].overrides)
                if " ".join(advice) in tried:
                    log.info("fidelity: %s would widen the choice, but was followed before "
                             "for fewer passes", " ".join(advice))  # fmt: skip
                    continue
                refused = _refusal(config, advice)
                if refused is None:
                    log.warning("fidelity: checks failed; the same command with `%s` widens "
                                "or sharpens the measured choice", " ".join(advice))  # fmt: skip
                    return advice
                log.info("fidelity: %s would widen the choice, but is refused: %s",
                         " ".join(advice), refused)  # fmt: skip
    return None


#: ``fidelity.sim_seed`` + this: the whole check drawn again (every stream of the default
#: offset's runs lies below sim_seed + 3 x 1,000 + the training seeds)
DRAW_AGAIN_STRIDE = 10_000


def draw_again(
    settings: FidelitySettings, summary: Mapping[str, Any], config: Mapping[str, Any]
) -> list[str] | None:
    """Where a check failed: ``fidelity.sim_seed`` moved by :data:`DRAW_AGAIN_STRIDE`, which
    draws the full model, its floor and every chain again on the same collections and fits,
    checked by this stage's own settings on ``config`` (refused, e.g. stored references of
    the old seed: None, logged). A miss the draw decides moves to other checks in another draw,
    one the abstraction decides stays: CERENA's seed 1 passed 81 of 84 over seven draws, seed
    0 missed its L2 `high` mean in all seven (docs/choice.md)."""
    if summary["passed"] >= summary["checks"]:
        return None
    again = [f"fidelity.sim_seed={int(settings.options['sim_seed']) + DRAW_AGAIN_STRIDE}"]
    refused = _refusal(config, again)
    if refused is not None:
        log.info("fidelity: %s would draw the check again, but is refused: %s", again[0], refused)
        return None
    return again


def settled_kept(settings: FidelitySettings) -> float | None:
    """The smallest share of its collection's rows a candidate's fit read where the fits left
    the rows soon after a jump out (:func:`~surrogate.stages.reproduce.kept_share`); None where
    every fit read every row."""
    from surrogate.stages.reproduce import kept_share

    shares = [s for c in settings.candidates if (s := kept_share(c.train)) is not None]
    return min(shares) if shares else None


def check(settings: FidelitySettings, results: Mapping[str, RunResult]) -> pd.DataFrame:
    """One row per field, candidate (the exact psi's chain and every abstraction) and quantity:
    the statistic, the noise floor (the same statistic of the second full run), the threshold
    and whether it passes. The second full run is no candidate: its KS against the full run is
    the floor itself, so its checks could not fail."""
    from scipy import stats  # ~1.7 s to import: only where used

    o = settings.options
    alpha = float(o.get("alpha", 0.05))
    n = int(o["n_cells"])
    crit = ks_critical_value(n, n, KS_C[alpha])
    factor, ks_max, tol = float(o["ks_factor"]), float(o["ks_max"]), float(o["duration_tolerance"])
    lumps = settings.setup.model.internal.lump_names
    candidates = (["exact"] if settings.exact_psi else []) + (
        [EXACT_CLOCK] if settings.exact_clocks else []) + (
        [EXACT_CLASSES] if settings.exact_classes else []) + [
        c.label for c in settings.candidates]  # fmt: skip
    rows = []
    for name in settings.fields:
        full, repeat = results[f"full|{name}"], results[f"full_repeat|{name}"]
        for cand in candidates:
            run = results[f"{cand}|{name}"]
            again = [results[k] for k in results if k.startswith(f"{cand}|{name}|{REPEAT}")]
            for t in settings.times:
                ks = float(stats.ks_2samp(run.observables[t], full.observables[t]).statistic)
                floor = float(stats.ks_2samp(repeat.observables[t], full.observables[t]).statistic)
                limit = float(noise_threshold(floor, crit, factor, ks_max))
                row = {"field": name, "candidate": cand, "quantity": f"distance_t{t:g}",
                       "value": ks, "noise_floor": floor, "threshold": limit,
                       "passed": ks <= limit}  # fmt: skip
                if again:  # fidelity.chain_repeats: the share of the chain's runs that pass
                    others = [float(stats.ks_2samp(r.observables[t], full.observables[t]).statistic)
                              for r in again]  # fmt: skip
                    row["chain_pass_share"] = float(np.mean([v <= limit for v in (ks, *others)]))
                rows.append(row)
            for p in (1, 0):
                kind = lumps[p]
                rel = run.mean_durations[kind] / full.mean_durations[kind] - 1.0
                row = {"field": name, "candidate": cand, "quantity": f"mean_{kind}",
                       "value": rel, "noise_floor": repeat.mean_durations[kind]
                       / full.mean_durations[kind] - 1.0, "threshold": tol,
                       "passed": abs(rel) <= tol, "mean_s": run.mean_durations[kind],
                       "full_mean_s": full.mean_durations[kind],
                       "segments": run.segments[kind]}  # fmt: skip
                if again:  # fidelity.chain_repeats: the same chain's means from other seeds
                    means = np.array([r.mean_durations[kind] for r in (run, *again)])
                    row["chain_rel_sd"] = float(means.std(ddof=1) / means.mean())
                    row["chain_mean_rel"] = float(means.mean() / full.mean_durations[kind] - 1.0)
                rows.append(row)
    return pd.DataFrame(rows)


def _percent(value: float, tolerance: float) -> str:
    """A relative error in percent to one decimal, or two where one would print the tolerance
    itself (a -3.04 % miss of a 3 % check read "-3.0 % ✗")."""
    text = f"{100 * value:+.1f}"
    return f"{100 * value:+.2f}" if abs(float(text)) == round(100 * tolerance, 1) else text


def summarise(table: pd.DataFrame, settings: FidelitySettings) -> dict[str, Any]:
    """Counts of passing checks per candidate kind."""
    learned = table[~table["candidate"].isin(REFERENCES)]
    observed = f"{settings.setup.model.body.observable_names[0]}_t"  # its KS rows
    out: dict[str, Any] = {
        "checks": len(learned),
        "passed": int(learned["passed"].sum()),
        "by_candidate": {
            c: {"checks": len(g), "passed": int(g["passed"].sum())}
            for c, g in table.groupby("candidate", sort=False)
        },
        "max_distance_ks": {  # the key's name predates other observables (kept: summary.json)
            c: float(g.loc[g["quantity"].str.startswith(observed), "value"].max())
            for c, g in table.groupby("candidate", sort=False)
        },
        "max_abs_duration_error": {
            c: float(g.loc[g["quantity"].str.startswith("mean_"), "value"].abs().max())
            for c, g in table.groupby("candidate", sort=False)
        },
    }
    return out


def report_sections(
    table: pd.DataFrame, summary: Mapping[str, Any], settings: FidelitySettings
) -> list[tuple[str, str]]:
    """The markdown report: setting, the target table per candidate, diagnostics."""
    o = settings.options
    name = settings.setup.model.body.observable_names[0]
    n = int(o["n_cells"])
    crit = ks_critical_value(n, n, KS_C[float(o.get("alpha", 0.05))])
    setting = (
        f"{settings.setup.model.describe()}. {o['n_cells']} cells per run, {o['t_end']} s, "
        f"dt {settings.setup.dt:g} s, start {list(o['start'])}; abstractions trained on "
        f"`{settings.setup.field_name}` with seeds {sorted({c.train_seed for c in settings.candidates})} "
        f"(collection and training), inputs {sorted({'+'.join(c.train.inputs) for c in settings.candidates})}. "
        f"Full model seed {o['sim_seed']}, noise floor seed {int(o['sim_seed']) + int(o.get('noise_seed_offset', 1000))}, "
        f"chain seeds {_chain_seeds(settings)}"
        + (
            f", each field past the last's by {FIELD_SEED_STRIDE:,} (fidelity.streams=per_field). "
            if streams_of(o) == "per_field"
            else ", every field the same (fidelity.streams=shared). "
        )
        + f"Check: {name} KS <= min(max({o['ks_factor']} x full-vs-full KS, KS critical {crit:.4f} at "
        f"alpha {o.get('alpha', 0.05)}), {o['ks_max']}); mean segment durations within "
        f"{100 * float(o['duration_tolerance']):g} % of the full model's."
    )
    rows = []
    for (field, cand), g in table.groupby(["field", "candidate"], sort=False):
        row: dict[str, Any] = {"field": field, "candidate": cand}
        for _, r in g.iterrows():
            q = r["quantity"]
            mark = "" if r["passed"] else " ✗"
            if q.startswith(f"{name}_t"):
                share = (f" (runs pass {100 * r['chain_pass_share']:.0f} %)"
                         if pd.notna(r.get("chain_pass_share", np.nan)) else "")  # fmt: skip
                row[q.replace(f"{name}_", "KS ")] = (
                    f"{r['value']:.3f} ({r['noise_floor']:.3f}){mark}{share}"
                )
            else:
                spread = (f" (runs {100 * r['chain_mean_rel']:+.1f} % +- "
                          f"{100 * r['chain_rel_sd']:.1f} % sd)"
                          if pd.notna(r.get("chain_rel_sd", np.nan)) else "")  # fmt: skip
                floor = (f" ({100 * r['noise_floor']:+.1f} %)"
                         if pd.notna(r.get("noise_floor", np.nan)) else "")  # fmt: skip
                row[q.replace("mean_", "mean ")] = (f"{_percent(r['value'], r['threshold'])} %"
                                                    f"{floor}{mark}{spread}")  # fmt: skip
        row["passed"] = f"{int(g['passed'].sum())}/{len(g)}"
        rows.append(row)
    alpha = float(o.get("alpha", 0.05))
    learned = table[~table["candidate"].isin(REFERENCES)]
    n_ks = int(learned["quantity"].str.startswith(f"{name}_t").sum())
    target = (
        f"{summary['passed']} of {summary['checks']} checks of the learned abstractions pass. "
        f"Each KS check's limit is at least the critical value at alpha {alpha:g}, so a chain "
        f"with the full model's own law still fails each with probability up to alpha: up to "
        f"{alpha * n_ks:.1f} of these {n_ks} KS checks by chance (for E. coli, `python "
        "scripts/fidelity_null.py` runs the full model itself as the candidate). "
        "Cells: KS distance abstraction vs full model, and the relative error of the mean "
        "segment durations (in brackets: the same between two full runs, the noise floor; a "
        f"mean is held to {100 * float(o['duration_tolerance']):g} % whatever its floor, so "
        "where the floor is near that, the check sits at the full model's own spread); ✗ "
        "marks a failed check. The row `exact` is the chain driven by the exact lumped psi: the psi of "
        "cells adapted to their current input (moving cells are not adapted, so a psi learned "
        "from the full model's transitions can pass checks it fails)."
        + (
            f" With `fidelity.chain_repeats={o['chain_repeats']}`, each abstraction ran that "
            f"many times per field from other seeds: `runs` gives the share of its runs that "
            f"pass each KS check, and its means' average error and their sd from one run to "
            f"the next (the check reads the first run). Every run is compared with the one "
            f"full-model run, so the shares carry that run's own draw too; another "
            f"`fidelity.sim_seed` draws the whole check again (full model, floor and chains)."
            if int(o.get("chain_repeats", 1)) > 1
            else ""
        )
        + "\n\n"
        + format_markdown_table(pd.DataFrame(rows))
    )
    diag_rows = []
    classes = summary.get("class_diagnostics") or {}
    for label, d in (summary.get("diagnostics") or {}).items():
        if not d:
            continue
        for p in (0, 1):
            s = d.get(f"phi{p}")
            if not s:
                continue
            row = {"abstraction": label, "leaving": settings.setup.model.internal.lump_names[p],
                   "bias": f"{100 * s['rel_bias']:+.1f} %",
                   "mean abs. rel. error": f"{100 * s['mean_abs_rel_error']:.1f} %"}  # fmt: skip
            k = (classes.get(label) or {}).get(f"phi{p}")
            if k:
                se = f" +- {100 * k['rel_bias_se']:.1f} %" if "rel_bias_se" in k else ""
                row["K-lumps chain, class-weighted bias"] = f"{100 * k['rel_bias']:+.1f} %{se}"
            diag_rows.append(row)
    diag = ("The learned switching probabilities against the reference where the population "
            "lives (train_metrics.json of each abstraction): the two-state psi's, and for a "
            "K-lumps chain its classes' switching out of each lump weighted by the population's "
            "class shares (what it simulates, if its class shares stay the population's).\n\n"
            + (format_markdown_table(pd.DataFrame(diag_rows)) if diag_rows else "none"))  # fmt: skip
    outside = summary.get("outside_training") or {}
    support = (
        "The share of each run's cell-steps (sampled every few steps) whose abstraction inputs "
        "lay outside the range its training data covered (each input's min and max over the "
        "training rows; the lookup clamps there, so those steps use the psi at the edge), and "
        "inside it in a bin where the training rows are sparse (the fit's histogram; `not "
        "stored` for an older fit).\n\n"
        + format_markdown_table(pd.DataFrame([
            {"run": label, "outside": f"{100 * r['share_outside']:.2f} %",
             "sparse": ("not stored" if sparse_share(r) is None else
                        f"{100 * float(r['share_sparse']):.2f} % (most at "
                        f"{describe_sparse_where(r)})"),
             "inputs": "; ".join(
                 f"{n} seen [{v['seen'][0]:.3g}, {v['seen'][1]:.3g}], trained "
                 f"[{v['trained'][0]:.3g}, {v['trained'][1]:.3g}]"
                 for n, v in r["inputs"].items())}
            for label, r in outside.items()]))
        if outside else "No learned run.")  # fmt: skip
    wider = summary.get("wider_collection")
    if wider:
        support += (f"\n\nRuns left the inputs their collection covered: the same command with "
                    f"`{' '.join(wider)}` (checked) collects where they go, collect's jumps "
                    f"twice as far from the field's peak.")  # fmt: skip
    settled = summary.get("settled_collection")
    if settled:
        kept = summary.get("settled_kept")
        learnt = ("and psi learns that lag" if kept is None else
                  f"and the fits left those rows out, reading {kept:.0%} of the rows")  # fmt: skip
        target += (f"\n\nThe training collections' rows switched at other rates soon after a "
                   f"jump than once it had settled (collect's warning, the `after_jump` of its "
                   f"manifest), {learnt}: the same command with `{' '.join(settled)}` "
                   f"(checked) records rows only once a jump has settled"
                   f"{'' if kept is None else ', as many as the collection asks for'}, a new "
                   f"collection and new fits (docs/choice.md, \"The lag without the clock\").")  # fmt: skip
    wider = summary.get("wider_choice")
    if wider:
        target += (f"\n\nThe chains were chosen by measurement (`gp=auto`): the same command "
                   f"with `{' '.join(wider)}` (checked) widens or sharpens that choice (more "
                   f"candidates, or more held-out cells where it was a tie), which measures "
                   f"them against the rest again (docs/choice.md, \"The verdict's remedies "
                   f"under a measured choice\").")  # fmt: skip
    if summary.get(PREVIOUS):
        target += "\n\n" + describe_previous(summary[PREVIOUS], summary["checks"])
    if summary.get("not_advised"):
        target += "\n\n" + describe_not_advised(summary["not_advised"])
    again = summary.get("draw_again")
    if again:
        target += (f"\n\nTo tell a miss the draw decides from one the abstraction decides: the "
                   f"same command with `{' '.join(again)}` (checked) draws the full model, its "
                   f"floor and every chain again on the same collections and fits (only the "
                   f"simulations run again); a miss that stays in the same check is the "
                   f"abstraction's (docs/choice.md, \"Seed 0's L2 `high` is its fit's\").")  # fmt: skip
    return [
        ("Setting", setting),
        ("The target", target),
        ("The learned psi where cells live", diag),
        ("Inputs outside the training data", support),
    ]


def plot_ks(table: pd.DataFrame, settings: FidelitySettings) -> Any:
    """KS distance against time per field: every candidate, the noise floor (the second full
    run against the full run) and the threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fields = list(settings.fields)
    fig, axes = plt.subplots(1, len(fields), figsize=(4 * len(fields), 3.6), sharey=True,
                             constrained_layout=True, squeeze=False)  # fmt: skip
    observed = f"{settings.setup.model.body.observable_names[0]}_t"
    dist = table[table["quantity"].str.startswith(observed)].copy()
    dist["t"] = dist["quantity"].str.replace(observed, "").astype(float)
    for ax, name in zip(axes[0], fields, strict=True):
        g = dist[dist["field"] == name]
        floor = g.groupby("t")["noise_floor"].first()
        ax.plot(floor.index, floor.values, marker="o", color="k", ls="--", label="noise floor")
        for cand, h in g.groupby("candidate", sort=False):
            style = {"exact": ("grey", ":")}.get(cand, (None, "-"))
            ax.plot(h["t"], h["value"], marker="o", color=style[0], ls=style[1], label=cand)
        thr = g.groupby("t")["threshold"].max()
        ax.plot(thr.index, thr.values, color="red", lw=1, label="threshold")
        ax.set_title(name)
        ax.set_xlabel("t (s)")
    axes[0][0].set_ylabel("KS distance vs full model")
    axes[0][-1].legend(fontsize=7)
    return fig


def plot_drift(mean_observable: Mapping[str, Mapping[str, list[float]]],
               settings: FidelitySettings) -> Any:  # fmt: skip
    """The drift per field: every run's mean observable minus the full model's, against time,
    on the full model's noise band (the 95 % range of a second run's mean, +- 1.96 sqrt(2)
    s.e., around 0), with the second full run, so a gap (or its absence) is seen at a glance.

    Args:
        mean_observable: ``{"<run>|<field>": {"<t>": [mean, s.e.]}}`` (the summary's).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from surrogate.evaluate.figures import drift_band

    fields = list(settings.fields)
    fig, axes = plt.subplots(1, len(fields), figsize=(4 * len(fields), 3.8), sharey=True,
                             constrained_layout=True, squeeze=False)  # fmt: skip
    name = settings.setup.model.body.observable_names[0]
    for ax, field in zip(axes[0], fields, strict=True):
        runs = {k.split("|")[0]: v for k, v in mean_observable.items() if k.endswith(f"|{field}")}
        full = runs.pop("full")
        t = [float(k) for k in full]
        drift_band(ax, np.array(t), np.array([se for _, se in full.values()]),
                   "full model's noise band (95 %)")  # fmt: skip
        for label, series in runs.items():
            style = {"full_repeat": ("k", "--"), "exact": ("grey", ":")}.get(label, (None, "-"))
            gap = [series[k][0] - full[k][0] for k in full]
            ax.plot(t, gap, marker=".", color=style[0], ls=style[1], label=label)
        ax.set_title(field)
        ax.set_xlabel("t (s)")
    axes[0][0].set_ylabel(f"mean {name} minus the full model's")
    axes[0][-1].legend(fontsize=7)
    return fig


__all__ = ["FidelitySettings", "RunResult", "check", "plot_drift", "run", "validate"]
