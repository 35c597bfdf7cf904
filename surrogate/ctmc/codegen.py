"""Loading code generated from a validated expression tree (propensities, SSA kernels).

The only place the package turns generated source into code: :mod:`surrogate.ctmc.kinetics`
emits it from expression trees whose every node is on a whitelist (numbers, column indices and
our own templates; nothing of a user's file is copied into it verbatim), and this module writes
it to a content-addressed file and imports it as a module, so numba can cache its machine code
and tracebacks point at real lines. No ``eval``/``exec`` of strings anywhere.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

from surrogate.io import write_text


def default_cache_dir() -> Path:
    """Where generated modules (and numba's cache of them) live: ``$SURROGATE_CACHE_DIR`` or
    ``~/.cache/surrogate``, under ``ssa/``."""
    root = os.environ.get("SURROGATE_CACHE_DIR")
    base = Path(root) if root else Path.home() / ".cache" / "surrogate"
    return base / "ssa"


def load_generated(source: str, cache_dir: Path | None = None, prefix: str = "gen") -> ModuleType:
    """Write ``source`` under ``cache_dir`` (content-addressed, atomically) and import it."""
    digest = hashlib.sha256(source.encode()).hexdigest()[:20]
    name = f"_surrogate_{prefix}_{digest}"
    if name in sys.modules:
        return sys.modules[name]
    cache_dir = default_cache_dir() if cache_dir is None else Path(cache_dir)
    path = cache_dir / f"{name}.py"
    if not path.exists() or path.read_text() != source:
        write_text(path, source)
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


__all__ = ["default_cache_dir", "load_generated"]
