"""A toy chain kind defined outside the package, as a newcomer's kind is: this one module (its
class, registered with :func:`register_chain_kind`) and one yaml (:data:`TOY_YAML`, a recipe
under ``conf/gp/``) and nothing else. It is a chain over phi whose fit is its own (the share of
switches out of each phi, no GP), written as its own file, and whose layer reads that file and
records that it was used."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import pandas as pd
import torch

from surrogate.errors import ConfigError
from surrogate.gp.training import GPSettings
from surrogate.kinds.base import ChainKind, LayerRequest
from surrogate.simulate.decision import AbstractDecision, DecisionLayer

#: the kind's recipe, conf/gp/toy.yaml
TOY_YAML = """\
defaults:
  - svgp
  - _self_

lumps: toy
toy_floor: 0.01
"""
TOY_FILE = "toy_chain.json"


@dataclass(frozen=True)
class ToyChain(ChainKind):
    """A two-state chain with a constant psi per phi, fitted by counting."""

    lumps = "toy"
    gp_keys = ("toy_floor",)
    title = "toy"
    recipe = "toy"
    files = (TOY_FILE,)
    #: what the kind's methods were asked for (the test reads it)
    calls: ClassVar[list[str]] = []

    def configure(
        self,
        gp_config: Mapping[str, Any],
        gp: GPSettings,
        inputs: tuple[str, ...],
        internal: Any,
        model_name: str,
    ) -> tuple[GPSettings, tuple[str, ...]]:
        floor = gp_config.get("toy_floor", 0.01)
        if not isinstance(floor, float) or not 0 < floor < 0.5:
            raise ConfigError(f"gp.toy_floor must be in (0, 0.5), got {floor!r}")
        self.calls.append("configure")
        return gp, inputs

    def label(self) -> dict[str, Any]:
        return {"lumps": self.lumps}

    def fit(
        self, settings: Any, table: pd.DataFrame, domain: Mapping[str, tuple[float, float]]
    ) -> tuple[dict[str, Any], dict[str, Any]] | None:
        self.calls.append("fit")
        floor = settings.gp_config["toy_floor"]
        run = [float(table.loc[table["phi"] == phi, "phi_next"].mean()) for phi in (0, 1)]
        return {"run": [min(max(p, floor), 1 - floor) for p in run]}, {"rows": len(table)}

    def write(
        self,
        directory: Path,
        fitted: tuple[dict[str, Any], dict[str, Any]] | None,
        identity: Mapping[str, Any],
    ) -> dict[str, Any]:
        assert fitted is not None
        self.calls.append("write")
        state, metrics = fitted
        (directory / TOY_FILE).write_text(json.dumps({**state, "settings": dict(identity)}))
        return {"toy": metrics}

    def load(self, directory: str | os.PathLike, device: str | torch.device = "cpu") -> Any:
        self.calls.append("load")
        return json.loads((Path(directory) / TOY_FILE).read_text())

    def decision_layer(
        self, request: LayerRequest, directory: Path
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        self.calls.append("decision_layer")
        run = torch.tensor(self.load(directory)["run"], device=request.device)

        def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
            return run[phi.long()]

        layer = AbstractDecision(psi, request.model.internal, None, "toy")
        return layer, {"inputs": [], "lumps": self.lumps}
