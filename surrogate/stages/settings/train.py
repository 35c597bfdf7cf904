"""Settings of the train stage: transitions (collected or an external table) -> the two GP
classifiers of the abstraction (the fit), its diagnostic and its output grid."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from surrogate.config import grid_size, non_negative, positive, to_dict, validate_start
from surrogate.errors import ConfigError
from surrogate.gp.class_relaxation import DEFAULT_CELLS, DEFAULT_LAGS
from surrogate.gp.classes import DEFAULT_MAX_LABEL_WEIGHT
from surrogate.gp.training import GPSettings
from surrogate.io import artefact_dir
from surrogate.kinds import (
    DEFAULT_MEAN,
    FIT_GP_KEYS,
    JUMP_ROWS,
    TWO_STATE,
    ChainKind,
    fit_chain,
    is_auto,
    kind_gp_keys,
    resolve_auto_lumps,
)
from surrogate.models.capabilities import start_size_of
from surrogate.stages.settings.choice import (
    DEFAULTS,
    ChoiceSettings,
    PendingChoice,
    candidate_groups,
    collecting_pending,
    pending,
    stored_choice,
)
from surrogate.stages.settings.collect import CollectSettings
from surrogate.stages.settings.common import (
    TRAIN_CMD,
    Job,
    ModelSetup,
    command_line,
    group_overrides,
)
from surrogate.stages.settings.occupancy import OccupancySettings
from surrogate.validation import known_keys

#: keys of the gp group that are not GP hyperparameters (nor are the chain kinds' own,
#: :func:`~surrogate.kinds.kind_gp_keys`)
GP_EXTRA = (*FIT_GP_KEYS, "history", "max_age", "clock_bins", "lumps", "min_events",
            "max_label_weight", "class_moves", "relaxation", "choice")  # fmt: skip
#: keys of the gp group that the train stage reads after the fit (its diagnostic and output
#: grid): they change neither a candidate's fit nor its score, so a measured choice is made
#: without them and gp=auto's chosen candidate takes the job's own
GP_AFTER_FIT = ("grid_size", "diagnostic")
#: keys of the gp group that do not change the fit (the diagnostic and the output grid), or
#: enter its identity resolved (threads: null means the job's count)
GP_NOT_FIT = (*GP_AFTER_FIT, "threads")
#: auto_recipe's prefix where gp=auto is a measured choice's candidate
MEASURED = "measured"
#: gp.labels: the column each option trains on (auto: expected where the table has them)
LABEL_COLUMNS = {"outcome": "phi_next", "expected": "phi_next_expected"}
LABEL_CHOICES = ("auto", *LABEL_COLUMNS)
DIAGNOSTIC_DEFAULTS: dict[str, Any] = {
    "n_cells": 1000,
    "t_end": 100.0,
    "record_every": 10,  # as conf/gp/svgp.yaml
    "start": [2.0, 0.0],
    "equilibration_time": 10.0,
    # where the reference is too noisy to judge psi's bias, the diagnostic is made again with
    # the cells that judge it, up to this many (0: never; surrogate.stages.train.grown_diagnostic)
    "max_cells": 8000,
}


def bins_labels_conflict(labels: str) -> str:
    """Why ``gp.bins=0`` cannot train on the expected labels ``gp.labels=<labels>`` picks."""
    picks = "trains on" if labels == "expected" else "picks, where the table has them,"
    return (f"gp.labels={labels} {picks} the expected labels (fractions), which need binned "
            f"training, but gp.bins=0 (minibatch training) takes 0/1 outcomes only; set "
            f"gp.bins > 0 (default 500) or gp.labels=outcome")  # fmt: skip


def _check_labels(
    gp_config: Mapping[str, Any], source: CollectSettings | ExternalTable, model_name: str
) -> None:
    """Refuse a ``gp.labels`` that ``gp_config``'s training cannot read from ``source``: an
    unknown one, expected labels with minibatches (``gp.bins=0``; found here, not after the
    collection), or ``expected`` where the collection records none."""
    labels = gp_config.get("labels", "outcome")
    if labels not in LABEL_CHOICES:
        raise ConfigError(f"gp.labels must be one of {list(LABEL_CHOICES)}, got {labels!r}")
    expected = isinstance(source, CollectSettings) and source.expected_labels
    if not gp_config.get("bins") and (labels == "expected" or (labels == "auto" and expected)):
        raise ConfigError(bins_labels_conflict(labels))  # minibatches read 0/1 labels only
    if not gp_config.get("bins") and isinstance(source, CollectSettings) and source.keep_switches:
        raise ConfigError("collect.keep_switches=true weights each row by the windows it stands "
                          "for, which binned training reads; gp.bins=0 (minibatches) counts "
                          "each row once: set gp.bins > 0 or collect.keep_switches=false")  # fmt: skip
    if labels == "expected" and isinstance(source, CollectSettings) and not expected:
        why = (
            "collect.expected_labels=false"
            if not source.options.get("expected_labels", False)
            else "collect.keep_switches=true records none"
            if source.keep_switches
            else f"model {model_name!r} gives none (no expected_phi_next)"
        )
        raise ConfigError(
            f"gp.labels=expected trains on expected labels, but {why}; use gp.labels=outcome"
        )


@dataclass(frozen=True)
class ExternalTable:
    """A transitions table from outside the pipeline (CSV or Parquet), identified by content."""

    path: Path
    sha256: str

    @classmethod
    def from_path(cls, path: str | Path) -> ExternalTable:
        """Hash the file (its content defines what is trained on)."""
        p = Path(path).expanduser().resolve()
        if not p.is_file():
            raise ConfigError(f"transitions={path}: no such file")
        if p.suffix.lower() not in (".csv", ".parquet", ".pq"):
            raise ConfigError(f"transitions={path}: expected a .csv or .parquet table")
        digest = hashlib.sha256()
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                digest.update(chunk)
        return cls(p, digest.hexdigest())


@dataclass(frozen=True, eq=False)
class TrainSettings:
    """The train stage: transitions -> the two GP classifiers of the abstraction (the fit,
    ``data/fit/``: what simulations use), and the train directory around it (``data/train/``:
    the fit's files, its diagnostic where the population lives and its output grid).

    ``fit_threads`` is the fit's torch thread count resolved when the settings are made
    (``gp.threads``, else this process's count): the fit's result depends on it.
    """

    setup: ModelSetup
    source: CollectSettings | ExternalTable
    gp: GPSettings
    gp_config: dict[str, Any]
    inputs: tuple[str, ...]
    grid_size: tuple[int, ...] | None
    diagnostic: dict[str, Any]
    job: Job
    fit_threads: int
    #: the chain (gp.lumps, gp.history, gp.class_moves as a kind, :mod:`surrogate.kinds`):
    #: the two-state chain, the switch clock (psi also over the clock, its last input) or K
    #: lumps (also the chain over the model's classes, :mod:`surrogate.gp.classes`)
    kind: ChainKind = TWO_STATE
    #: gp.max_age: the switch clock's cap (s)
    max_age: float = 5.0
    #: gp.min_events: events a destination of the K-lumps chain needs for a GP surface (None:
    #: by the labels, :data:`surrogate.gp.classes.MIN_EVENTS`)
    min_events: float | None = None
    #: gp.max_label_weight: the most draws one expected label counts as in the K-lumps chain's
    #: GPs (:func:`surrogate.gp.training.label_weight`; 1: as a 0/1 outcome)
    max_label_weight: float = DEFAULT_MAX_LABEL_WEIGHT
    #: gp.relaxation: the stationary sample's cells and lags (s), for class_moves=relaxation
    relaxation_cells: int = DEFAULT_CELLS
    relaxation_lags: tuple[float, ...] = DEFAULT_LAGS
    #: what gp.lumps=auto chose: the rule's recipe (``classes`` or ``svgp``), or
    #: ``measured: <choice directory>`` (the measured choice's candidate); None where a chain
    #: was named
    auto_recipe: str | None = None
    #: the measured choice's directory where gp=auto is its chosen candidate (auto_recipe:
    #: ``measured: <candidate>``)
    choice_directory: Path | None = None

    @classmethod
    def from_config(
        cls, cfg: Mapping[str, Any], setup: ModelSetup | None = None, job: Job | None = None
    ) -> TrainSettings:
        """Validate the gp group; the data is collected with ``cfg`` or read from
        ``transitions`` (an external table).

        Args:
            cfg: The job's config (its ``gp``, ``collect`` and ``transitions``).
            setup: The model setup, built once at the stage's entry (None: built from ``cfg``;
                a run's abstraction passes its own, in the training field).
            job: The job, likewise (a run's abstraction: on the fit's device).
        """
        external = cfg.get("transitions")
        if external:
            setup = ModelSetup.from_config(cfg) if setup is None else setup
            job = Job.from_config(cfg) if job is None else job
            source: CollectSettings | ExternalTable = ExternalTable.from_path(str(external))
        else:
            source = CollectSettings.from_config(cfg, setup, job, fits=cls.design_fits)
            setup, job = source.setup, source.job
        return cls._build(setup, source, job, to_dict(cfg["gp"]))

    @classmethod
    def design_fits(cls, source: CollectSettings, gp: dict[str, Any]) -> TrainSettings:
        """The fits of a sequential design's rounds: ``gp`` (the group as given) on the
        collection ``source`` (without its design), with its setup and job; ``gp=auto``
        measuring resolves by the rule here (the choice needs the collection the design makes)."""
        with collecting_pending():
            return cls._build(source.setup, source, source.job, gp)

    @classmethod
    def _build(
        cls,
        setup: ModelSetup,
        source: CollectSettings | ExternalTable,
        job: Job,
        raw_gp: dict[str, Any],
    ) -> TrainSettings:
        """The settings of a fit of ``raw_gp`` (the gp group as given) on ``source``: with
        ``gp=auto`` measuring (``gp.choice.by=measure``, the default) on a collection, the
        stored choice's candidate (:func:`_measured`), or the rule's chain while the choice is
        pending."""
        measured = _measured(cls, setup, source, job, raw_gp)
        if measured is not None:
            return measured
        gp_config = resolve_auto_lumps(
            {k: v for k, v in raw_gp.items() if k != "choice"}, setup.model
        )
        extra = {*GP_EXTRA, *kind_gp_keys()}  # a chain kind's own keys are no hyperparameters
        hyper = {k: v for k, v in gp_config.items() if k not in extra}
        # the labels first: gp.bins=0 with expected labels is refused whatever the optimiser
        # (Newton, K lumps' recipe, needs bins too, and its own advice would not run)
        _check_labels(gp_config, source, setup.model.name)
        jump_rows = gp_config.get("jump_rows", JUMP_ROWS[0])
        if jump_rows not in JUMP_ROWS:
            raise ConfigError(f"gp.jump_rows must be one of {list(JUMP_ROWS)}, got "
                              f"{jump_rows!r} (auto: the rows soon after a jump left out where "
                              f"collect measured them lagging)")  # fmt: skip
        gp = GPSettings.from_config({**hyper, "seed": setup.seed})
        # the stage reports held-out metrics, so it needs a validation split (GPSettings allows 0)
        if not 0.0 < gp.validation_fraction < 1.0:
            raise ConfigError(
                f"gp.validation_fraction must lie in (0, 1) for the train stage (it reports "
                f"held-out metrics), got {gp.validation_fraction!r}"
            )
        inputs = setup.model.abstraction_inputs(gp_config.get("inputs"))
        chain = fit_chain(gp_config, gp, inputs, setup.model.internal, setup.model.name)
        gp, inputs = chain.gp, chain.inputs  # a switch clock: psi's last input, its own bins
        if isinstance(source, CollectSettings):
            n_per_state = source.options["n_per_state"]
            n_train = n_per_state - round(gp.validation_fraction * n_per_state)
            if gp.n_inducing > n_train:
                raise ConfigError(
                    f"gp.n_inducing={gp.n_inducing} exceeds the {n_train} training points per "
                    f"classifier (collect.n_per_state={n_per_state} minus the validation "
                    f"split); lower gp.n_inducing or raise collect.n_per_state"
                )
        sizes = grid_size(gp_config.get("grid_size"), "gp.grid_size", len(inputs))
        diagnostic = _diagnostic(gp_config.get("diagnostic") or {}, start_size_of(setup.model.body))
        threads = gp_config.get("threads")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int)
                                    or threads < 1):  # fmt: skip
            raise ConfigError(f"gp.threads must be a positive integer or null, got {threads!r}")
        # gp.lumps=auto: the recipe it chose, for the log
        auto_recipe = chain.kind.recipe if is_auto(raw_gp) else None
        return cls(setup, source, gp, gp_config, inputs, sizes, diagnostic, job,
                   int(threads) if threads is not None else torch.get_num_threads(), chain.kind,
                   chain.max_age, chain.min_events, chain.max_label_weight, chain.relaxation_cells,
                   chain.relaxation_lags, auto_recipe)  # fmt: skip

    def input_warps(self) -> dict[str, float]:
        """The inputs psi reads on a log axis (name -> knee, s): the kind's
        (:meth:`~surrogate.kinds.base.ChainKind.input_warps`; a clock with ``gp.clock_knee``)."""
        return self.kind.input_warps(self.gp_config)

    def measured_choice(self) -> Path | None:
        """The directory of the measured choice that made these settings (``gp=auto``), or
        None."""
        return self.choice_directory

    @property
    def lumps(self) -> str:
        """gp.lumps: phi (the two-state chain and the clock) | classes (K lumps)."""
        return self.kind.lumps

    @property
    def history(self) -> str:
        """gp.history: none | age (psi also over the switch clock)."""
        return self.kind.history

    @property
    def class_moves(self) -> str:
        """gp.class_moves: learned (every class move from the windows) | relaxation (bins of a
        slow count relax to their stationary law, :mod:`surrogate.gp.class_relaxation`)."""
        return self.kind.class_moves

    def check_label_column(self, column: str, where: str) -> None:
        """Refuse training ``where``'s expected labels (``column``, e.g. an external table's,
        picked by ``gp.labels=auto``) with minibatch training (``gp.bins=0``)."""
        if column == LABEL_COLUMNS["expected"] and not self.gp.bins:
            labels = self.gp_config.get("labels", "outcome")
            raise ConfigError(f"{where} has expected labels: {bins_labels_conflict(labels)}")

    @property
    def jump_rows(self) -> str:
        """gp.jump_rows: auto | keep | drop (the rows soon after a jump, :data:`JUMP_ROWS`)."""
        return str(self.gp_config.get("jump_rows", JUMP_ROWS[0]))

    def label_column(self, columns: Sequence[str]) -> str:
        """The column of a transitions table (with ``columns``) the classifiers are trained on
        (``gp.labels``; ``auto``: the expected labels where the table has them, as collect
        records them for models that give them; else the outcomes)."""
        labels = self.gp_config.get("labels", "outcome")
        if labels == "auto":
            expected = LABEL_COLUMNS["expected"]
            return expected if expected in columns else LABEL_COLUMNS["outcome"]
        return LABEL_COLUMNS[labels]

    @property
    def seed(self) -> int:
        """The seed of the collection and of the training."""
        return self.setup.seed

    def fit_identity(self) -> dict[str, Any]:
        """Everything that defines the fitted classifiers: the data, the GP settings, the fit's
        thread count (float reductions) and device type; not the diagnostic or the grid."""
        if isinstance(self.source, CollectSettings):
            # the bins where the rows leave them to train (the rows' identity has none)
            data = {**self.source.identity(), **self.source.bins_identity()}
        else:
            data = {"table": str(self.source.path), "sha256": self.source.sha256,
                    "model": self.setup.model_config, "seed": self.setup.seed}  # fmt: skip
        # each kind keeps its keys only: older kinds' fits keep the identities they had
        gp = self.kind.fit_identity({k: v for k, v in self.gp_config.items() if k not in GP_NOT_FIT},
                                    self.min_events, self.max_label_weight,
                                    self.relaxation_cells, self.relaxation_lags)  # fmt: skip
        return {**data, "gp": gp, "inputs": list(self.inputs), "fit_threads": self.fit_threads,
                "device": self.job.device_type}  # fmt: skip

    def identity(self) -> dict[str, Any]:
        """Everything that defines the train directory: the fit, the diagnostic's settings
        and the output grid (a change in either re-runs them around the same fit)."""
        sizes = list(self.grid_size) if self.grid_size is not None else None
        return {"fit": self.fit_identity(), "grid_size": sizes, "diagnostic": self.diagnostic}

    def _label(self) -> dict[str, Any]:
        label = (self.setup.label() if isinstance(self.source, CollectSettings)
                 else {"table": self.source.path.stem})  # fmt: skip
        return {**label, "inputs": "+".join(self.inputs), "kernel": self.gp.kernel,
                "inducing": self.gp.n_inducing, **self.kind.label(),
                **({} if self.gp.mean == DEFAULT_MEAN else {"mean": self.gp.mean}),
                "seed": self.seed}  # fmt: skip

    @functools.cached_property
    def fit_directory(self) -> Path:
        """``data/fit/model=..._field=..._dt=..._inputs=..._kernel=..._seed=...-<hash>``: the
        classifiers the simulations use."""
        return artefact_dir(self.job.data_dir, "fit", self._label(), self.fit_identity())

    @functools.cached_property
    def directory(self) -> Path:
        """``data/train/model=..._field=..._dt=..._inputs=..._kernel=..._seed=...-<hash>``."""
        return artefact_dir(self.job.data_dir, "train", self._label(), self.identity())

    def gp_overrides(self) -> list[str]:
        """The gp overrides that reproduce these settings (``gp.threads`` as resolved: a
        command run with another thread count would make another fit)."""
        # the recipe named: the default (gp=auto) would choose K lumps for a model with classes
        return group_overrides("gp", {**self.gp_config, "threads": self.fit_threads},
                               self.kind.recipe)  # fmt: skip

    def command(self) -> str:
        """The command that makes this artefact (and the fit)."""
        if isinstance(self.source, CollectSettings):
            data = [*self.setup.overrides(), *self.source._overrides()]
        else:
            data = [f"transitions={self.source.path}", *self.setup.overrides()]
        return command_line(TRAIN_CMD, data, self.gp_overrides(), self.job.device_overrides())

    @property
    def collected(self) -> bool:
        """Whether the transitions are collect's (not an external table)."""
        return isinstance(self.source, CollectSettings)

    def input_command(self) -> str:
        """The command that makes this stage's input (the collected transitions)."""
        if isinstance(self.source, CollectSettings):
            return self.source.command()
        return f"(the external table {self.source.path})"

    def occupancy(self) -> OccupancySettings:
        """The diagnostic's occupancy run: an unperturbed full-model population in the training
        field (``gp.diagnostic``: its size, start and length), seeded with this seed."""
        # its cells' ceiling is the train stage's, not the run's (a stored run is reused)
        options = {k: v for k, v in self.diagnostic.items() if k != "max_cells"}
        if self.kind.clock:  # the rows need the switch clocks
            options["clock"] = True
        return OccupancySettings(self.setup, options, self.job, self.command())


def _measured(
    cls: type[TrainSettings],
    setup: ModelSetup,
    source: CollectSettings | ExternalTable,
    job: Job,
    raw_gp: dict[str, Any],
) -> TrainSettings | None:
    """``gp=auto``'s settings where it measures: the chosen candidate's train settings where
    the choice of this collection is stored; None where the rule resolves it (``gp.choice.by=
    rule``, a named chain, an external table: no full model to hold out) or the choice is
    pending (:func:`~surrogate.stages.settings.choice.pending`: recorded while an entry checks
    its settings, refused elsewhere, naming the command that makes it)."""
    if not is_auto(raw_gp):  # a chain named (gp.lumps=phi under gp=auto: experiment=paper)
        return None
    choice = ChoiceSettings.from_config(raw_gp.get("choice"))
    if choice.by != "measure" or not isinstance(source, CollectSettings):
        return None
    choice.check_windows(setup.dt)
    groups = candidate_groups(raw_gp, choice, setup.model.internal)
    finals = groups if not choice.refit else candidate_groups(raw_gp, choice, setup.model.internal,
                                                              scoring=False)  # fmt: skip
    candidates = {name: cls._build(setup, source, job, gp) for name, gp in groups.items()}
    identity = {"candidates": {n: t.fit_identity() for n, t in candidates.items()},
                "choice": choice.identity(), "seed": setup.seed}  # fmt: skip
    if finals is not groups:
        # the record names the chosen's recipe group, which gp=auto then trains: a recipe
        # changed since (the clock's epochs) makes another choice, not the old group's fit;
        # the keys read after the fit do not (the verdict's gp.diagnostic.n_cells=N reuses it)
        identity["recipes"] = {n: {k: v for k, v in g.items() if k not in GP_AFTER_FIT}
                               for n, g in finals.items() if g != groups.get(n)}  # fmt: skip
    made_by = command_line(TRAIN_CMD, [*setup.overrides(), *source._overrides()],
                           _choice_overrides(raw_gp), job.device_overrides())  # fmt: skip
    directory = artefact_dir(job.data_dir, "choice", {"model": setup.model.name}, identity)
    plan = PendingChoice(choice, candidates, directory, groups,
                         make=lambda gp: cls._build(setup, source, job, gp), finals=finals,
                         made_by=made_by)  # fmt: skip
    stored = stored_choice(plan)
    if stored is None:
        pending(plan)
        return None
    chosen, gp = stored
    # the record's group: the candidate refitted with its recipe's optimiser (gp.choice.refit),
    # or as scored, or a clock the choice added; its diagnostic and grid this job's
    gp = {**gp, **{k: raw_gp[k] for k in GP_AFTER_FIT if k in raw_gp}}
    settings = cls._build(setup, source, job, gp)
    return dataclasses.replace(settings, auto_recipe=f"{MEASURED}: {chosen}",
                               choice_directory=plan.directory)  # fmt: skip


def _choice_overrides(raw_gp: Mapping[str, Any]) -> list[str]:
    """``gp=auto`` and the ``gp.choice`` keys that differ from conf/gp/auto.yaml's (what the
    command that makes a measured choice needs)."""
    default = {**DEFAULTS, "by": "measure"}
    given = raw_gp.get("choice") or {}
    return ["gp=auto", *(f"gp.choice.{k}={_override_value(v)}" for k, v in given.items()
                         if k in default and default[k] != v)]  # fmt: skip


def _override_value(value: Any) -> str:
    """A value as a Hydra override writes it (lists without spaces)."""
    if isinstance(value, list | tuple):
        return "[" + ",".join(_override_value(v) for v in value) + "]"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _diagnostic(options: Mapping[str, Any], start_size: int | None) -> dict[str, Any]:
    d = {**DIAGNOSTIC_DEFAULTS,
         **known_keys(options, sorted(DIAGNOSTIC_DEFAULTS), "gp.diagnostic")}  # fmt: skip
    positive(d, "n_cells", "gp.diagnostic.", integer=True)
    positive(d, "t_end", "gp.diagnostic.")
    positive(d, "record_every", "gp.diagnostic.", integer=True)
    non_negative(d, "equilibration_time", "gp.diagnostic.")
    if non_negative(d, "max_cells", "gp.diagnostic.") != int(d["max_cells"]):
        raise ConfigError(f"gp.diagnostic.max_cells must be a whole number of cells (0: the "
                          f"diagnostic never grows), got {d['max_cells']!r}")  # fmt: skip
    d["start"] = list(validate_start(d, "start", "gp.diagnostic.", start_size))
    return d
