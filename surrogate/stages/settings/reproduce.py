"""Settings of the reproduce stage: collect -> train -> simulate and evaluate on several
fields -> report, with the small runs marked as one batch."""

from __future__ import annotations

import functools
import hashlib
import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from surrogate.config import build_field, field_config, field_name, group_config, to_dict
from surrogate.errors import ConfigError, SurrogateError
from surrogate.grid import is_coupled
from surrogate.io import artefact_dir
from surrogate.models.capabilities import has_exact_psi, signal_bounds_of
from surrogate.models.network import direct_exact_step_seconds
from surrogate.stages.settings.common import EVALUATE_CMD, REPRODUCE_CMD, Job, command_line
from surrogate.stages.settings.evaluate import EvaluateSettings
from surrogate.stages.settings.simulate import SimulateSettings
from surrogate.stages.settings.train import TrainSettings

log = logging.getLogger(__name__)

#: why ``background`` is refused: its second process was removed (issue 28, docs/performance.md)
REMOVED_BACKGROUND = (
    "background was removed: reproduce's second process gained nothing measurable end to end "
    "and slowed the fit under load (docs/performance.md); drop the setting"
)


#: the most seconds reproduce spends on a directly computed exact chain before skipping it
DIRECT_EXACT_MAX_SECONDS = 120.0


def _direct_affordable(c: Mapping[str, Any], internal: Any) -> bool:
    """False (with a warning saying how to have it) where the exact chain would be computed
    directly, the model declaring no signal bounds to tabulate it over, and its estimated cost
    exceeds :data:`DIRECT_EXACT_MAX_SECONDS`."""
    space = getattr(internal, "state_space", None)
    if signal_bounds_of(internal) is not None or space is None:
        return True
    fields = len(c.get("fields") or [])
    steps = (float(c.get("t_end", 0.0)) + float(c.get("equilibration_time", 0.0))) / float(c["dt"])
    per_step = direct_exact_step_seconds(internal)
    seconds = fields * int(c.get("n_cells", 0)) * steps * per_step
    if seconds <= DIRECT_EXACT_MAX_SECONDS:
        return True
    log.warning(
        "reproduce: the exact-psi chain skipped: without signal bounds it computes exp(Q dt) of "
        "the %d-state generator at each cell's inputs, ~%.3g s per cell-step, ~%.3g s for "
        "these runs; give the model its signal bounds (a yaml's `signal_bounds: {<input>: "
        "[lo, hi]}`, the input range scripts/inspect_model.py reports) to tabulate it, or set "
        "exact_psi=false", space.n_states, per_step, seconds,
    )  # fmt: skip
    return False


@dataclass(frozen=True, eq=False)
class ReproduceSettings:
    """collect -> train -> simulate and evaluate on several fields -> report."""

    train: TrainSettings
    evaluations: dict[str, EvaluateSettings]
    exact: dict[str, EvaluateSettings]
    job: Job
    #: every run of the report in one batch (``batch``)
    batch: bool = True

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
        refuse_coupled(c, fields)
        for key in ("batch", "exact_psi", "exact_psi_figures"):
            if not isinstance(c.get(key, True), bool):
                raise ConfigError(f"{key} must be true or false, got {c[key]!r}")
        if c.get("background") is not None:
            raise ConfigError(REMOVED_BACKGROUND)
        evaluations = {
            name: EvaluateSettings.from_config(_field_run(c, name, c["decision"]))
            for name in fields
        }
        train = next(iter(evaluations.values())).candidate.decision.train
        if train is None:
            raise ConfigError("reproduce needs decision=abstract (the learned abstraction)")
        exact = {}
        internal = train.setup.model.internal
        if c.get("exact_psi") and has_exact_psi(internal) and _direct_affordable(c, internal):
            decision = {**group_config("decision", "exact")}
            if signal_bounds_of(internal) is None:
                # a table needs the signal's bounds (a yaml's `signal_bounds`); without them
                # the exact chain computes exp(Q dt) at each cell's inputs
                decision["mode"] = "direct"
            # the report shows the abstraction's figures only; the exact chain's are optional
            figures = {"figures": bool(c.get("exact_psi_figures", False))}
            exact = {
                name: EvaluateSettings.from_config(_field_run(c, name, decision, **figures))
                for name in fields
            }
        if c.get("batch", True) and c.get("compile", False):
            evaluations, exact = _batched(evaluations, exact)
        return cls(train, evaluations, exact, Job.from_config(cfg), c.get("batch", True))

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


def refuse_coupled(cfg: dict[str, Any], fields: list[str]) -> None:
    """Refuse, before any work, a coupled field (the cells change it: experiment=band's
    travelling band) given as ``field`` or listed in ``fields``: reproduce's report compares
    given fields and shows no band (profiles, front, speed against mass balance, band checks),
    and its ``fields`` would silently win over an experiment's ``field``. The error names the
    evaluate command that makes the band's evaluation for these settings.

    Raises:
        ConfigError: a coupled field, naming that command.
    """
    candidates = {f"field={field_name(cfg['field'])}": cfg}
    candidates.update({f"fields: {n}": {**cfg, "field": field_config(n)} for n in fields})
    coupled = [(where, c) for where, c in candidates.items() if is_coupled(build_field(c["field"]))]
    if not coupled:
        return
    where, c = coupled[0]
    name = field_name(c["field"])
    run_missing = {**c, "evaluate": {**c["evaluate"], "run_missing": True}}
    try:  # the command for these very settings (n_cells, t_end, the abstraction's gp, ...)
        command = EvaluateSettings.from_config(run_missing).command()
    except SurrogateError:  # any other error of the settings is evaluate's to report
        command = f"{EVALUATE_CMD} field={name} decision=abstract"
    raise ConfigError(
        f"reproduce compares given fields ({', '.join(fields)}) in one report without a band; "
        f"{where} is coupled (the cells change it: a travelling band), and its evaluation "
        f"(profiles, the front, its speed against mass balance, kymographs, the band's checks "
        f"against the noise floor) is evaluate's: run `{command} evaluate.run_missing=true` "
        f"(experiment=band: `{EVALUATE_CMD} experiment=band decision=abstract "
        f"evaluate.run_missing=true`; docs/fields.md)"
    )


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
    made_by = command_line(REPRODUCE_CMD, keep)

    def tagged(e: EvaluateSettings) -> EvaluateSettings:
        def mark(s: SimulateSettings) -> SimulateSettings:
            return s.replace(batch=batch, made_by=made_by) if batchable(s) else s

        repeat = e.full_repeat
        return replace(e, candidate=mark(e.candidate), full=mark(e.full),
                       full_repeat=None if repeat is None else mark(repeat))  # fmt: skip

    return ({k: tagged(v) for k, v in evaluations.items()},
            {k: tagged(v) for k, v in exact.items()})  # fmt: skip


def _field_run(
    cfg: dict[str, Any], name: str, decision: Mapping[str, Any], **evaluate: Any
) -> dict[str, Any]:
    """The evaluate config for one field: same settings, that field, missing runs simulated
    (and any other ``evaluate`` options given)."""
    return {**cfg, "field": field_config(name), "decision": dict(decision),
            "evaluate": {**cfg["evaluate"], **evaluate, "run_missing": True}}  # fmt: skip
