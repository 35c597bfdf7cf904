"""Settings of a run's decision layer: the full model, the learned abstraction (located by
its training settings) or the exact lumped psi."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import torch

from surrogate.config import field_config, grid_size, resolve_device, to_dict
from surrogate.errors import ConfigError
from surrogate.kinds import (
    DECISION_KINDS,
    ChainKind,
    DecisionKind,
    decision_identity,
    decision_kind,
    exact_chain,
    exact_clock,
)
from surrogate.models.capabilities import has_exact_psi, signal_bounds_of
from surrogate.simulate.classes import STARTS
from surrogate.stages.settings.common import Job, ModelSetup
from surrogate.stages.settings.train import TrainSettings

DECISIONS = tuple(DECISION_KINDS)
DECISION_MODES = {name: tuple(m.name for m in kind.modes)
                  for name, kind in DECISION_KINDS.items() if kind.modes}  # fmt: skip


@dataclass(frozen=True, eq=False)
class DecisionSettings:
    """The decision layer of a run: full model, learned abstraction, or exact lumped psi."""

    name: str
    config: dict[str, Any]
    mode: str | None = None
    lookup_size: tuple[int, ...] | None = None
    train: TrainSettings | None = None
    train_field: str | None = None
    #: decision=exact: the chain the exact law drives (:mod:`surrogate.kinds`: the two-state
    #: chain, the switch clock or K lumps over the model's classes) and the clock's cap (s)
    chain: ChainKind | None = None
    max_age: float = 5.0
    #: decision=abstract: where cells start (``decision.initial`` resolved: internal | stationary)
    start: str = "internal"

    @property
    def kind(self) -> DecisionKind:
        """The layer's kind (full, abstract, exact)."""
        return decision_kind(self.name)

    @property
    def history(self) -> str:
        """decision=exact: none | age (the exact psi with a switch clock); else none."""
        return self.chain.history if self.chain is not None else "none"

    @property
    def lumps(self) -> str:
        """decision=exact: phi | classes (the exact K-lumps chain); else phi."""
        return self.chain.lumps if self.chain is not None else "phi"

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], setup: ModelSetup, job: Job) -> DecisionSettings:
        """Validate the decision group (and, for an abstraction, the settings that locate it).

        Args:
            cfg: The run's config (its ``decision`` group; an abstraction's ``gp`` and
                ``collect``).
            setup: The run's model setup (an abstraction's fit: the same in its training field).
            job: The run's job (an abstraction's fit: the same on ``decision.train_device``).
        """
        d = to_dict(cfg["decision"])
        kind = decision_kind(d.get("name"))
        name = kind.name
        if kind.full:
            return cls(name, d)
        mode = kind.mode(d.get("mode"))
        if kind.exact:
            internal = setup.model.internal
            if not has_exact_psi(internal):
                raise ConfigError(
                    f"decision=exact: model {setup.model.name!r} has no exact lumped psi (its "
                    f"network's state space is too large to enumerate); use decision=full (the "
                    f"model itself) or decision=abstract (the learned psi)"
                )
            history, max_age = exact_clock(d, mode, internal, setup.model.name)
            sizes = None
            if mode.table:
                sizes = grid_size(d.get("lookup_size"), "decision.lookup_size",
                                  len(internal.signal_names))  # fmt: skip
                if signal_bounds_of(internal) is None:
                    raise ConfigError(
                        f"decision=exact with decision.mode=lookup tabulates the exact psi over "
                        f"the model's signal bounds; model {setup.model.name!r} declares none: "
                        f"give them (a yaml model's `signal_bounds: {{<input>: [lo, hi]}}`, the "
                        f"range scripts/inspect_model.py measures) or use decision.mode=direct"
                    )
            chain = exact_chain(d, history, mode, internal, setup.model.name)
            return cls(name, d, mode.name, sizes, chain=chain, max_age=max_age)
        train_field = str(d.get("train_field"))
        train_setup = setup.with_field(field_config(train_field))  # unknown -> ConfigError
        train_device = d.get("train_device")
        if train_device is not None:  # a fit made on another device (e.g. a CPU fit on CUDA)
            job = replace(job, device=train_device_of(train_device))
        train = TrainSettings.from_config(cfg, train_setup, job)
        sizes = None
        train.kind.check_mode(mode)
        if mode.table:
            if len(train.inputs) > 3:
                raise ConfigError(
                    f"decision.mode=lookup tabulates at most 3 inputs, the abstraction has "
                    f"{list(train.inputs)}: use decision.mode=classifier"
                )
            sizes = grid_size(d.get("lookup_size"), "decision.lookup_size", len(train.inputs))
        start = resolve_start(d.get("initial", "internal"), train, "decision.initial")
        return cls(name, d, mode.name, sizes, train, train_field, start=start)

    def identity(self) -> dict[str, Any]:
        """What of the decision defines a run (the abstraction by its fit's identity: the
        diagnostic and the output grid do not change the psi a run uses)."""
        config = decision_identity(self.config)  # as before K lumps, for two-state runs
        # runs starting as before keep the identity they had before decision.initial; the
        # fit's device is in the abstraction's identity (train_device only locates it)
        config = {k: v for k, v in config.items() if k not in ("initial", "train_device")}
        out: dict[str, Any] = {"decision": config}
        if self.train is not None:
            out["abstraction"] = self.train.fit_identity()
        if self.start != "internal":
            out["initial"] = self.start
        return out


def train_device_of(value: Any) -> torch.device:
    """``decision.train_device`` validated: the device the abstraction was trained on, where it
    is not the run's (a fit is identified by the device that made it: CPU and CUDA draw other
    random numbers from one seed)."""
    if not isinstance(value, str):
        raise ConfigError(f"decision.train_device must be null (the run's device), cpu or cuda, "
                          f"got {value!r}")  # fmt: skip
    try:
        return resolve_device(value)
    except ConfigError as exc:
        raise ConfigError(f"decision.train_device: {exc}") from None


def resolve_start(value: Any, train: TrainSettings, where: str) -> str:
    """``decision.initial`` (or ``fidelity.initial``), validated: ``internal`` (the internal
    model's initial law, as the full model's cells start) or ``stationary`` (a K-lumps chain's
    own stationary law at the inputs, no internal state simulated: a network's burn-in is not
    paid, but the start is only as good as the chain's stationary law; docs/fidelity.md)."""
    if value not in STARTS:
        raise ConfigError(f"{where} must be one of {list(STARTS)}, got {value!r}")
    train.kind.check_start(str(value), where)
    return str(value)
