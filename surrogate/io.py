"""Artefact paths, manifests and atomic writes.

Every stage writes into a directory derived from the settings that define its output, so stages
chain without passing paths and sweep jobs never collide. Every file is written to a temporary
name in the same directory and renamed into place, so a killed job leaves either the previous
complete file or none.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import tempfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pandas as pd
import torch

from surrogate import __version__
from surrogate.errors import ArtefactError, MissingArtefactError

try:  # POSIX only; without it stages run unlocked and leave stale temporaries alone
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
JOB_STATUS = "job_status.json"  # a Hydra job's outcome, written by surrogate.cli
LOCK = ".lock"
TMP_GLOB = ".*.tmp"

# mkstemp creates 0600 files; artefacts get the permissions a plain open() would give them.
_UMASK = os.umask(0)
os.umask(_UMASK)


# ----------------------------------------------------------------------------------------------
# atomic writes


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it onto ``path``.

    On any exception (or a kill) the temporary file is removed or left under a ``.tmp`` name
    that no loader reads, and ``path`` keeps its previous content.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        publish(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def publish(tmp_path: str | os.PathLike[str], path: str | os.PathLike[str]) -> None:
    """Make a finished temporary file the artefact ``path``: usual permissions (mkstemp gives
    0600), flushed to disk, then renamed into place in one atomic step."""
    os.chmod(tmp_path, 0o666 & ~_UMASK)
    with open(tmp_path, "rb") as fh:  # flush to disk before the rename makes it visible
        os.fsync(fh.fileno())
    os.replace(tmp_path, path)
    fsync_directory(Path(path).parent)  # the rename itself survives a crash only once synced


def fsync_directory(directory: str | os.PathLike[str]) -> None:
    """Flush a directory's entries (e.g. a rename into it) to disk, where the OS allows it."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # pragma: no cover - e.g. Windows cannot open directories
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - some file systems refuse fsync on directories
        pass
    finally:
        os.close(fd)


def clean_stale_tmp(directory: str | os.PathLike[str]) -> list[Path]:
    """Remove the ``.*.tmp`` files a killed run left in ``directory``; return what was removed.

    Only safe while no other process writes into ``directory``: call it under
    :func:`artefact_lock` (which does), never on a directory another job may be writing.
    """
    directory = Path(directory)
    removed = []
    for tmp in sorted(directory.glob(TMP_GLOB)):
        if tmp.is_file():
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    if removed:
        log.info(
            "removed %d stale temporary file(s) of a killed run in %s", len(removed), directory
        )
    return removed


@contextmanager
def artefact_lock(directory: str | os.PathLike[str]) -> Iterator[Path]:
    """Hold an exclusive lock on a stage's artefact directory while the stage writes it.

    Two jobs with the same settings (hence the same directory) take turns instead of writing
    the same files at once; the second should re-check the manifest once it has the lock. The
    lock (``flock`` on ``directory/.lock``) is released by the kernel when its holder dies, even
    by SIGKILL, so every ``.*.tmp`` file found while holding it belongs to a dead run and is
    removed. Where ``flock`` is unsupported (e.g. some network file systems) the stage runs
    unlocked and stale temporaries are left in place (no loader reads them). Not re-entrant:
    taking it twice on one directory in one process blocks forever.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if fcntl is None:  # pragma: no cover - Windows
        yield directory
        return
    with open(directory / LOCK, "a+b") as fh:
        locked = _flock(fh.fileno(), directory)
        try:
            if locked:
                clean_stale_tmp(directory)
            yield directory
        finally:
            if locked:
                fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _flock(fd: int, directory: Path) -> bool:
    """Take an exclusive flock on ``fd`` (waiting if needed); False where flock is unsupported."""
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("another job is writing %s; waiting for it to finish", directory)
            fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError as exc:
        log.warning("cannot lock %s (%s); running unlocked, stale temporaries kept", directory, exc)
        return False
    return True


def write_atomic(path: str | os.PathLike[str], writer: Callable[[Path], object]) -> Path:
    """Call ``writer(tmp_path)`` and atomically move the result to ``path``."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)


def write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as indented JSON, atomically."""

    def _w(tmp: Path) -> None:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")

    return write_atomic(path, _w)


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write a text file atomically."""
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def write_parquet(path: str | os.PathLike[str], df: pd.DataFrame) -> Path:
    """Write a DataFrame as Parquet, atomically."""
    return write_atomic(path, lambda tmp: df.to_parquet(tmp, index=False))


def write_csv(path: str | os.PathLike[str], df: pd.DataFrame) -> Path:
    """Write a DataFrame as CSV (no index), atomically."""
    return write_atomic(path, lambda tmp: df.to_csv(tmp, index=False))


