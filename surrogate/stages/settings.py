"""Typed settings of every stage, built once from a Hydra config at the stage's edge.

Each settings object validates its part of the config on construction (so a bad setting is
refused by name before any work starts), builds the objects the stage needs (model, field, GP
settings) and knows, in one place, its artefact directory (a function of its ``identity``:
exactly the settings that change the output, including ones that change the random stream such
as ``compile``) and the command that makes it. Stages receive these objects, never raw configs.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from surrogate.config import (
    build_field,
    build_model,
    field_config,
    field_name,
    grid_size,
    group_config,
    group_options,
    non_negative,
    positive,
    resolve_device,
    seed_setting,
    to_dict,
    validate_start,
)
from surrogate.errors import ConfigError
from surrogate.fields import Field
from surrogate.gp.training import GPSettings
from surrogate.io import artefact_dir
from surrogate.models.base import Model, has_exact_psi
from surrogate.simulate.memory import AGE, can_age, history_setting
from surrogate.simulate.recorders import DEFAULT_RECORD_CELLS

COLLECT_CMD = "python scripts/collect.py"
TRAIN_CMD = "python scripts/train.py"
SIMULATE_CMD = "python scripts/simulate.py"
EVALUATE_CMD = "python scripts/evaluate.py"
REPRODUCE_CMD = "python scripts/reproduce.py"

DECISIONS = ("full", "abstract", "exact")
DECISION_MODES = {"abstract": ("lookup", "classifier"), "exact": ("lookup", "direct")}
#: keys of the gp group that are not GP hyperparameters
GP_EXTRA = ("inputs", "grid_size", "diagnostic", "threads", "labels", "history", "max_age",
            "clock_bins")  # fmt: skip
#: keys of the gp group that only a fit with a switch clock reads (gp.history=age)
GP_CLOCK = ("history", "max_age", "clock_bins")
#: keys of the gp group that do not change the fit (the diagnostic and the output grid), or
#: enter its identity resolved (threads: null means the job's count)
GP_NOT_FIT = ("grid_size", "diagnostic", "threads")
#: gp.labels: the column each option trains on (auto: expected where the table has them)
LABEL_COLUMNS = {"outcome": "phi_next", "expected": "phi_next_expected"}
LABEL_CHOICES = ("auto", *LABEL_COLUMNS)
DIAGNOSTIC_DEFAULTS: dict[str, Any] = {
    "n_cells": 1000,
    "t_end": 100.0,
    "record_every": 10,  # as conf/gp/svgp.yaml
    "start": [2.0, 0.0],
    "equilibration_time": 10.0,
}
#: bytes of device memory per simulated cell, measured at ~690 B for the E. coli abstraction
#: (1e6 cells in 689 MiB); the estimate is generous (recorders, the full model's motors)
BYTES_PER_CELL = 4096


# ----------------------------------------------------------------------------------------------
# commands: the overrides that reproduce a setting, relative to the shipped defaults


def _flatten(prefix: str, value: Any) -> dict[str, Any]:
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(f"{prefix}.{k}", v))
        return out
    return {prefix: value}


def _fmt(value: Any) -> str:
    if isinstance(value, list | tuple):
        return "[" + ",".join(_fmt(v) for v in value) + "]"
    if isinstance(value, bool):
        return str(value).lower()
    if value is None:
        return "null"
    return repr(value) if isinstance(value, float) else str(value)


def group_overrides(group: str, value: Mapping[str, Any], choice: str | None = None) -> list[str]:
    """Command-line overrides that select ``value`` for config ``group``: the shipped option it
    is based on (``choice``, or the one with the same ``_target_``) plus every key that differs."""
    value = to_dict(value)
    if choice is None:
        for name in group_options(group):
            if group_config(group, name).get("_target_") == value.get("_target_"):
                choice = name
                break
    base = group_config(group, choice) if choice else {}
    want, have = _flatten(group, value), _flatten(group, base)
    out = [f"{group}={choice}"] if choice else []
    for key, v in want.items():
        if key not in have:
            out.append(f"+{key}={_fmt(v)}")
        elif have[key] != v:
            out.append(f"{key}={_fmt(v)}")
    return out


def _command(script: str, *parts: list[str]) -> str:
    return " ".join([script, *[p for part in parts for p in part]])


# ----------------------------------------------------------------------------------------------
# building blocks


@dataclass(frozen=True)
class Job:
    """Settings of a job: where artefacts go, device, progress. Only the device type changes a
    result (:attr:`device_type`, in the identities)."""

    data_dir: Path
    device: torch.device
    progress: bool

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> Job:
        """Validated job settings."""
        return cls(
            Path(str(cfg.get("data_dir", "data"))),
            resolve_device(cfg.get("device", "cpu")),
            bool(cfg.get("progress", True)),
        )

    @property
    def device_type(self) -> str:
        """``cpu`` or ``cuda``: part of the identity of everything that draws random numbers
        (CPU and CUDA generators give different streams from one seed; any one CUDA device
        gives the same)."""
        return self.device.type


@dataclass(frozen=True, eq=False)
class ModelSetup:
    """The agent model, the field, the time step and the seed of a run, built and checked."""

    model_config: dict[str, Any]
    field_config: dict[str, Any]
    model: Model
    field: Field
    dt: float
    seed: int

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> ModelSetup:
        """Validate dt and seed, build the model (with its own checks of dt) and the field."""
        dt = float(positive(cfg, "dt"))
        seed = seed_setting(cfg)
        model_config, field_cfg = to_dict(cfg["model"]), to_dict(cfg["field"])
        model = build_model(model_config)
        model.validate(dt)
        return cls(model_config, field_cfg, model, build_field(field_cfg), dt, seed)

    @property
    def field_name(self) -> str:
        """Short name of the field (the shipped config it equals, else its class)."""
        return field_name(self.field_config)

    def identity(self) -> dict[str, Any]:
        """What of these settings defines an artefact (with the digests of the files the
        model is read from, where it reads any)."""
        out = {"model": self.model_config, "field": self.field_config, "dt": self.dt,
               "seed": self.seed}  # fmt: skip
        sources = self.model.sources()
        return {**out, "model_sources": sources} if sources else out

    def label(self) -> dict[str, Any]:
        """Readable part of a directory name."""
        return {"model": self.model.name, "field": self.field_name, "dt": self.dt}

    def overrides(self) -> list[str]:
        """Overrides that reproduce these settings."""
        return [
            *group_overrides("model", self.model_config),
            *group_overrides("field", self.field_config, self._field_choice()),
            f"dt={self.dt:g}",
            f"seed={self.seed}",
        ]

    def _field_choice(self) -> str | None:
        name = self.field_name
        return name if name in group_options("field") else None

    def with_field(self, field_cfg: Mapping[str, Any]) -> ModelSetup:
        """The same setup in another field."""
        cfg = to_dict(field_cfg)
        return ModelSetup(self.model_config, cfg, self.model, build_field(cfg), self.dt, self.seed)

    def with_seed(self, seed: int) -> ModelSetup:
        """The same setup with another seed."""
        return ModelSetup(self.model_config, self.field_config, self.model, self.field, self.dt,
                          int(seed))  # fmt: skip


# ----------------------------------------------------------------------------------------------
# collect


@dataclass(frozen=True, eq=False)
class CollectSettings:
    """The collect stage: perturbed full-model runs -> transitions table."""

    setup: ModelSetup
    options: dict[str, Any]
    job: Job
    #: the collect settings as given (null: the model's default budget), for the command
    given: dict[str, Any] | None = None
    #: the fits of a sequential design (``collect.design.target_error`` set), else None
    design: TrainSettings | None = None

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> CollectSettings:
        """Validate the collect group (and the model's perturbation options); the budget left
        null (``n_per_state``, ``n_cells``, ``record_every``) is the model's default, which
        fits its cost (``Model.collect_defaults``)."""
        setup = ModelSetup.from_config(cfg)
        given = to_dict(cfg["collect"])
        c = dict(given)
        defaults = setup.model.collect_defaults(setup.dt)
        for key in ("n_per_state", "n_cells", "record_every"):
            if c.get(key) is None:
                c[key] = defaults[key]
        for key in ("n_per_state", "n_cells", "record_every"):
            positive(c, key, "collect.", integer=True)
        positive(c, "max_time", "collect.")
        non_negative(c, "equilibration_time", "collect.")
        non_negative(c, "blackout_time", "collect.")
        rate = non_negative(c, "perturb_rate", "collect.")
        if rate * setup.dt > 1.0:
            raise ConfigError(
                f"collect.perturb_rate={rate:g}/s cannot be met with dt={setup.dt:g} s: at most "
                f"one perturbation per step, so the rate must be <= 1/dt = {1 / setup.dt:g}/s"
            )
        from surrogate.stages.budget import check_table_memory

        internal = setup.model.internal
        check_table_memory(int(c["n_per_state"]),
                           len(internal.input_names) + len(internal.feature_names) + 7)  # fmt: skip
        expected = c.get("expected_labels", False)
        if not isinstance(expected, bool):
            raise ConfigError(f"collect.expected_labels must be true or false, got {expected!r}")
        # the body checks its own perturbation options now, not after simulating
        setup.model.body.perturbation(setup.field, setup.model.perturbation_options)
        return cls(setup, c, Job.from_config(cfg), given=given,
                   design=_design_settings(cfg, c, rate))  # fmt: skip

    @property
    def expected_labels(self) -> bool:
        """Whether the table gets the expected labels (``collect.expected_labels`` and a model
        whose internal model gives them)."""
        from surrogate.simulate.transitions import can_expect

        wanted = bool(self.options.get("expected_labels", False))
        return wanted and can_expect(self.setup.model.internal)

    @property
    def target_error(self) -> float | None:
        """The sequential design's target (``collect.design.target_error``), or None."""
        return None if self.design is None else float(self.options["design"]["target_error"])

    def identity(self) -> dict[str, Any]:
        """Everything that defines a transitions table: the device too (its random stream), and
        the design's fits where it has one (a switched-off design leaves the fixed design's
        identity as it was)."""
        options = {k: v for k, v in self.options.items() if k != "design" or self.design}
        out = {**self.setup.identity(), "collect": options, "device": self.job.device_type}
        if self.design is not None:
            # its rounds fit psi and score it on the diagnostic's occupancy run
            out["design_fit"] = {**self.design.fit_identity(), "occupancy": self.design.diagnostic}
        return out

    @functools.cached_property
    def directory(self) -> Path:
        """``data/collect/model=..._field=..._dt=..._seed=...-<hash>``."""
        label = {**self.setup.label(), "seed": self.setup.seed}
        return artefact_dir(self.job.data_dir, "collect", label, self.identity())

    def command(self) -> str:
        """The command that makes this artefact."""
        return _command(COLLECT_CMD, self.setup.overrides(), self._overrides())

    def _overrides(self) -> list[str]:
        given = self.options if self.given is None else self.given
        return group_overrides("collect", given, "default")[1:]


#: keys of ``collect.design`` (the sequential design; surrogate/stages/design.py)
DESIGN_KEYS = ("target_error", "max_rounds", "candidates", "explore")


def _design_settings(
    cfg: Mapping[str, Any], options: dict[str, Any], perturb_rate: float
) -> TrainSettings | None:
    """Validate ``collect.design``; the settings of its fits where ``target_error`` is set."""
    d = options.get("design")
    if d is None:
        return None
    if not isinstance(d, Mapping):
        raise ConfigError(f"collect.design must be a mapping of {list(DESIGN_KEYS)}, got {d!r}")
    unknown = sorted(set(d) - set(DESIGN_KEYS))
    if unknown:
        raise ConfigError(
            f"unknown collect.design setting(s) {unknown}; allowed: {list(DESIGN_KEYS)}"
        )
    if d.get("target_error") is None:
        return None
    target = positive(d, "target_error", "collect.design.")
    if target >= 1.0:
        raise ConfigError(
            f"collect.design.target_error={target:g} is a relative error of psi: give a value "
            f"in (0, 1), e.g. 0.02"
        )
    positive(d, "max_rounds", "collect.design.", integer=True)
    positive(d, "candidates", "collect.design.", integer=True)
    explore = non_negative(d, "explore", "collect.design.")
    if explore > 1.0:
        raise ConfigError(f"collect.design.explore={explore:g} is a share: give a value in [0, 1]")
    if perturb_rate <= 0.0:
        raise ConfigError(
            "collect.design needs perturbations to guide: set collect.perturb_rate > 0"
        )
    if "gp" not in cfg:
        raise ConfigError(
            "collect.design.target_error needs the gp group (its rounds fit psi): run "
            f"{TRAIN_CMD} collect.design.target_error={target:g} or add gp=svgp"
        )
    inner = to_dict(cfg)
    inner["collect"] = {**options, "design": {**dict(d), "target_error": None}}
    return TrainSettings.from_config(inner)


# ----------------------------------------------------------------------------------------------
# train


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
    #: gp.history: none | age (psi also over the switch clock, its last input) and its cap (s)
    history: str = "none"
    max_age: float = 5.0

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> TrainSettings:
        """Validate the gp group; the data is collected with ``cfg`` or read from
        ``transitions`` (an external table)."""
        external = cfg.get("transitions")
        if external:
            setup = ModelSetup.from_config(cfg)
            source: CollectSettings | ExternalTable = ExternalTable.from_path(str(external))
        else:
            source = CollectSettings.from_config(cfg)
            setup = source.setup
        gp_config = to_dict(cfg["gp"])
        hyper = {k: v for k, v in gp_config.items() if k not in GP_EXTRA}
        gp = GPSettings.from_config({**hyper, "seed": setup.seed})
        # the stage reports held-out metrics, so it needs a validation split (GPSettings allows 0)
        if not 0.0 < gp.validation_fraction < 1.0:
            raise ConfigError(
                f"gp.validation_fraction must lie in (0, 1) for the train stage (it reports "
                f"held-out metrics), got {gp.validation_fraction!r}"
            )
        inputs = setup.model.abstraction_inputs(gp_config.get("inputs"))
        history, max_age = history_setting(gp_config.get("history"),
                                           gp_config.get("max_age", 5.0), "gp")  # fmt: skip
        if history == "age":
            if isinstance(gp.bins, int) and gp.bins:  # the clock's axis has its own bin count
                clock_bins = gp_config.get("clock_bins", gp.bins)
                gp = GPSettings.from_config({**hyper, "seed": setup.seed,
                                             "bins": [gp.bins] * len(inputs) + [clock_bins]})  # fmt: skip
            inputs = (*inputs, AGE)
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
        diagnostic = _diagnostic(gp_config.get("diagnostic") or {})
        threads = gp_config.get("threads")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int)
                                    or threads < 1):  # fmt: skip
            raise ConfigError(f"gp.threads must be a positive integer or null, got {threads!r}")
        labels = gp_config.get("labels", "outcome")
        if labels not in LABEL_CHOICES:
            raise ConfigError(f"gp.labels must be one of {list(LABEL_CHOICES)}, got {labels!r}")
        if labels == "expected":
            if not gp.bins:
                raise ConfigError("gp.labels=expected needs binned training (gp.bins > 0)")
            if isinstance(source, CollectSettings) and not source.expected_labels:
                why = (
                    "collect.expected_labels=false"
                    if not source.options.get("expected_labels", False)
                    else f"model {setup.model.name!r} gives none (no expected_phi_next)"
                )
                raise ConfigError(
                    f"gp.labels=expected trains on expected labels, but {why}; use "
                    "gp.labels=outcome"
                )
        return cls(setup, source, gp, gp_config, inputs, sizes, diagnostic, Job.from_config(cfg),
                   int(threads) if threads is not None else torch.get_num_threads(),
                   history, max_age)  # fmt: skip

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
            data = self.source.identity()
        else:
            data = {"table": str(self.source.path), "sha256": self.source.sha256,
                    "model": self.setup.model_config, "seed": self.setup.seed}  # fmt: skip
        gp = {k: v for k, v in self.gp_config.items() if k not in GP_NOT_FIT}
        if self.history == "none":  # fits without a clock keep the identity they had before it
            gp = {k: v for k, v in gp.items() if k not in GP_CLOCK}
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
                "inducing": self.gp.n_inducing, "seed": self.seed}  # fmt: skip

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
        return group_overrides("gp", {**self.gp_config, "threads": self.fit_threads}, "svgp")[1:]

    def command(self) -> str:
        """The command that makes this artefact (and the fit)."""
        if isinstance(self.source, CollectSettings):
            data = [*self.setup.overrides(), *self.source._overrides()]
        else:
            data = [f"transitions={self.source.path}", *self.setup.overrides()]
        return _command(TRAIN_CMD, data, self.gp_overrides())

    def input_command(self) -> str:
        """The command that makes this stage's input (the collected transitions)."""
        if isinstance(self.source, CollectSettings):
            return self.source.command()
        return f"(the external table {self.source.path})"

    def occupancy(self) -> OccupancySettings:
        """The diagnostic's occupancy run: an unperturbed full-model population in the training
        field (``gp.diagnostic``: its size, start and length), seeded with this seed."""
        options = dict(self.diagnostic)
        if self.history == "age":  # the rows need the switch clocks
            options["clock"] = True
        return OccupancySettings(self.setup, options, self.job, self.command())


