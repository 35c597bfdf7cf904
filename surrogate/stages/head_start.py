"""reproduce's head start: its worker process starts from the composed config, before this
process imports torch.

``scripts/reproduce.py`` spends its first ~2.5 s importing torch, pandas and scipy. A worker
started first (:class:`~surrogate.stages.background.Worker`; its own imports take as long, on
the other core) validates the same config and makes what the learned psi does not change, in
the order it is needed (:func:`surrogate.stages.reproduce.prepare`): the collection (the train
stage here waits for it, under the artefact's lock, then reuses it), the diagnostic's occupancy
run, the runs of the full model and of the exact psi. This module imports nothing heavy.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from omegaconf import DictConfig, OmegaConf

from surrogate.stages.background import Worker, worker_threads

log = logging.getLogger(__name__)


def head_start(cfg: DictConfig, launcher: Mapping[str, Any]) -> Worker | None:
    """Start the worker of a reproduce job on ``prepare(cfg)`` where the config asks for one
    (``batch`` and ``background``: true, or auto with two or more threads for this job); None
    otherwise, also for a config the job will refuse (its own validation says why). ``cfg``
    must be final: the job's per-job adjustments (:func:`surrogate.cli.prepare_config`) done."""
    from surrogate.cli import available_cores, resolve_threads
    from surrogate.errors import ConfigError

    setting = cfg.get("background", "auto")
    if cfg.get("batch", True) is not True or setting not in (True, "auto"):
        return None
    try:
        threads = resolve_threads(cfg, launcher) or available_cores()
    except ConfigError:
        return None
    if setting == "auto" and threads < 2:
        return None
    worker = Worker(worker_threads(threads))
    worker.submit(prepare_in_worker, OmegaConf.to_container(cfg, resolve=True))
    log.info("in a background process (%d thread(s)): the collection, then what needs no "
             "abstraction (the full model's and the exact psi's runs)", worker.threads)  # fmt: skip
    return worker


def prepare_in_worker(config: dict[str, Any]) -> None:
    """The worker's side: :func:`surrogate.stages.reproduce.prepare` (imported here, in the
    worker, so that sending this job imports nothing heavy in the parent)."""
    from surrogate.stages.reproduce import prepare

    prepare(config)


__all__ = ["head_start", "prepare_in_worker"]
