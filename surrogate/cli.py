"""The wrapper every script in ``scripts/`` runs its stage through.

It sets torch's thread count (setting ``threads``), configures logging, runs the stage and records
the outcome in ``job_status.json`` in the job's Hydra output directory. In a multirun (``-m``) a
failing job is logged and recorded as failed instead of raising, because Hydra's launchers abort
the whole sweep when one job raises; ``scripts/summarize.py`` reports the failures afterwards. In a
single run errors reach the user: a :class:`~surrogate.errors.SurrogateError` (a bad setting, a
missing artefact) as one line ``error: <message>`` and exit code 2, anything else as a traceback.
"""

from __future__ import annotations

import atexit
import datetime
import logging
import os
import platform
import sys
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from surrogate.errors import ConfigError, SurrogateError

log = logging.getLogger(__name__)

EXIT_USER_ERROR = 2

JOBLIB_TARGET = "JoblibLauncher"
SUBMITIT_TARGET = "hydra_submitit_launcher"

# Libraries that log at INFO/DEBUG on import or on every figure; their chatter hides ours.
QUIET_LOGGERS = ("matplotlib", "PIL", "fsspec", "urllib3", "numexpr")


@dataclass
class JobContext:
    """Where and how a stage runs: filled from Hydra's runtime config, or by hand in tests."""

    multirun: bool = False
    output_dir: Path | None = None
    overrides: list[str] = field(default_factory=list)
    launcher: dict[str, Any] = field(default_factory=dict)
    job_num: int | None = None
    job_id: str | None = None
    original_cwd: Path | None = None


def hydra_context() -> JobContext:
    """The context of the running Hydra job (an empty single-run context outside Hydra)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return JobContext()
    # hydra types get() as its HydraConf schema; at run time it is the DictConfig node (whose
    # .get and `in` this reads: unset keys such as job.num in a single run are MISSING)
    hc: DictConfig = HydraConfig.get()  # type: ignore[assignment]
    launcher: Any = OmegaConf.to_container(hc.launcher, resolve=False) if "launcher" in hc else {}
    num = hc.job.get("num")
    return JobContext(
        multirun=hc.mode == RunMode.MULTIRUN,
        output_dir=Path(hc.runtime.output_dir) if hc.runtime.get("output_dir") else None,
        overrides=[str(o) for o in hc.overrides.task],
        launcher=launcher if isinstance(launcher, dict) else {},
        job_num=int(num) if num is not None else None,
        job_id=str(hc.job.get("id")) if hc.job.get("id") is not None else None,
        original_cwd=Path(hc.runtime.cwd) if hc.runtime.get("cwd") else None,
    )


def task_overrides() -> list[str]:
    """The command-line overrides of the running Hydra job (empty outside Hydra)."""
    return hydra_context().overrides


def available_cores() -> int:
    """CPU cores this process may run on (the affinity mask, so SLURM/cgroup limits count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def default_threads(launcher: Mapping[str, Any], cores: int | None = None) -> int | None:
    """Torch threads per job when ``threads`` is null: enough to fill, not oversubscribe, the
    cores.

    * ``hydra/launcher=joblib``: ``max(1, cores // n_jobs)`` (``n_jobs=-1`` means one job per
      core, as in joblib, so one thread each);
    * ``hydra/launcher=submitit_*``: ``cpus_per_task`` when set;
    * otherwise ``None``: torch's own default (all cores), right for one job at a time.
    """
    target = str(launcher.get("_target_", ""))
    cores = available_cores() if cores is None else cores
    if target.endswith(JOBLIB_TARGET):
        n_jobs = int(launcher.get("n_jobs") or -1)
        if n_jobs < 0:  # joblib: -1 = all cores, -2 = all but one, ...
            n_jobs = max(1, cores + 1 + n_jobs)
        return max(1, cores // n_jobs)
    if SUBMITIT_TARGET in target and launcher.get("cpus_per_task"):
        return int(launcher["cpus_per_task"])
    return None


def resolve_threads(cfg: Mapping[str, Any], launcher: Mapping[str, Any]) -> int | None:
    """The thread count a job uses: setting ``threads``, else the launcher's default."""
    threads = cfg.get("threads")
    if threads is None:
        return default_threads(launcher)
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"threads must be a positive integer or null, got {threads!r}")
    return threads


def configure_logging() -> None:
    """INFO logging for surrogate (Hydra has set up the handlers; outside Hydra add one),
    Python warnings routed into the job log, noisy libraries at WARNING."""
    root = logging.getLogger()
    if not root.handlers:
        logging.basicConfig(
            level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"
        )
    logging.getLogger("surrogate").setLevel(logging.INFO)
    logging.captureWarnings(True)
    for name in QUIET_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)


def prepare_config(cfg: DictConfig, ctx: JobContext) -> None:
    """Per-job adjustments that do not change any result (none enters a settings hash).

    * A relative ``data_dir`` is anchored at the directory the command was started from, so a
      launcher or ``hydra.job.chdir=true`` that changes the working directory still finds and
      shares the same artefacts.
    * In a multirun, progress bars are off unless ``progress`` was overridden: parallel jobs'
      bars interleave on one terminal and fill SLURM logs.
    """
    data_dir = cfg.get("data_dir")
    if (
        data_dir is not None
        and ctx.original_cwd is not None
        and not Path(str(data_dir)).is_absolute()
        and Path.cwd().resolve() != ctx.original_cwd.resolve()
    ):
        cfg.data_dir = str(ctx.original_cwd / str(data_dir))
    if ctx.multirun and "progress" in cfg and not _overridden("progress", ctx.overrides):
        cfg.progress = False


