"""Settings of the inspect stage: a model checked before any collection (the network, the
inputs the fields give, phi's occupancy and memory, settling, cost; a recommended abstraction).

The run settings it judges (fields, ``n_cells``, ``t_end``, the collect, gp and evaluate groups)
are reproduce's, so the costs it reports are those of ``scripts/reproduce.py`` with the same
overrides; its own keys are the ``inspect`` group of ``conf/inspect.yaml``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from surrogate.config import (
    CONF_DIR,
    field_config,
    non_negative,
    positive,
    to_dict,
    validate_start,
)
from surrogate.errors import ConfigError
from surrogate.io import artefact_dir
from surrogate.models.capabilities import start_size_of
from surrogate.stages.settings.choice import collecting_pending
from surrogate.stages.settings.collect import identity_options
from surrogate.stages.settings.common import (
    Job,
    ModelSetup,
    command_line,
    format_value,
    group_overrides,
)
from surrogate.stages.settings.reproduce import ReproduceSettings
from surrogate.validation import known_keys

INSPECT_CMD = "python3 scripts/inspect_model.py"
#: the top-level run settings the costs and the population runs are read from
RUN_KEYS = ("n_cells", "t_end", "start", "equilibration_time", "record_interval", "exact_psi",
            "batch", "compile", "backend")  # fmt: skip
#: the groups whose settings the reported costs depend on, and reproduce's choice of each
GROUP_CHOICES = {"collect": "default", "gp": "auto", "evaluate": "default", "decision": "abstract"}
COST_GROUPS = tuple(GROUP_CHOICES)
#: the inspect keys: positive numbers, positive integers, shares in (0, 1) and the quantile pair
POSITIVE = ("min_time", "max_time", "max_seconds", "burn_in_factor", "memory_effect")
INTEGERS = ("population_cells", "grid_points", "n_cells", "record_windows", "exact_max_states",
            "min_switches")  # fmt: skip
SHARES = ("population_share", "min_occupancy", "settle_tolerance", "effect_threshold",
          "markov_alpha", "oscillation_depth")  # fmt: skip


def inspect_defaults() -> dict[str, Any]:
    """The shipped ``inspect`` keys (conf/inspect.yaml): what a command leaves unsaid."""
    from omegaconf import OmegaConf

    return to_dict(OmegaConf.load(CONF_DIR / "inspect.yaml"))["inspect"]


@dataclass(frozen=True, eq=False)
class InspectSettings:
    """The inspection of a model: its setup, the fields whose inputs it measures, its own
    options (validated), and the full config (the reproduce settings whose cost it reports are
    built from it on demand)."""

    setup: ModelSetup
    fields: tuple[str, ...]
    options: dict[str, Any]
    run: dict[str, Any]
    job: Job
    config: dict[str, Any]

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> InspectSettings:
        """Validate the inspect keys, the fields and the model (before any simulation)."""
        c = to_dict(cfg)
        setup = ModelSetup.from_config(c)
        fields = tuple(str(f) for f in (c.get("fields") or []))
        if not fields:
            raise ConfigError("fields must list at least one field, e.g. [gaussian, linear]")
        for name in fields:
            field_config(name)
        defaults = inspect_defaults()
        given = known_keys(c.get("inspect") or {}, sorted(defaults), "inspect")
        o = {**defaults, **given}
        for key in POSITIVE:
            positive(o, key, "inspect.")
        for key in INTEGERS:
            positive(o, key, "inspect.", integer=True)
            o[key] = int(o[key])
        for key in SHARES:
            if not 0 < positive(o, key, "inspect.") < 1:
                raise ConfigError(f"inspect.{key} must be a share in (0, 1), got {o[key]!r}")
        if o["grid_points"] < 2:
            raise ConfigError(f"inspect.grid_points must be >= 2, got {o['grid_points']}")
        if not o["min_occupancy"] < 0.5:
            raise ConfigError(f"inspect.min_occupancy must be below 0.5, got {o['min_occupancy']}")
        if o["min_time"] > o["max_time"]:
            raise ConfigError(f"inspect.min_time={o['min_time']:g} s exceeds inspect.max_time="
                              f"{o['max_time']:g} s")  # fmt: skip
        q = o["quantiles"]
        if not (isinstance(q, list | tuple) and len(q) == 2
                and all(isinstance(v, int | float) and not isinstance(v, bool) for v in q)
                and 0 <= q[0] < 0.5 < q[1] <= 1):  # fmt: skip
            raise ConfigError(f"inspect.quantiles must be [low, high] with 0 <= low < 0.5 < high "
                              f"<= 1, got {q!r}")  # fmt: skip
        o["quantiles"] = [float(q[0]), float(q[1])]
        o["pilot"] = _pilot(o["pilot"], defaults["pilot"])
        run = {k: c.get(k) for k in RUN_KEYS}
        positive(run, "t_end")
        non_negative(run, "equilibration_time")
        run["start"] = list(validate_start(c, size=start_size_of(setup.model.body)))
        return cls(setup, fields, o, run, Job.from_config(c), c)

    def field_setup(self, name: str) -> ModelSetup:
        """The model setup in field ``name``."""
        return self.setup.with_field(field_config(name))

    @functools.cached_property
    def reproduce(self) -> ReproduceSettings:
        """The reproduce settings of the same config: what the reported costs are of
        (``gp=auto``'s measured choice, made by train later, resolved by the rule meanwhile)."""
        with collecting_pending():
            return ReproduceSettings.from_config(self.config)

    def identity(self) -> dict[str, Any]:
        """What defines the report: the model setup, the fields, the inspect options, the run
        settings and groups whose costs it reports, and the device type."""
        return {**self.setup.identity(),
                "fields": {name: field_config(name) for name in self.fields},
                "inspect": self.options, "run": self.run,
                "costs": {g: self._cost_group(g) for g in COST_GROUPS},
                "device": self.job.device_type}  # fmt: skip

    def _cost_group(self, group: str) -> Any:
        """The config's ``group`` as it enters the identity: collect's without the keys that
        are no part of a table's (``collect.probe_seconds``)."""
        value = self.config.get(group)
        if group == "collect" and isinstance(value, Mapping):
            return identity_options(value)
        if group == "gp" and isinstance(value, Mapping) and value.get("lumps") != "auto":
            # gp.choice is gp=auto's: a named chain's command (gp.lumps=..., no gp=) composes
            # under gp=auto and brings it along, though nothing reads it
            return {k: v for k, v in value.items() if k != "choice"}
        return value

    @functools.cached_property
    def directory(self) -> Path:
        """``data/inspect/model=..._dt=..._seed=...-<hash>``."""
        label = {"model": self.setup.model.name, "dt": self.setup.dt, "seed": self.setup.seed}
        return artefact_dir(self.job.data_dir, "inspect", label, self.identity())

    def command(self) -> str:
        """The command that makes this report: the model setup, the fields, the run settings,
        the groups the costs are of (each relative to reproduce's choice) and the inspect keys
        that differ from the shipped ones."""
        defaults = inspect_defaults()
        flat = {k: v for k, v in self.options.items() if k != "pilot"}
        flat.update({f"pilot.{k}": v for k, v in self.options["pilot"].items()})
        shipped = {**defaults, **{f"pilot.{k}": v for k, v in defaults["pilot"].items()}}
        changed = [f"inspect.{k}={format_value(v)}" for k, v in flat.items()
                   if _differs(v, shipped.get(k))]  # fmt: skip
        run = [f"fields={format_value(list(self.fields))}"]
        run += [f"{k}={format_value(v)}" for k, v in self.run.items() if v is not None]
        groups = []
        for group, choice in GROUP_CHOICES.items():
            if self.config.get(group) is not None:
                groups += group_overrides(group, self.config[group], choice)[1:]
        return command_line(INSPECT_CMD, self.setup.overrides(), run, groups, changed)


def _pilot(value: Any, defaults: Mapping[str, Any]) -> dict[str, Any]:
    """``inspect.pilot`` checked (:mod:`surrogate.stages.pilot`), each bad value refused by
    its key before any work."""
    if not isinstance(value, Mapping):
        raise ConfigError(f"inspect.pilot must be a group of {sorted(defaults)}, got {value!r}")
    p = {**defaults, **known_keys(value, sorted(defaults), "inspect.pilot")}
    if not isinstance(p["enabled"], bool):
        raise ConfigError(f"inspect.pilot.enabled must be true or false, got {p['enabled']!r}")
    positive(p, "n_per_state", "inspect.pilot.", integer=True)
    positive(p, "n_cells", "inspect.pilot.", integer=True)
    positive(p, "t_end", "inspect.pilot.")
    if p["n_cells"] < 2:
        # the choice's tie rule reads the SE of a paired per-cell difference
        raise ConfigError(f"inspect.pilot.n_cells={p['n_cells']} held-out cell gives the "
                          f"choice's paired difference no standard error: use 2 or more "
                          f"(default {defaults['n_cells']})")  # fmt: skip
    return {"enabled": p["enabled"], "n_per_state": int(p["n_per_state"]),
            "n_cells": int(p["n_cells"]), "t_end": float(p["t_end"])}  # fmt: skip


def _differs(a: Any, b: Any) -> bool:
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) != len(b) or any(_differs(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, int | float) and isinstance(b, int | float):
        return not math.isclose(float(a), float(b))
    return a != b


__all__ = ["INSPECT_CMD", "InspectSettings", "inspect_defaults"]
