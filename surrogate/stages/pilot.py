"""The inspector's pilot: the measured choice of the chain kind (``gp=auto``, docs/choice.md) made
once at a small size, so that the inspector reports what the measurement picks instead of a
kind by rule (issue 52).

The pilot is the train stage's own choice (:func:`~surrogate.stages.choice.make_choice` with
:func:`~surrogate.stages.train.fit_candidate`) on the inspected config with a small collection
(``inspect.pilot.n_per_state`` per origin), a small held-out run (``inspect.pilot.n_cells``
cells for ``inspect.pilot.t_end`` s), every candidate fitted by L-BFGS and, among the clock's
caps, the one the hazard measured suggests (:func:`~surrogate.diagnosis.recommendation.
memory_facts`). Its collection and record are ordinary artefacts under the job's ``data_dir``:
their settings differ from a full run's, so their directories do too.

Before it runs, its simulation (the collection and the held-out run) is priced with the stages'
cost model (:mod:`surrogate.stages.budget`) at the events the inspection measured; where that
exceeds ``inspect.max_seconds`` the pilot is halved (rows and held-out cells, down to
:data:`MIN_ROWS` and :data:`MIN_CELLS`) until it fits, else skipped with the estimate. The fits
are not priced (the cost model prices simulation only).
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Mapping
from typing import Any

from surrogate.config import group_config, to_dict
from surrogate.diagnosis.cost import Work, duration, step_seconds
from surrogate.errors import ConfigError
from surrogate.io import read_json
from surrogate.kinds.chains import is_auto
from surrogate.kinds.scoring import clock_name
from surrogate.stages import budget
from surrogate.stages.choice import make_choice
from surrogate.stages.reproduce import choice_text, collection_blackout
from surrogate.stages.settings import CollectSettings, TrainSettings
from surrogate.stages.settings.choice import (
    CHOICE,
    RELAXING_FAMILY,
    ChoiceSettings,
    PendingChoice,
    collecting_pending,
)
from surrogate.stages.train import fit_candidate

log = logging.getLogger(__name__)

#: the smallest pilot the budget may shrink it to: rows per origin and held-out cells
MIN_ROWS = 2_000
MIN_CELLS = 20


def cap_name(age: float) -> str:
    """The candidate name of the switch clock at cap ``age`` (s), as
    :func:`~surrogate.stages.settings.choice.candidate_groups` names it."""
    return clock_name(age)


def pilot_config(
    config: Mapping[str, Any], n_per_state: int, n_cells: int, t_end: float, cap: float | None
) -> tuple[dict[str, Any], list[float], bool]:
    """The inspected ``config`` as the pilot runs it, the clock's caps it tries and whether
    ``cap`` is among them only by the pilot (not one of ``gp.choice.max_ages``).

    ``gp=auto`` (the user's group where it is auto, else the shipped one) measuring, with
    ``gp.choice``'s caps plus ``cap`` (the hazard's, where measured), ``n_cells`` held-out
    cells for ``t_end`` s (never grown), fitted by the choice's own ``gp.choice.optimizer``,
    nothing trained ahead, no K lumps whose bins relax (their stationary sample is a
    full-model run the pilot does not price); ``collect.n_per_state=n_per_state``."""
    cfg = copy.deepcopy(to_dict(config))
    cfg.pop("inspect", None)
    raw = cfg.get("gp") or {}
    gp = dict(raw) if is_auto(raw) else group_config("gp", "auto")
    ages = list(ChoiceSettings.from_config(gp.get("choice")).max_ages)
    added = cap is not None and float(cap) not in ages
    if cap is not None and added:
        ages.append(float(cap))
    # nothing trained ahead: the pilot trains no chain after its choice; no K lumps whose bins
    # relax: their stationary sample would cost the pilot a full-model run it does not price
    kinds = [k for k in ChoiceSettings.from_config(gp.get("choice")).kinds if k != RELAXING_FAMILY]
    # nor a held-out run grown: the pilot is priced at its cells, and recommends a kind
    gp["choice"] = {**(gp.get("choice") or {}), "by": "measure", "n_cells": int(n_cells),
                    "t_end": float(t_end), "max_ages": ages, "max_cells": int(n_cells),
                    "ahead": False, "kinds": kinds or [RELAXING_FAMILY]}  # fmt: skip
    cfg["gp"] = gp
    # no top-up: the pilot is priced as one collection, and its lag is what it reports (the
    # blackout it advises records settled rows in one pass, collect's top-up in two)
    cfg["collect"] = {**(cfg.get("collect") or {}), "n_per_state": int(n_per_state),
                      "top_up": "off"}  # fmt: skip
    return cfg, ages, added


def _plan(cfg: Mapping[str, Any]) -> tuple[TrainSettings, PendingChoice | None]:
    """The pilot's train settings and its choice where not stored yet (None: stored)."""
    with collecting_pending() as plans:
        train = TrainSettings.from_config(cfg)
    return train, (plans[0] if plans else None)