@dataclass(frozen=True, eq=False)
class OccupancySettings:
    """Where an unperturbed full-model population lives (the train diagnostic's weights): an
    artefact of its own, made by the train command that needs it."""

    setup: ModelSetup
    options: dict[str, Any]
    job: Job
    made_by: str

    def identity(self) -> dict[str, Any]:
        """Model, field, step, seed, the ``gp.diagnostic`` settings and the device type."""
        return {**self.setup.identity(), "occupancy": self.options,
                "device": self.job.device_type}  # fmt: skip

    @functools.cached_property
    def directory(self) -> Path:
        """``data/occupancy/model=..._field=..._dt=..._n=..._T=..._seed=...-<hash>``."""
        label = {**self.setup.label(), "n": self.options["n_cells"], "T": self.options["t_end"],
                 "seed": self.setup.seed}  # fmt: skip
        return artefact_dir(self.job.data_dir, "occupancy", label, self.identity())

    def command(self) -> str:
        """The command that makes this artefact (the train stage, which needs it)."""
        return self.made_by


def _diagnostic(options: Mapping[str, Any]) -> dict[str, Any]:
    unknown = sorted(set(options) - set(DIAGNOSTIC_DEFAULTS))
    if unknown:
        raise ConfigError(
            f"unknown gp.diagnostic setting(s) {unknown}; allowed: {sorted(DIAGNOSTIC_DEFAULTS)}"
        )
    d = {**DIAGNOSTIC_DEFAULTS, **dict(options)}
    positive(d, "n_cells", "gp.diagnostic.", integer=True)
    positive(d, "t_end", "gp.diagnostic.")
    positive(d, "record_every", "gp.diagnostic.", integer=True)
    non_negative(d, "equilibration_time", "gp.diagnostic.")
    d["start"] = list(validate_start(d, "start", "gp.diagnostic."))
    return d


