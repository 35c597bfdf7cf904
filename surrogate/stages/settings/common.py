"""What every stage's settings share: the job (where artefacts go, the device), the model
setup (model, field, dt, seed), the scripts' commands, the overrides that reproduce a setting
and the memory checks that refuse a setting before it is allocated."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from surrogate.config import (
    build_field,
    build_model,
    field_name,
    group_config,
    group_options,
    positive,
    resolve_device,
    seed_setting,
    to_dict,
)
from surrogate.errors import ConfigError
from surrogate.fields import Field
from surrogate.models.base import Model

COLLECT_CMD = "python scripts/collect.py"
TRAIN_CMD = "python scripts/train.py"
SIMULATE_CMD = "python scripts/simulate.py"
EVALUATE_CMD = "python scripts/evaluate.py"
REPRODUCE_CMD = "python scripts/reproduce.py"
FIDELITY_CMD = "python scripts/fidelity.py"

#: bytes per value of a transitions table while it is collected (float64 columns, generous for
#: the rows gathered before the per-origin subsample)
TABLE_BYTES_PER_VALUE = 32


# ----------------------------------------------------------------------------------------------
# commands: the overrides that reproduce a setting, relative to the shipped defaults


def _flatten(prefix: str, value: Any) -> dict[str, Any]:
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(f"{prefix}.{k}", v))
        return out
    return {prefix: value}


def format_value(value: Any) -> str:
    """``value`` as a Hydra override writes it (lists in brackets, ``true``, ``null``)."""
    if isinstance(value, list | tuple):
        return "[" + ",".join(format_value(v) for v in value) + "]"
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
            out.append(f"+{key}={format_value(v)}")
        elif have[key] != v:
            out.append(f"{key}={format_value(v)}")
    return out


def command_line(script: str, *parts: list[str]) -> str:
    """``script`` followed by every override of ``parts``, as one command."""
    return " ".join([script, *[p for part in parts for p in part]])


# ----------------------------------------------------------------------------------------------
# building blocks


@dataclass(frozen=True)
class Job:
    """Settings of a job: where artefacts go, device, progress, when to warn of inputs outside
    an abstraction's training data. Only the device type changes a result
    (:attr:`device_type`, in the identities)."""

    data_dir: Path
    device: torch.device
    progress: bool
    #: share of sampled cell-steps outside the trained range (or inside it in a sparsely
    #: trained bin) above which a run warns
    outside_warning: float = 0.01
    #: training rows per state a bin of the fit's histogram needs not to be sparse (None: per
    #: state, 25 expected switches at its switching share,
    #: :func:`~surrogate.simulate.support.min_rows_of`)
    support_min_rows: int | None = None

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> Job:
        """Validated job settings."""
        warn = cfg.get("outside_warning", 0.01)
        if isinstance(warn, bool) or not isinstance(warn, int | float) or not 0 <= warn <= 1:
            raise ConfigError(f"outside_warning must be a share in [0, 1] of the cell-steps, "
                              f"got {warn!r}")  # fmt: skip
        rows = cfg.get("support_min_rows")
        if rows is not None and (isinstance(rows, bool) or not isinstance(rows, int) or rows < 1):
            raise ConfigError(f"support_min_rows must be null (the default rule) or a whole "
                              f"number of training rows >= 1, got {rows!r}")  # fmt: skip
        return cls(
            Path(str(cfg.get("data_dir", "data"))),
            resolve_device(cfg.get("device", "cpu")),
            bool(cfg.get("progress", True)),
            float(warn),
            None if rows is None else int(rows),
        )

    @property
    def device_type(self) -> str:
        """``cpu`` or ``cuda``: part of the identity of everything that draws random numbers
        (CPU and CUDA generators give different streams from one seed; any one CUDA device
        gives the same)."""
        return self.device.type

    def device_overrides(self) -> list[str]:
        """``device=...`` where it is not the CPU (a command that remakes an artefact of this
        job names its device: the device type is part of the artefact's identity)."""
        return [] if self.device_type == "cpu" else [f"device={self.device_type}"]


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
        model_config = _for_class_moves(model_config, cfg.get("gp"))
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


def _for_class_moves(model_config: dict[str, Any], gp: Any) -> dict[str, Any]:
    """``model_config`` as ``gp.class_moves`` needs it: with ``relaxation``, a model whose
    class offers ``relaxation_config`` (the SBML model: ``classes: auto`` then chooses bins
    both lumps share) gets that config, before it is built: every stage builds the same."""
    from hydra.utils import get_class

    from surrogate.kinds import KLumps

    moves = gp.get("class_moves") if isinstance(gp, Mapping) else None
    # the kind says what its value means (a bad one: the train settings refuse it by name)
    if moves not in KLumps.class_moves_choices or not KLumps.make(str(moves)).relaxation:
        return model_config

    try:
        target = get_class(str(model_config.get("_target_")))
    except Exception:  # an unknown target: build_model refuses it by name
        return model_config
    adapt = getattr(target, "relaxation_config", None)
    return to_dict(adapt(model_config)) if callable(adapt) else model_config


# ----------------------------------------------------------------------------------------------
# memory: what a setting would need, refused before it is allocated


def free_memory_bytes() -> int | None:
    """Free physical memory (bytes) of this machine; None where it cannot be read (non-POSIX)."""
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return None


def check_table_memory(n_per_state: int, columns: int) -> None:
    """Refuse a collection whose table cannot fit in memory, naming ``collect.n_per_state``."""
    need = 2 * n_per_state * columns * TABLE_BYTES_PER_VALUE
    have = free_memory_bytes()
    if have is None:
        return
    if need > have:
        raise ConfigError(
            f"collect.n_per_state={n_per_state}: the transitions table ({columns} columns) "
            f"needs about {need / 2**30:.1f} GiB while collected, but {have / 2**30:.1f} GiB "
            f"are free; lower collect.n_per_state"
        )