def save_tensors(path: str | os.PathLike[str], obj: Mapping[str, Any]) -> Path:
    """``torch.save`` a dict of tensors / plain Python values, atomically."""
    return write_atomic(path, lambda tmp: torch.save(dict(obj), tmp))


def save_figure(path: str | os.PathLike[str], fig: Any, crop: bool | None = None) -> Path:
    """Save a matplotlib figure atomically (format from the suffix) and close it.

    ``crop=True`` crops the image to its contents (``bbox_inches="tight"``, which costs a
    second draw). By default (``None``) a figure with a layout engine (e.g.
    ``layout="constrained"``), which already fits its canvas, is drawn once and one without
    is cropped; pass ``crop=False`` for a figure whose margins were set by hand.
    """
    import matplotlib.pyplot as plt

    path = Path(path)
    fmt = path.suffix.lstrip(".") or "png"
    if crop is None:
        crop = fig.get_layout_engine() is None
    bbox = "tight" if crop else None
    write_atomic(path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=120, bbox_inches=bbox))
    plt.close(fig)
    return path


def _json_default(obj: Any) -> Any:
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, torch.Tensor):
        return obj.tolist()
    if hasattr(obj, "item"):
        return obj.item()
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


# ----------------------------------------------------------------------------------------------
# safe reads


def read_json(path: str | os.PathLike[str], made_by: str | None = None) -> dict[str, Any]:
    """Read a JSON file, with a clear error when it is missing or corrupt."""
    path = Path(path)
    _require(path, made_by)
    try:
        data: dict[str, Any] = json.loads(path.read_text())  # the artefacts' JSON is an object
        return data
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ArtefactError(f"{path} is corrupt or truncated (not valid JSON: {exc})") from exc


def read_csv(path: str | os.PathLike[str], made_by: str | None = None) -> pd.DataFrame:
    """Read a CSV table, with a clear error when it is missing, empty or unparsable."""
    path = Path(path)
    _require(path, made_by)
    try:
        return pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ArtefactError(
            f"{path} is corrupt or truncated (not a readable CSV file: {exc})"
        ) from exc


def read_parquet(path: str | os.PathLike[str], made_by: str | None = None) -> pd.DataFrame:
    """Read a Parquet file, with a clear error when it is missing or corrupt."""
    path = Path(path)
    _require(path, made_by)
    try:
        return pd.read_parquet(path)
    except Exception as exc:  # pyarrow raises several types for a truncated file
        raise ArtefactError(
            f"{path} is corrupt or truncated (not a readable Parquet file: {exc})"
        ) from exc


def load_tensors(
    path: str | os.PathLike[str], made_by: str | None = None, map_location: Any = "cpu"
) -> dict[str, Any]:
    """``torch.load(weights_only=True)`` with clear errors; never unpickles arbitrary objects."""
    path = Path(path)
    _require(path, made_by)
    try:
        tensors: dict[str, Any] = torch.load(path, map_location=map_location, weights_only=True)
        return tensors
    except Exception as exc:
        raise ArtefactError(
            f"{path} is corrupt, truncated or not a safe tensor file: {exc}"
        ) from exc


def _require(path: Path, made_by: str | None) -> None:
    if not path.exists():
        hint = f" Run `{made_by}` first to create it." if made_by else ""
        raise MissingArtefactError(f"missing artefact {path}.{hint}")


# ----------------------------------------------------------------------------------------------
# settings-derived directories and manifests


def settings_hash(settings: Mapping[str, Any], length: int = 8) -> str:
    """A short stable hash of a (nested) settings mapping; numbers are hashed as floats, so
    ``radius=3`` and ``radius=3.0`` (one setting, typed two ways) share a directory."""
    blob = json.dumps(_numbers_as_floats(_normalise(settings)), sort_keys=True,
                      separators=(",", ":"))  # fmt: skip
    return hashlib.sha256(blob.encode()).hexdigest()[:length]


