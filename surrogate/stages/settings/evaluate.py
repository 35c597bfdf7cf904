"""Settings of the evaluate stage: a candidate run vs a full run and the noise floor."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from surrogate.config import positive, to_dict
from surrogate.errors import ConfigError
from surrogate.grid import GridField
from surrogate.io import artefact_dir
from surrogate.stages.settings.common import EVALUATE_CMD, Job, command_line
from surrogate.stages.settings.simulate import SimulateSettings


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
        if candidate.decision.kind.full:
            raise ConfigError(
                "evaluate compares an abstraction with the full model: use decision=abstract "
                "(or decision=exact)"
            )
        e = to_dict(cfg["evaluate"])
        # the full run: the candidate's setup (in a scaled field, with another seed: below)
        full_cfg = {**cfg, "decision": {"name": "full"}}
        setup = candidate.setup
        if e.get("full_n_cells") is not None:  # the full model on fewer cells (large runs)
            full_n = int(positive(e, "full_n_cells", "evaluate.", integer=True))
            full_cfg["n_cells"] = full_n
            setup = setup.with_field(scaled_field(candidate, full_n))
        full_seed = e.get("full_seed")
        if full_seed is not None:  # candidates of several training seeds against one full run
            if isinstance(full_seed, bool) or not isinstance(full_seed, int) or full_seed < 0:
                raise ConfigError(f"evaluate.full_seed must be a non-negative integer or null "
                                  f"(null: seed), got {full_seed!r}")  # fmt: skip
            setup = setup.with_seed(full_seed)
        full = SimulateSettings.from_config(full_cfg, setup, candidate.job)
        positive(e, "band_factor", "evaluate.")
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
            seed = full.setup.seed
            # offset 0 would compare the full run with itself: a noise floor of exactly zero
            if (
                isinstance(offset, bool)
                or not isinstance(offset, int)
                or offset == 0
                or seed + offset < 0
            ):
                raise ConfigError(
                    f"evaluate.noise_seed_offset must be a non-zero integer with seed + offset "
                    f">= 0 (the noise floor's second full run uses seed + offset; seed: "
                    f"evaluate.full_seed where set), got {offset!r}"
                )
            repeat = full.replace(seed=seed + offset)
        options = {k: v for k, v in e.items() if k != "run_missing"}
        return cls(candidate, full, repeat, times, subsample, options,
                   bool(e.get("run_missing", False)), candidate.job)  # fmt: skip

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
        return command_line(EVALUATE_CMD, self.candidate.overrides())


def scaled_field(candidate: SimulateSettings, full_n: int) -> dict[str, Any]:
    """The full runs' field config for ``full_n`` cells against the candidate's ``n_cells``.

    A given field is the candidate's. A coupled grid field has its ``depth`` scaled by
    ``full_n / n_cells``, so that both populations put the same cells per unit cross-section
    into the channel: uptake per volume, the only thing the field's dynamics sees
    (docs/fields.md, "A travelling band"), so each full cell stands for more bacteria. The depth
    is rounded to 12 significant digits, so that it equals the number a user types for the same
    run (``field.depth=0.032``) and the run is found again.
    """
    field = to_dict(candidate.setup.field_config)
    grid_field = candidate.setup.field
    if not isinstance(grid_field, GridField) or full_n == candidate.n_cells:
        return field
    depth = float(grid_field.grid.depth) * full_n / candidate.n_cells
    return {**field, "depth": float(f"{depth:.12g}")}
