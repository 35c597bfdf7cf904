"""Settings of a run's decision layer: the full model, the learned abstraction (located by
its training settings) or the exact lumped psi."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from surrogate.config import field_config, grid_size, to_dict
from surrogate.errors import ConfigError
from surrogate.models.capabilities import exact_class_step_of, has_exact_psi, signal_bounds_of
from surrogate.simulate.classes import LUMPINGS, STARTS, can_classify
from surrogate.simulate.memory import can_age, history_setting
from surrogate.stages.settings.common import ModelSetup
from surrogate.stages.settings.train import TrainSettings

DECISIONS = ("full", "abstract", "exact")
DECISION_MODES = {"abstract": ("lookup", "classifier"), "exact": ("lookup", "direct")}


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
    #: decision=exact: phi | classes (the exact K-lumps chain over the model's classes)
    lumps: str = "phi"
    #: decision=abstract: where cells start (``decision.initial`` resolved: internal | stationary)
    start: str = "internal"

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
                if signal_bounds_of(internal) is None:
                    raise ConfigError(
                        f"decision=exact with decision.mode=lookup tabulates the exact psi over "
                        f"the model's signal bounds; model {setup.model.name!r} declares none: "
                        f"give them (a yaml model's `signal_bounds: {{<input>: [lo, hi]}}`, the "
                        f"range scripts/inspect_model.py measures) or use decision.mode=direct"
                    )
            lumps = d.get("lumps", "phi")
            if lumps not in LUMPINGS:
                raise ConfigError(f"decision.lumps must be one of {list(LUMPINGS)}, got {lumps!r}")
            if lumps == "classes" and (
                history != "none" or mode != "lookup" or not can_classify(internal)
                or exact_class_step_of(internal) is None or len(internal.signal_names) != 1
            ):  # fmt: skip
                raise ConfigError(
                    f"decision.lumps=classes needs decision.mode=lookup, no clock and a model "
                    f"with classes and their exact law over one signal (exact_class_step); "
                    f"model {setup.model.name!r}, mode {mode!r}, history {history!r}"
                )
            return cls(name, d, mode, sizes, history=history, max_age=max_age, lumps=lumps)
        train_field = str(d.get("train_field"))
        train_cfg = {**to_dict(cfg), "field": field_config(train_field)}  # unknown -> ConfigError
        train = TrainSettings.from_config(train_cfg)
        sizes = None
        if train.lumps == "classes" and mode != "lookup":
            raise ConfigError(
                "gp.lumps=classes: the K-lumps chain is a table (decision.mode=lookup), it has "
                f"no classifier mode; got decision.mode={mode!r}. The two-state chain has one: "
                "add gp=svgp (the default, gp=auto, runs K lumps for a model with classes)"
            )
        if mode == "lookup":
            if len(train.inputs) > 3:
                raise ConfigError(
                    f"decision.mode=lookup tabulates at most 3 inputs, the abstraction has "
                    f"{list(train.inputs)}: use decision.mode=classifier"
                )
            sizes = grid_size(d.get("lookup_size"), "decision.lookup_size", len(train.inputs))
        start = resolve_start(d.get("initial", "internal"), train, "decision.initial")
        return cls(name, d, mode, sizes, train, train_field, start=start)

    def identity(self) -> dict[str, Any]:
        """What of the decision defines a run (the abstraction by its fit's identity: the
        diagnostic and the output grid do not change the psi a run uses)."""
        config = self.config
        if config.get("lumps", "phi") == "phi":  # runs keep the identity they had before K lumps
            config = {k: v for k, v in config.items() if k != "lumps"}
        # runs starting as before keep the identity they had before decision.initial
        config = {k: v for k, v in config.items() if k != "initial"}
        out: dict[str, Any] = {"decision": config}
        if self.train is not None:
            out["abstraction"] = self.train.fit_identity()
        if self.start != "internal":
            out["initial"] = self.start
        return out


def resolve_start(value: Any, train: TrainSettings, where: str) -> str:
    """``decision.initial`` (or ``fidelity.initial``), validated: ``internal`` (the internal
    model's initial law, as the full model's cells start) or ``stationary`` (a K-lumps chain's
    own stationary law at the inputs, no internal state simulated: a network's burn-in is not
    paid, but the start is only as good as the chain's stationary law; docs/fidelity.md)."""
    if value not in STARTS:
        raise ConfigError(f"{where} must be one of {list(STARTS)}, got {value!r}")
    if value == "stationary" and train.lumps != "classes":
        raise ConfigError(
            f"{where}=stationary starts a K-lumps chain from its stationary law (gp=classes); "
            f"the two-state chain starts from the internal model's initial law: use "
            f"{where}=internal"
        )
    return str(value)