def _numbers_as_floats(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _numbers_as_floats(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_numbers_as_floats(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def artefact_dir(
    root: str | os.PathLike[str], stage: str, label: Mapping[str, Any], settings: Mapping[str, Any]
) -> Path:
    """``root/stage/k1=v1_k2=v2-<hash>``: readable label plus a hash of all defining settings."""
    readable = "_".join(f"{k}={_fmt(v)}" for k, v in label.items())
    return Path(root) / stage / f"{readable}-{settings_hash(settings)}"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    return str(v).replace("/", "-").replace(" ", "")


def versions() -> dict[str, str]:
    """Versions of the packages that define results."""
    import gpytorch
    import numpy
    import scipy

    return {
        "surrogate": __version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "gpytorch": gpytorch.__version__,
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "pandas": pd.__version__,
    }


def write_manifest(
    directory: str | os.PathLike[str],
    *,
    stage: str,
    config: Mapping[str, Any],
    seed: int | None,
    **extra: Any,
) -> Path:
    """Write ``manifest.json``: stage, resolved config, seed, versions and any extra fields."""
    manifest = {
        "stage": stage,
        "seed": seed,
        "config": dict(config),
        "versions": versions(),
        # float reductions (GP training) depend on the thread count: part of reproducing a run
        "torch_threads": torch.get_num_threads(),
        "host": platform.node(),
        **extra,
    }
    return write_json(Path(directory) / MANIFEST, manifest)


def read_manifest(directory: str | os.PathLike[str], made_by: str | None = None) -> dict[str, Any]:
    """Read a stage's ``manifest.json`` (the last file a stage writes, so its presence means done)."""
    path = Path(directory) / MANIFEST
    manifest = read_json(path, made_by=made_by)
    if not isinstance(manifest, dict) or "stage" not in manifest:
        # valid JSON but not a manifest (e.g. a file replaced by hand): refuse, don't KeyError later
        raise ArtefactError(f"{path} is not a stage manifest (no 'stage' entry)")
    return manifest


def check_settings(
    expected: Mapping[str, Any], found: Mapping[str, Any], where: str, made_by: str
) -> None:
    """Refuse an artefact whose defining settings differ from ours, naming the differences."""
    diffs = [
        f"{key}: artefact has {found.get(key)!r}, this run wants {expected[key]!r}"
        for key in expected
        if _normalise(found.get(key)) != _normalise(expected[key])
    ]
    if diffs:
        raise ArtefactError(
            f"artefact {where} was made with different settings ({'; '.join(diffs)}). "
            f"Re-create it with `{made_by}`."
        )


def existing_artefact(
    directory: str | os.PathLike[str], settings: Mapping[str, Any], made_by: str
) -> dict[str, Any] | None:
    """The manifest of the complete artefact in ``directory``, or None when there is none.

    A stage calls this before (re)computing, and again once it holds :func:`artefact_lock`.
    A corrupt manifest, or one made with other ``settings``, is refused rather than reused;
    rerunning the same command would only reuse it again, so the message says to delete it.
    """
    directory = Path(directory)
    if not (directory / MANIFEST).exists():
        return None
    remake = f"rm -r {directory} && {made_by}"
    try:
        manifest = read_manifest(directory)
    except ArtefactError as exc:
        raise ArtefactError(f"{exc}. Re-create it with `{remake}`.") from exc
    check_settings(settings, manifest.get("settings", {}), str(directory), remake)
    return manifest


def _normalise(v: Any) -> Any:
    return json.loads(json.dumps(v, sort_keys=True, default=_json_default))


def require_artefact(
    directory: str | os.PathLike[str],
    settings: Mapping[str, Any],
    made_by: str,
    what: str,
    after: str | None = None,
) -> dict[str, Any]:
    """The manifest of a stage's INPUT artefact: it must exist (else the error names the
    command that makes it, and ``after`` the one before that) and match ``settings`` (else the
    error names the differences)."""
    directory = Path(directory)
    if not (directory / MANIFEST).exists():
        then = f" (after `{after}`)" if after else ""
        raise MissingArtefactError(
            f"no {what} for these settings ({directory} is missing). Run `{made_by}` first{then}."
        )
    manifest = read_manifest(directory, made_by=made_by)
    check_settings(settings, manifest.get("settings", {}), str(directory), made_by)
    return manifest


def make_once(
    directory: str | os.PathLike[str],
    settings: Mapping[str, Any],
    made_by: str,
    make: Callable[[Any], None],
    *,
    what: str,
    force: bool = False,
    prepare: Callable[[], Any] | None = None,
) -> Path:
    """Reuse the complete artefact of ``settings`` in ``directory``, or make it under the lock.

    The shared skeleton of every stage: check for a complete artefact; ``prepare()`` (reading
    inputs, so a missing input fails before any lock or directory is made); take
    :func:`artefact_lock`; re-check (a job with the same settings may have finished meanwhile);
    ``make(prepared)``, which writes the manifest last. ``force`` always remakes.
    """
    directory = Path(directory)

    def reusable() -> bool:
        if force or existing_artefact(directory, settings, made_by) is None:
            return False
        log.info("%s exists, reusing %s", what, directory)
        return True

    if reusable():
        return directory
    prepared = prepare() if prepare is not None else None
    with artefact_lock(directory):  # also removes the temporaries of killed runs
        if reusable():
            return directory
        make(prepared)
    return directory
