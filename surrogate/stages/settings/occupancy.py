"""Settings of the occupancy run: where an unperturbed full-model population lives (the
train diagnostic's weights)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from surrogate.io import artefact_dir
from surrogate.stages.settings.common import Job, ModelSetup


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
