"""House rules of the package layout, checked on the source (ast), not by convention.

Engine packages (ctmc, simulate, gp, evaluate, sbml and the model protocols) never import a
concrete model; no model imports the engine above it (simulate, gp: the engine packs what a
model's kernel needs into plain arrays); nothing but the stages themselves, the scripts and the
loop benchmark imports a stage; and every stage (a module with a ``run`` and a ``validate``
entry point) lives in ``surrogate/stages``. The rules are checked over every module, so a new
file is held to them too.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "surrogate"
ENGINE = ["ctmc", "simulate", "gp", "evaluate", "sbml", "models/base.py", "models/network.py",
          "models/capabilities.py", "models/packed.py",
          "fields.py", "field_formula.py", "field_kernel.py", "scalar.py", "io.py", "config.py",
          "errors.py"]  # fmt: skip
#: the model protocols engine code may import (every other surrogate.models.* is a model)
PROTOCOLS = (
    "surrogate.models",
    "surrogate.models.base",
    "surrogate.models.capabilities",
    "surrogate.models.network",
    "surrogate.models.packed",
)
#: engine packages above the models: a model never imports them (the engine adapts the model)
ABOVE_MODELS = ("surrogate.simulate", "surrogate.gp")
#: modules outside surrogate/stages that may import a stage (they run stages' settings)
STAGE_USERS = ("surrogate/benchmarks/loop.py",)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[str]:
    """Every module ``path`` imports, relative imports resolved (``from p import x`` counts
    ``p.x`` too where x is a module)."""
    package = _module_name(path).rsplit(".", 1)[0] if path.name != "__init__.py" else (
        _module_name(path))  # fmt: skip
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            out.append(base)
            out += [f"{base}.{a.name}" for a in node.names if _is_module(f"{base}.{a.name}")]
    return out


def _is_module(name: str) -> bool:
    """Whether ``name`` is a module or package of the package (not a name inside one)."""
    path = PACKAGE.parent.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _files(entry: str) -> list[Path]:
    path = PACKAGE / entry
    return sorted(path.rglob("*.py")) if path.is_dir() else [path]


def _is_model(module: str) -> bool:
    return (
        module.startswith("surrogate.models.")
        and not module.startswith(tuple(f"{p}." for p in PROTOCOLS[1:]))
        and module not in PROTOCOLS
    )


@pytest.mark.parametrize("entry", ENGINE)
def test_engine_never_imports_a_concrete_model_or_a_stage(entry: str) -> None:
    offences = [
        f"{f.relative_to(PACKAGE.parent)} imports {m}"
        for f in _files(entry)
        for m in _imports(f)
        if _is_model(m) or m == "surrogate.stages" or m.startswith("surrogate.stages.")
    ]
    assert not offences, "\n".join(offences)


def _is_above_models(module: str) -> bool:
    return module in ABOVE_MODELS or module.startswith(tuple(f"{p}." for p in ABOVE_MODELS))


def test_models_never_import_simulate_or_gp() -> None:
    """Every module under surrogate/models (the protocols included) imports neither
    :mod:`surrogate.simulate` nor :mod:`surrogate.gp`, not even inside a function: a model's
    kernel receives its decision layer packed by the engine (surrogate.models.packed)."""
    offences = [
        f"{f.relative_to(PACKAGE.parent)} imports {m}"
        for f in _files("models")
        for m in _imports(f)
        if _is_above_models(m)
    ]
    assert not offences, "\n".join(offences)


def test_only_stages_and_the_bench_import_a_stage() -> None:
    offences = [
        f"{f.relative_to(PACKAGE.parent)} imports {m}"
        for f in sorted(PACKAGE.rglob("*.py"))
        if "stages" not in f.relative_to(PACKAGE).parts[:1]
        and str(f.relative_to(PACKAGE.parent)) not in STAGE_USERS
        for m in _imports(f)
        if m == "surrogate.stages" or m.startswith("surrogate.stages.")
    ]
    assert not offences, "\n".join(offences)


def test_every_stage_lives_in_stages() -> None:
    """A stage is a module with both a ``run`` and a ``validate`` function at its top level
    (the entry points the scripts call); none lives elsewhere."""
    stages = []
    for f in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(f.read_text())
        names = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
        if {"run", "validate"} <= names:
            stages.append(f.relative_to(PACKAGE))
    assert stages and all(p.parts[0] == "stages" for p in stages), stages


def test_the_rules_see_what_they_forbid(tmp_path: Path, monkeypatch) -> None:
    """On a package that breaks them, the checks find a relative import of a model in the
    engine, a stage imported by a model, the engine imported (relatively, inside a function)
    by a model and a stage entry point outside stages."""
    package = tmp_path / "surrogate"
    for sub in ("gp", "models", "simulate", "stages"):
        (package / sub).mkdir(parents=True)
    (package / "gp" / "x.py").write_text("from ..models import ecoli\n")
    (package / "models" / "ecoli.py").write_text("")
    (package / "gp" / "stage.py").write_text("def run(cfg): ...\ndef validate(cfg): ...\n")
    (package / "models" / "m.py").write_text("from surrogate.stages import train\n")
    (package / "models" / "k.py").write_text("def f():\n    from ..simulate import loop\n")
    (package / "stages" / "s.py").write_text("def run(cfg): ...\ndef validate(cfg): ...\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    with pytest.raises(AssertionError, match="gp/x.py imports surrogate.models.ecoli"):
        test_engine_never_imports_a_concrete_model_or_a_stage("gp")
    with pytest.raises(AssertionError, match="models/m.py imports surrogate.stages"):
        test_only_stages_and_the_bench_import_a_stage()
    with pytest.raises(AssertionError, match="models/k.py imports surrogate.simulate"):
        test_models_never_import_simulate_or_gp()
    with pytest.raises(AssertionError, match="gp/stage.py"):
        test_every_stage_lives_in_stages()


def test_cli_and_sweep_do_not_import_each_other() -> None:
    assert "surrogate.cli" not in _imports(PACKAGE / "sweep.py")
    # cli imports the sweep summary lazily (inside the callback), never at module level
    tree = ast.parse((PACKAGE / "cli.py").read_text())
    top = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    assert all(getattr(n, "module", None) != "surrogate.sweep" for n in top)