# ----------------------------------------------------------------------------------------------
# simulate


@dataclass(frozen=True, eq=False)
class DecisionSettings:
    """The decision layer of a run: full model, learned abstraction, or exact lumped psi."""

    name: str
    config: dict[str, Any]
    mode: str | None = None
    lookup_size: tuple[int, ...] | None = None
    train: TrainSettings | None = None
    train_field: str | None = None
    #: decision=exact: none | age (the exact psi with a switch clock) and the clock's cap (s)
    history: str = "none"
    max_age: float = 5.0

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], setup: ModelSetup) -> DecisionSettings:
        """Validate the decision group (and, for an abstraction, the settings that locate it)."""
        d = to_dict(cfg["decision"])
        name = d.get("name")
        if name not in DECISIONS:
            raise ConfigError(
                f"decision.name must be one of {list(DECISIONS)} (select with "
                f"decision=full|abstract|exact), got {name!r}"
            )
        if name == "full":
            return cls(name, d)
        mode = d.get("mode")
        if mode not in DECISION_MODES[name]:
            raise ConfigError(
                f"decision.mode must be one of {list(DECISION_MODES[name])} for "
                f"decision={name}, got {mode!r}"
            )
        if name == "exact":
            internal = setup.model.internal
            if not has_exact_psi(internal):
                raise ConfigError(
                    f"decision=exact: model {setup.model.name!r} has no exact lumped psi (its "
                    f"network's state space is too large to enumerate); use decision=full (the "
                    f"model itself) or decision=abstract (the learned psi)"
                )
            history, max_age = history_setting(d.get("history"), d.get("max_age", 5.0),
                                               "decision")  # fmt: skip
            if history == "age" and (mode != "lookup" or not can_age(internal)):
                raise ConfigError(
                    f"decision.history=age needs decision.mode=lookup and a model with an exact "
                    f"psi over one signal with a clock (exact_age_psi); model "
                    f"{setup.model.name!r}, mode {mode!r}"
                )
            sizes = None
            if mode == "lookup":
                sizes = grid_size(d.get("lookup_size"), "decision.lookup_size",
                                  len(internal.signal_names))  # fmt: skip
                if not getattr(internal, "signal_bounds", None):
                    raise ConfigError(
                        f"decision.mode=lookup needs the model's signal bounds; model "
                        f"{setup.model.name!r} declares none: use decision.mode=direct"
                    )
            return cls(name, d, mode, sizes, history=history, max_age=max_age)
        train_field = str(d.get("train_field"))
        train_cfg = {**to_dict(cfg), "field": field_config(train_field)}  # unknown -> ConfigError
        train = TrainSettings.from_config(train_cfg)
        sizes = None
        if mode == "lookup":
            if len(train.inputs) > 3:
                raise ConfigError(
                    f"decision.mode=lookup tabulates at most 3 inputs, the abstraction has "
                    f"{list(train.inputs)}: use decision.mode=classifier"
                )
            sizes = grid_size(d.get("lookup_size"), "decision.lookup_size", len(train.inputs))
        return cls(name, d, mode, sizes, train, train_field)

    def identity(self) -> dict[str, Any]:
        """What of the decision defines a run (the abstraction by its fit's identity: the
        diagnostic and the output grid do not change the psi a run uses)."""
        out: dict[str, Any] = {"decision": self.config}
        if self.train is not None:
            out["abstraction"] = self.train.fit_identity()
        return out