def _overridden(key: str, overrides: list[str]) -> bool:
    return any(o.lstrip("+~").split("=", 1)[0] == key for o in overrides)


def exit_when_done(code: int = 0) -> NoReturn:
    """End a script's process once its work is done, without the interpreter's teardown.

    Python's shutdown frees every module and object one by one: ~0.3 s with torch imported and
    0.7-1.5 s after a pipeline run (measured), time a user waits for the prompt with nothing
    left to do. The exit handlers still run (logging flushes and closes its handlers), the
    standard streams are flushed, then ``os._exit``. Nothing written depends on it: every
    artefact is complete on disk (written, renamed into place, manifest last) before its stage
    returns. Called only from the scripts' ``__main__`` blocks, after Hydra returns. While
    another non-daemon thread lives (e.g. a joblib launcher's executor manager), whose shutdown
    the interpreter orders before the exit handlers, the normal exit runs instead.
    """
    main = threading.main_thread()
    if any(t is not main and t.is_alive() and not t.daemon for t in threading.enumerate()):
        sys.exit(code)
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed or broken stream: nothing left to save
                pass
        os._exit(code)


def run_stage(name: str, stage: Callable[[DictConfig], Any], cfg: DictConfig) -> str | None:
    """Run ``stage(cfg)`` as a Hydra job; return its artefact directory (``None`` if it failed
    in a multirun). See the module docstring for what happens on failure."""
    return execute(name, stage, cfg, hydra_context())


def execute(
    name: str, stage: Callable[[DictConfig], Any], cfg: DictConfig, ctx: JobContext
) -> str | None:
    """:func:`run_stage` with an explicit context (testable without a Hydra runtime)."""
    started = datetime.datetime.now().astimezone()
    t0 = time.perf_counter()
    threads: int | None = None
    try:
        configure_logging()
        threads = resolve_threads(cfg, ctx.launcher)
        if threads is not None:
            import torch  # here, not at import: this module imports nothing heavy

            torch.set_num_threads(threads)
        prepare_config(cfg, ctx)
        result = stage(cfg)
    except Exception as exc:
        status = _status(name, ctx, started, t0, threads, exc=exc)
        _write_status(ctx, status)
        if ctx.multirun:
            # The job's log keeps the traceback of unexpected errors; ours are explained already.
            if isinstance(exc, SurrogateError):
                log.error("job %s failed: %s: %s", ctx.job_num, type(exc).__name__, exc)
            else:
                log.exception("job %s failed", ctx.job_num)
            return None
        if isinstance(exc, SurrogateError):
            print(f"error: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(EXIT_USER_ERROR) from None
        raise
    out = Path(result).resolve() if result is not None else None
    _write_status(ctx, _status(name, ctx, started, t0, threads, artefact_dir=out))
    return str(out) if out is not None else None


def _status(
    name: str,
    ctx: JobContext,
    started: datetime.datetime,
    t0: float,
    threads: int | None,
    *,
    artefact_dir: Path | None = None,
    exc: BaseException | None = None,
) -> dict[str, Any]:
    return {
        "status": "failed" if exc is not None else "ok",
        "stage": name,
        "job_num": ctx.job_num,
        "job_id": ctx.job_id,
        "overrides": list(ctx.overrides),
        "artefact_dir": str(artefact_dir) if artefact_dir is not None else None,
        "error_type": type(exc).__name__ if exc is not None else None,
        "error": str(exc) if exc is not None else None,
        "traceback": (
            "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
            if exc is not None
            else None
        ),
        "wall_time_s": time.perf_counter() - t0,
        "threads": threads if threads is not None else _torch_threads(),
        "host": platform.node(),
        "pid": os.getpid(),
        "started": started.isoformat(timespec="seconds"),
        "finished": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
    }


def _torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def _write_status(ctx: JobContext, status: dict[str, Any]) -> None:
    if ctx.output_dir is None:
        return
    from surrogate.io import JOB_STATUS, write_json

    try:
        write_json(ctx.output_dir / JOB_STATUS, status)
    except OSError as exc:  # a full or read-only disk must not hide the job's own outcome
        log.warning("could not write %s: %s", ctx.output_dir / JOB_STATUS, exc)


class SweepSummaryCallback(Callback):
    """Hydra callback (``hydra.callbacks`` in conf/common.yaml): at the end of a multirun, write
    the sweep's ``summary.csv`` / ``summary.png`` and log how many jobs failed."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Summarise the sweep directory; never raises (the jobs' results are on disk anyway)."""
        if not self.enabled:
            return
        sweep_dir = Path(str(config.hydra.sweep.dir))
        try:
            from surrogate.sweep import summarize

            summarize(sweep_dir)
        except Exception:
            log.exception(
                "could not summarise %s; run `python scripts/summarize.py %s`", sweep_dir, sweep_dir
            )
