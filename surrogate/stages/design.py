"""Sequential design of the collect stage (``collect.design.target_error``): rounds until the
learned psi is known to the target where the population lives.

Each round adds ``collect.n_per_state`` transitions per origin state from the same perturbed
population (:class:`~surrogate.simulate.transitions.TransitionCollector`), fits psi on everything
so far with the gp group's recipe and scores it by its own posterior: the relative sd of psi,
``sd / psi``, averaged over the rows of an unperturbed occupancy run (the train diagnostic's,
shared with it). The design stops when both origins are at or below the target, or after
``max_rounds`` (a warning; the manifest says ``target_met: false``). From the second round on,
jumps are guided to where occupancy x posterior sd is largest
(:class:`~surrogate.simulate.design.GuidedJump`), so the budget goes where it lowers the error
where cells live; a share ``explore`` of jumps stays as drawn, for fields not trained on.

The posterior treats expected labels as Bernoulli trials, so with them it overstates the error
(their variance is several times smaller, README "Fewer full-model samples"): the design stops
late rather than early.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import pandas as pd
import torch

from surrogate.gp.fast import CachedPsi
from surrogate.gp.predictor import fit_psi
from surrogate.models.base import Perturbation
from surrogate.simulate.design import Acquisition, GuidedJump
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import TransitionCollector
from surrogate.stages.occupancy import occupancy
from surrogate.stages.settings import CollectSettings

log = logging.getLogger(__name__)


def posterior_error(psi: CachedPsi, rows: pd.DataFrame, names: list[str]) -> list[float]:
    """Per origin state: the mean of ``sd / psi`` (posterior sd of psi over psi) over the
    ``rows`` (an occupancy run's) that start in it."""
    out = []
    for p in (0, 1):
        part = rows[rows["phi"] == p]
        if part.empty:
            out.append(float("nan"))
            continue
        z = torch.from_numpy(part[names].to_numpy(np.float32, copy=True))
        value, sd = psi.spread(torch.full((len(part),), p), z)
        out.append(float((sd / value.clamp_min(1e-12)).double().mean()))
    return out


def collect_in_rounds(
    settings: CollectSettings, simulator: Simulator, perturbation: Perturbation, **collector: Any
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Collect in rounds until the target holds (see the module docstring).

    Args:
        settings: collect settings with a design (``settings.design`` not None).
        simulator: the full model's simulator.
        perturbation: the body's perturbation (proposes the guided jumps' destinations).
        collector: the rest of :class:`TransitionCollector`'s arguments.

    Returns:
        The table of every round and the design's record for the manifest (rounds, each with
        its rows per origin, posterior errors and seconds; the target and whether it was met).
    """
    design, options = settings.design, settings.options["design"]
    assert design is not None
    target = float(options["target_error"])
    model, job = settings.setup.model, settings.job
    names = list(design.inputs)
    occupied = occupancy(design.occupancy())
    per_round = int(settings.options["n_per_state"])
    featurize = model.featurizer(names)
    collected = TransitionCollector(simulator, perturbation, progress=job.progress, **collector)
    tables: list[pd.DataFrame] = []
    rounds: list[dict[str, Any]] = []
    met = False
    for r in range(int(options["max_rounds"])):
        t0 = time.perf_counter()
        tables.append(collected.take(per_round))
        table = pd.concat(tables, ignore_index=True)
        sim_s = time.perf_counter() - t0
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(design.fit_threads or threads)
            psi = fit_psi(table, names, design.gp, progress=False, device=job.device,
                          lump_names=model.internal.lump_names,
                          label=design.label_column(table.columns))  # fmt: skip
        finally:
            torch.set_num_threads(threads)
        cached = CachedPsi.from_classifier(psi.to("cpu"))
        errors = posterior_error(cached, occupied, names)
        met = all(e <= target for e in errors)
        rounds.append({"round": r + 1, "rows_per_origin": per_round * (r + 1),
                       "posterior_error": errors, "guided": collected.guide is not None,
                       "simulate_s": sim_s, "fit_s": time.perf_counter() - t0 - sim_s})  # fmt: skip
        log.info("design round %d: %d transitions per origin, posterior relative sd of psi where "
                 "cells live %.2f %% / %.2f %% (target %.2f %%)", r + 1, per_round * (r + 1),
                 100 * errors[0], 100 * errors[1], 100 * target)  # fmt: skip
        if met:
            break
        acquisition = Acquisition.from_posterior(
            cached.spread,
            torch.from_numpy(occupied["phi"].to_numpy(np.int64)),
            torch.from_numpy(occupied[names].to_numpy(np.float64, copy=True)),
        )
        options_ = settings.options["design"]
        collected.guide = GuidedJump(perturbation, model.body, simulator.field, featurize,
                                     acquisition, int(options_["candidates"]),
                                     float(options_["explore"]))  # fmt: skip
    if not met:
        log.warning("design: the target %.2f %% was not met in %d rounds (posterior errors "
                    "%s); raise collect.design.max_rounds or collect.n_per_state", 100 * target,
                    len(rounds), [round(100 * e, 2) for e in rounds[-1]["posterior_error"]])  # fmt: skip
    record = {"target_error": target, "target_met": met, "rounds": rounds,
              "rows_per_origin": per_round * len(rounds), "occupancy": str(design.occupancy().directory)}  # fmt: skip
    return pd.concat(tables, ignore_index=True), record


__all__ = ["collect_in_rounds", "posterior_error"]