@dataclass(frozen=True, eq=False)
class SimulateSettings:
    """The simulate stage: one population run (or one shard of it)."""

    setup: ModelSetup
    decision: DecisionSettings
    n_cells: int
    t_end: float
    record_interval: float
    start: tuple[float, float]
    equilibration_time: float
    record_durations: bool
    compile: bool
    job: Job
    shard: dict[str, int] | None = None
    record_cells: int | None = DEFAULT_RECORD_CELLS
    #: compiled runs simulated in one batch (reproduce): the batch's id (in the identity, since
    #: kernels fused for the batch's shape round differently) and the command that makes it
    batch: str | None = None
    made_by: str | None = None
    #: the loop's backend: auto | torch | numba (see :class:`~surrogate.simulate.Simulator`)
    backend: str = "auto"

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> SimulateSettings:
        """Validate the run settings, the decision and a memory estimate."""
        from surrogate.simulate.population import steps_between

        setup = ModelSetup.from_config(cfg)
        n_cells = int(positive(cfg, "n_cells", integer=True))
        t_end = float(positive(cfg, "t_end"))
        interval = float(positive(cfg, "record_interval"))
        if setup.dt > interval:
            raise ConfigError(f"dt={setup.dt:g} s is larger than record_interval={interval:g} s")
        try:
            steps_between(interval, setup.dt, "record_interval")
            steps_between(t_end, setup.dt, "t_end")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        eq = float(non_negative(cfg, "equilibration_time"))
        start = validate_start(cfg)
        decision = DecisionSettings.from_config(cfg, setup)
        job = Job.from_config(cfg)
        shards = (cfg.get("shard") or {}).get("count", 1)
        per_job = -(-n_cells // shards) if isinstance(shards, int) and shards >= 1 else n_cells
        check_memory(per_job, job.device)
        record_cells = cfg.get("record_cells", DEFAULT_RECORD_CELLS)
        if record_cells is not None:
            record_cells = int(positive(cfg, "record_cells", integer=True))
        return cls(setup, decision, n_cells, t_end, interval, start, eq,
                   bool(cfg.get("record_durations", True)), bool(cfg.get("compile", False)), job,
                   record_cells=record_cells, backend=validate_backend(cfg))  # fmt: skip

    def identity(self) -> dict[str, Any]:
        """Everything that defines a population run (``compile`` and ``backend`` too: compiled
        kernels round differently, so runs with one seed differ in the last bits; the device
        type: CPU and CUDA draw different random streams)."""
        out = {**self.setup.identity(), **self.decision.identity(), "n_cells": self.n_cells,
               "t_end": self.t_end, "record_interval": self.record_interval,
               "start": list(self.start), "equilibration_time": self.equilibration_time,
               "record_durations": self.record_durations, "compile": self.compile,
               "record_cells": self.record_cells, "backend": self.backend,
               "device": self.job.device_type}  # fmt: skip
        if self.shard is not None:
            out["shard"] = self.shard
        if self.batch is not None:
            out["batch"] = self.batch
        return out

    def label(self) -> dict[str, Any]:
        """Readable part of the directory name."""
        return {"decision": self.decision.name, **self.setup.label(), "n": self.n_cells,
                "T": self.t_end, "seed": self.setup.seed}  # fmt: skip

    @functools.cached_property
    def directory(self) -> Path:
        """``data/simulate/<decision>_model=..._field=..._n=..._T=..._seed=...-<hash>``."""
        return artefact_dir(self.job.data_dir, "simulate", self.label(), self.identity())

    def overrides(self) -> list[str]:
        """Overrides that reproduce this run (shards: the parent run's)."""
        setup = self.setup
        n, seed = self.n_cells, setup.seed
        if self.shard is not None:
            n, seed = self.shard["parent_n_cells"], self.shard["parent_seed"]
        out = [*group_overrides("decision", self.decision.config, self.decision.name),
               *setup.with_seed(seed).overrides()]  # fmt: skip
        shipped = _shipped_run_settings()
        run = {"n_cells": n, "t_end": self.t_end, "record_interval": self.record_interval,
               "start": list(self.start), "equilibration_time": self.equilibration_time,
               "record_durations": self.record_durations, "compile": self.compile,
               "record_cells": self.record_cells, "backend": self.backend}  # fmt: skip
        out += [
            f"{k}={_fmt(v)}"
            for k, v in run.items()
            if shipped.get(k) != v or k in ("n_cells", "t_end")
        ]
        if self.decision.train is not None:
            out += self.decision.train.gp_overrides()
            if isinstance(self.decision.train.source, CollectSettings):
                out += self.decision.train.source._overrides()
        if self.shard is not None:
            out += [f"shard.count={self.shard['count']}", f"shard.index={self.shard['index']}"]
        return out

    def command(self) -> str:
        """The command that makes this run."""
        return self.made_by or _command(SIMULATE_CMD, self.overrides())

    def replace(self, **changes: Any) -> SimulateSettings:
        """A copy with some fields changed (``seed=`` changes the setup's seed)."""
        from dataclasses import replace

        seed = changes.pop("seed", None)
        out = replace(self, **changes)
        if seed is not None:
            out = replace(out, setup=self.setup.with_seed(seed))
        out.__dict__.pop("directory", None)
        return out


@functools.lru_cache(maxsize=1)
def _shipped_run_settings() -> dict[str, Any]:
    """The run settings of the shipped ``conf/simulate.yaml`` (what a command need not repeat)."""
    from omegaconf import OmegaConf

    from surrogate.config import CONF_DIR

    data = to_dict(OmegaConf.load(CONF_DIR / "simulate.yaml"))
    return {k: v for k, v in data.items() if k != "defaults"}


def check_memory(n_cells: int, device: torch.device) -> None:
    """Refuse a population that cannot fit in memory, before allocating it (naming sharding)."""
    need = n_cells * BYTES_PER_CELL
    if device.type == "cuda":
        have = torch.cuda.mem_get_info(device)[0]
    else:
        try:
            import os

            have = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
            return
    if need > have:
        raise ConfigError(
            f"n_cells={n_cells} needs about {need / 2**30:.1f} GiB (~{BYTES_PER_CELL} B per "
            f"cell) but {have / 2**30:.1f} GiB are free on {device}; split the population "
            f"into shards (`{SIMULATE_CMD} -m shard.count=K shard.index='range(K)' "
            f"n_cells={n_cells}`, then scripts/merge_shards.py)"
        )


# ----------------------------------------------------------------------------------------------
# evaluate


@dataclass(frozen=True, eq=False)
class EvaluateSettings:
    """The evaluate stage: a candidate run (abstract or exact) vs a full run, and the noise
    floor (a second full run with another seed)."""

    candidate: SimulateSettings
    full: SimulateSettings
    full_repeat: SimulateSettings | None
    times: tuple[float, ...]
    subsample: int
    options: dict[str, Any]
    run_missing: bool
    job: Job

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> EvaluateSettings:
        """Validate the evaluate group and the three runs it compares."""
        candidate = SimulateSettings.from_config(cfg)
        if candidate.decision.name == "full":
            raise ConfigError(
                "evaluate compares an abstraction with the full model: use decision=abstract "
                "(or decision=exact)"
            )
        e = to_dict(cfg["evaluate"])
        full_cfg = {**to_dict(cfg), "decision": {"name": "full"}}
        if e.get("full_n_cells") is not None:  # the full model on fewer cells (large runs)
            full_cfg["n_cells"] = int(positive(e, "full_n_cells", "evaluate.", integer=True))
        full = SimulateSettings.from_config(full_cfg)
        subsample = int(positive(e, "subsample", "evaluate.", integer=True))
        if not isinstance(e.get("figures", True), bool):
            raise ConfigError(f"evaluate.figures must be true or false, got {e['figures']!r}")
        t_end = candidate.t_end
        times_cfg = e.get("times")
        if times_cfg is None:  # the paper's quarters of t_end
            times = tuple(t_end * (k + 1) / 4 for k in range(4))
        else:
            try:
                times = tuple(float(t) for t in times_cfg)
            except (TypeError, ValueError):
                raise ConfigError(
                    f"evaluate.times must be a list of times in s (or null), got {times_cfg!r}"
                ) from None
            bad = [t for t in times if not 0 <= t <= t_end]
            if bad:
                raise ConfigError(
                    f"evaluate.times {bad} lie outside [0, t_end={t_end:g}] s (null: quarters "
                    f"of t_end)"
                )
        repeat = None
        if e.get("noise_floor", True):
            offset = e.get("noise_seed_offset")
            seed = candidate.setup.seed
            # offset 0 would compare the full run with itself: a noise floor of exactly zero
            if (
                isinstance(offset, bool)
                or not isinstance(offset, int)
                or offset == 0
                or seed + offset < 0
            ):
                raise ConfigError(
                    f"evaluate.noise_seed_offset must be a non-zero integer with seed + offset "
                    f">= 0 (the noise floor's second full run uses seed + offset), got {offset!r}"
                )
            repeat = full.replace(seed=seed + offset)
        options = {k: v for k, v in e.items() if k != "run_missing"}
        return cls(candidate, full, repeat, times, subsample, options,
                   bool(e.get("run_missing", False)), Job.from_config(cfg))  # fmt: skip

    def identity(self) -> dict[str, Any]:
        """The candidate run's settings and the evaluation's own (times as resolved)."""
        return {"candidate": self.candidate.identity(),
                "evaluate": {**self.options, "times": list(self.times)}}  # fmt: skip

    @functools.cached_property
    def directory(self) -> Path:
        """``data/evaluate/<decision>_model=..._field=..._n=..._T=..._seed=...-<hash>``."""
        return artefact_dir(self.job.data_dir, "evaluate", self.candidate.label(), self.identity())

    def command(self) -> str:
        """The command that makes this evaluation."""
        return _command(EVALUATE_CMD, self.candidate.overrides())


# ----------------------------------------------------------------------------------------------
# reproduce


@dataclass(frozen=True, eq=False)
class ReproduceSettings:
    """collect -> train -> simulate and evaluate on several fields -> report."""

    train: TrainSettings
    evaluations: dict[str, EvaluateSettings]
    exact: dict[str, EvaluateSettings]
    job: Job
    config: dict[str, Any] = field(repr=False)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> ReproduceSettings:
        """Validate every stage's settings before any work starts."""
        fields = [str(f) for f in (cfg.get("fields") or [])]
        if not fields:
            raise ConfigError(
                "fields must list at least one field, e.g. [gaussian, linear, dynamic]"
            )
        for name in fields:
            field_config(name)
        c = to_dict(cfg)
        for key in ("batch", "exact_psi", "exact_psi_figures"):
            if not isinstance(c.get(key, True), bool):
                raise ConfigError(f"{key} must be true or false, got {c[key]!r}")
        background = c.get("background", "auto")
        if not isinstance(background, bool) and background != "auto":
            raise ConfigError(f"background must be true, false or auto, got {c['background']!r}")
        evaluations = {
            name: EvaluateSettings.from_config(_field_run(c, name, c["decision"]))
            for name in fields
        }
        train = next(iter(evaluations.values())).candidate.decision.train
        if train is None:
            raise ConfigError("reproduce needs decision=abstract (the learned abstraction)")
        exact = {}
        if c.get("exact_psi") and has_exact_psi(train.setup.model.internal):
            decision = {**group_config("decision", "exact")}
            # the report shows the abstraction's figures only; the exact chain's are optional
            figures = {"figures": bool(c.get("exact_psi_figures", False))}
            exact = {
                name: EvaluateSettings.from_config(_field_run(c, name, decision, **figures))
                for name in fields
            }
        if c.get("batch", True) and c.get("compile", False):
            evaluations, exact = _batched(evaluations, exact)
        return cls(train, evaluations, exact, Job.from_config(cfg), c)

    def runs(self) -> list[SimulateSettings]:
        """Every population run the report needs (each once)."""
        out: dict[Path, SimulateSettings] = {}
        for e in [*self.evaluations.values(), *self.exact.values()]:
            for s in (e.full, e.candidate, e.full_repeat):
                if s is not None:
                    out.setdefault(s.directory, s)
        return list(out.values())

    def identity(self) -> dict[str, Any]:
        """The evaluations' identities (which include the abstraction's fit) and the train
        directory's (its diagnostic is part of the report)."""
        out = {name: e.identity() for name, e in {**self.evaluations, **{
            f"exact:{k}": v for k, v in self.exact.items()}}.items()}  # fmt: skip
        return {**out, "train": self.train.identity()}

    @functools.cached_property
    def directory(self) -> Path:
        """``data/reproduce/model=..._dt=..._n=..._T=..._inputs=..._seed=...-<hash>``."""
        first = next(iter(self.evaluations.values())).candidate
        label = {"model": first.setup.model.name, "dt": first.setup.dt, "n": first.n_cells,
                 "T": first.t_end, "inputs": "+".join(self.train.inputs),
                 "seed": first.setup.seed}  # fmt: skip
        return artefact_dir(self.job.data_dir, "reproduce", label, self.identity())


def validate_backend(cfg: Mapping[str, Any]) -> str:
    """The ``backend`` setting (auto | torch | numba)."""
    from surrogate.simulate.loop import check_backend

    return check_backend(cfg.get("backend", "auto"))


#: runs of at most this many cells are simulated in one batch (reproduce); larger ones alone:
#: batching takes the per-step overhead out of small populations, and costs a large one
#: ~1.4x (1e6 cells, measured) in assembling the batch's random numbers and fields
BATCH_MAX_CELLS = 20_000


def batchable(run: SimulateSettings) -> bool:
    """Whether reproduce simulates ``run`` in its batch (small populations, unsharded)."""
    return run.n_cells <= BATCH_MAX_CELLS and run.shard is None


def _batched(
    evaluations: dict[str, EvaluateSettings], exact: dict[str, EvaluateSettings]
) -> tuple[dict[str, EvaluateSettings], dict[str, EvaluateSettings]]:
    """The evaluations with their (compiled) runs marked as one batch: the batch's id is a hash
    of its runs' identities; the command that makes them is reproduce's."""
    from dataclasses import replace

    everything = [*evaluations.values(), *exact.values()]
    runs = {json.dumps(s.identity(), sort_keys=True, default=str)
            for e in everything for s in (e.full, e.candidate, e.full_repeat)
            if s is not None and batchable(s)}  # fmt: skip
    batch = hashlib.sha256("\n".join(sorted(runs)).encode()).hexdigest()[:12]
    first = everything[0].candidate
    keep = [o for o in first.overrides() if not o.startswith(("field=", "decision"))]
    made_by = _command(REPRODUCE_CMD, keep)

    def tagged(e: EvaluateSettings) -> EvaluateSettings:
        def mark(s: SimulateSettings | None) -> SimulateSettings | None:
            if s is None or not batchable(s):
                return s
            return s.replace(batch=batch, made_by=made_by)

        return replace(e, candidate=mark(e.candidate), full=mark(e.full),
                       full_repeat=mark(e.full_repeat))  # fmt: skip

    return ({k: tagged(v) for k, v in evaluations.items()},
            {k: tagged(v) for k, v in exact.items()})  # fmt: skip


def _field_run(
    cfg: dict[str, Any], name: str, decision: Mapping[str, Any], **evaluate: Any
) -> dict[str, Any]:
    """The evaluate config for one field: same settings, that field, missing runs simulated
    (and any other ``evaluate`` options given)."""
    return {**cfg, "field": field_config(name), "decision": dict(decision),
            "evaluate": {**cfg["evaluate"], **evaluate, "run_missing": True}}  # fmt: skip