def pilot_work(train: TrainSettings, plan: PendingChoice | None, cell_step: float) -> list[Work]:
    """The pilot's simulations at ``cell_step`` s per full-model cell-step: its collection
    (unless stored) and the held-out run (unless the choice is stored)."""
    if plan is None:
        return []
    works: list[Work] = []
    if isinstance(train.source, CollectSettings):
        works += budget.collect_work(train.source, reuse=True, cell_step_seconds=cell_step)
    setup, c = train.setup, plan.settings
    fixed = step_seconds(setup.model, setup.field, setup.dt, "full", train.job.device)
    where = (f"inspect.pilot.n_cells={c.n_cells}, inspect.pilot.t_end={c.t_end:g} s + "
             f"gp.choice.equilibration_time={c.equilibration_time:g} s")  # fmt: skip
    works.append(Work("the pilot's held-out run", c.n_cells,
                      (c.t_end + c.equilibration_time) / setup.dt, cell_step, where,
                      setup.model.name, step_seconds=fixed))  # fmt: skip
    works += budget.burn_in_work(setup.model, c.n_cells, setup.dt, cell_step)
    return works


def run_pilot(
    config: Mapping[str, Any],
    pilot: Mapping[str, Any],
    max_seconds: float,
    cap: float | None,
    cell_step: float,
) -> dict[str, Any]:
    """Make (or reuse) the pilot's measured choice; return what it chose and how.

    Args:
        config: the inspected config (resolved).
        pilot: ``inspect.pilot`` validated (``enabled``, ``n_per_state``, ``n_cells``,
            ``t_end``).
        max_seconds: ``inspect.max_seconds``: the pilot's simulation is priced and shrunk to
            fit it, else skipped.
        cap: the switch clock's cap (s) the hazard suggests, added to the candidates; None.
        cell_step: the full model's cost per cell-step (s) at the events measured.

    Returns:
        ``{"ran": False, "note": why}`` where skipped; else ``ran``, ``chosen``, ``reason``,
        ``table`` (the choice's rows), ``named`` (the chosen candidate's overrides),
        ``max_ages``, ``cap``, ``cap_added``, the sizes it ran at, ``estimate_s``,
        ``wall_s``, ``directory``, ``text`` (the report's section), ``note`` and
        ``blackout`` (the collection collect advised where the pilot's rows lag a jump,
        :func:`~surrogate.stages.reproduce.collection_blackout`).
    """
    if not pilot["enabled"]:
        return {"ran": False, "note": "skipped (inspect.pilot.enabled=false)"}
    if config.get("transitions"):
        return {"ran": False, "note": f"skipped: the transitions are an external table "
                f"(transitions={config['transitions']}), so there is no full model to collect "
                f"from or hold out; name a kind (gp=svgp, gp=clock, ...)"}  # fmt: skip
    t0 = time.perf_counter()
    n, cells, t_end = int(pilot["n_per_state"]), int(pilot["n_cells"]), float(pilot["t_end"])
    notes: list[str] = []
    while True:
        cfg, ages, added = pilot_config(config, n, cells, t_end, cap)
        train, plan = _plan(cfg)
        estimate = sum(w.seconds for w in pilot_work(train, plan, cell_step))
        if estimate <= max_seconds or (n <= MIN_ROWS and cells <= MIN_CELLS):
            break
        smaller = max(MIN_ROWS, min(n, n // 2)), max(MIN_CELLS, min(cells, cells // 2))
        notes.append(f"{n:,} rows per origin and {cells} held-out cells would cost "
                     f"~{duration(estimate)} of simulation, over inspect.max_seconds="
                     f"{max_seconds:g}")  # fmt: skip
        n, cells = smaller
    if estimate > max_seconds:
        return {"ran": False, "estimate_s": estimate,
                "note": f"skipped: even at {n:,} rows per origin and {cells} held-out cells "
                        f"the pilot would cost ~{duration(estimate)} of simulation, over "
                        f"inspect.max_seconds={max_seconds:g} (raise it to run the pilot)"}  # fmt: skip
    if notes:
        notes = [f"shrunk to {n:,} rows per origin and {cells} held-out cells to fit the "
                 f"budget ({notes[0]})"]  # fmt: skip
    log.info("inspect: the pilot's measured choice, %d rows per origin, %d held-out cells x "
             "%g s, ~%s of simulation (inspect.pilot; docs/choice.md)", n, cells, t_end,
             duration(estimate))  # fmt: skip
    directory = make_choice(plan, fit_candidate, cfg) if plan is not None \
        else train.measured_choice()  # fmt: skip
    if directory is None:  # a stored choice resolves gp=auto; nothing else leaves it None
        raise ConfigError("the pilot's gp=auto did not resolve to a measured choice")
    record = read_json(directory / CHOICE, made_by="python3 scripts/inspect_model.py")
    return {"ran": True, "chosen": record["chosen"], "reason": record["reason"],
            "table": record["scores"], "named": str(record["overrides"]).split(),
            "max_ages": ages, "cap": cap, "cap_added": added, "n_per_state": n,
            "n_cells": cells, "t_end": t_end, "estimate_s": estimate,
            "wall_s": time.perf_counter() - t0, "directory": str(directory),
            "text": choice_text(directory), "note": "; ".join(notes),
            # whatever train would read: the blackout records as many settled rows as the
            # collection asks for, where train would leave the lagging ones out of its rows
            "blackout": list(collection_blackout(train, unless_left_out=False))}  # fmt: skip


def pilot_advice(config: Mapping[str, Any], pilot: Mapping[str, Any]) -> dict[str, Any]:
    """The inspector's recommendation from the pilot (:func:`run_pilot`): keep ``gp=auto``
    (it measures the same candidates at full size), with the overrides the inspected
    ``config`` needs for that (``gp=auto`` where another group is named, ``gp.choice.by=
    measure`` where the rule is set, and ``gp.choice.max_ages=[..., X]`` where the pilot chose
    the clock at the cap ``X`` it added from the hazard, or the log clock at twice it, which
    the choice adds from that clock); ``kind`` None where it did not run.
    The overrides are printed only once :func:`~surrogate.stages.advice_check.checked`."""
    if not pilot.get("ran"):
        return {"kind": None, "overrides": [], "named": [], "reason": pilot.get("note", "")}
    raw = config.get("gp") or {}
    overrides = [] if is_auto(raw) else ["gp=auto"]
    gp = raw if is_auto(raw) else group_config("gp", "auto")
    if ChoiceSettings.from_config(gp.get("choice")).by != "measure":
        overrides.append("gp.choice.by=measure")
    # the clock at the cap it added, or the log clock the choice adds from it at twice the cap
    cap = pilot.get("cap")
    from_cap = () if cap is None else (cap_name(cap), clock_name(2.0 * cap, log_axis=True))
    if pilot["cap_added"] and pilot["chosen"] in from_cap:
        overrides.append(f"gp.choice.max_ages=[{','.join(f'{a:g}' for a in pilot['max_ages'])}]")
    return {"kind": pilot["chosen"], "overrides": overrides, "named": list(pilot["named"]),
            "reason": pilot["reason"], "blackout": list(pilot.get("blackout") or [])}  # fmt: skip


__all__ = ["MIN_CELLS", "MIN_ROWS", "cap_name", "pilot_advice", "pilot_config", "pilot_work",
           "run_pilot"]  # fmt: skip
