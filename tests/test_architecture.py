"""House rules of the package layout, checked on the source (ast), not by convention.

Engine packages (ctmc, simulate, gp, evaluate, sbml and the model protocols) never import a
concrete model or a stage; stages live in one place; no module imports a stage module except
stages, scripts and the bench.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "surrogate"
ENGINE = ["ctmc", "simulate", "gp", "evaluate", "sbml", "models/base.py", "models/network.py",
          "fields.py", "io.py", "config.py", "errors.py"]  # fmt: skip


def _imports(path: Path) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.append(node.module)
    return out


def _files(entry: str) -> list[Path]:
    path = PACKAGE / entry
    return sorted(path.rglob("*.py")) if path.is_dir() else [path]


@pytest.mark.parametrize("entry", ENGINE)
def test_engine_never_imports_a_concrete_model_or_a_stage(entry: str) -> None:
    offences = [
        f"{f.relative_to(PACKAGE.parent)} imports {m}"
        for f in _files(entry)
        for m in _imports(f)
        if m.startswith(
            ("surrogate.models.ecoli", "surrogate.models.ecoli_phospho", "surrogate.stages")
        )
    ]
    assert not offences, "\n".join(offences)


def test_stage_modules_live_in_stages_only() -> None:
    for name in ("collect.py", "train.py", "reproduce.py", "paths.py"):
        assert not (PACKAGE / name).exists(), name
    for sub in ("simulate", "evaluate"):
        assert not (PACKAGE / sub / "stage.py").exists()
        assert not (PACKAGE / sub / "shards.py").exists()


def test_cli_and_sweep_do_not_import_each_other() -> None:
    assert "surrogate.cli" not in _imports(PACKAGE / "sweep.py")
    # cli imports the sweep summary lazily (inside the callback), never at module level
    tree = ast.parse((PACKAGE / "cli.py").read_text())
    top = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    assert all(getattr(n, "module", None) != "surrogate.sweep" for n in top)
