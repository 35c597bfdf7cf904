"""House rules of the package layout, checked on the source (ast), not by convention.

Engine packages (ctmc, simulate, gp, evaluate, sbml and the model protocols) never import a
concrete model; no model imports the engine above it (simulate, gp: the engine packs what a
model's kernel needs into plain arrays); nothing but the stages themselves, the scripts and the
loop benchmark imports a stage (the diagnosis package below the stages not even under ``if
TYPE_CHECKING:``); and every stage (a module with a ``run`` and a ``validate``
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
          "models/capabilities.py", "models/packed.py", "models/count_classes.py",
          "models/randoms.py", "fields.py", "field_formula.py", "field_kernel.py",
          "models/decision_kernel.py", "grid", "kinds",
          "scalar.py", "io.py", "config.py", "errors.py", "validation.py"]  # fmt: skip
#: the model protocols engine code may import (every other surrogate.models.* is a model)
PROTOCOLS = (
    "surrogate.models",
    "surrogate.models.base",
    "surrogate.models.capabilities",
    "surrogate.models.network",
    "surrogate.models.packed",
    "surrogate.models.count_classes",
    "surrogate.models.randoms",
    "surrogate.models.decision_kernel",
)
#: engine packages above the models: a model never imports them (the engine adapts the model)
ABOVE_MODELS = ("surrogate.simulate", "surrogate.gp")
#: the layer below the stages and above the engine: measurement, diagnosis and advice from plain
#: values and typed options (the stages read their settings, call it and write the artefacts)
DIAGNOSIS = ("diagnosis",)
#: modules outside surrogate/stages that may import a stage (they run stages' settings)
# the loop benchmark times the stages' own layers (the abstraction's; the field benchmark's exact
# psi's table is the kinds')
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


#: the package's layers, lowest first (docs/architecture.md): a module imports only modules of
#: its own layer or below, at its top level, under ``if TYPE_CHECKING:`` and inside functions
#: alike. A module's layer is that of its longest listed name (itself or a package above it;
#: the package's root ``surrogate`` only itself); every module must have one.
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "surrogate",
        "surrogate.threads",
        "surrogate.processes",
        "surrogate.errors",
        "surrogate.scalar",
    ),
    ("surrogate.validation", "surrogate.io"),
    ("surrogate.ctmc",),
    ("surrogate.sbml",),
    ("surrogate.field_formula", "surrogate.fields"),
    ("surrogate.grid", "surrogate.field_kernel"),
    # the model protocols and what a compiled kernel receives (the package's __init__, which
    # re-exports them, sits with the models)
    (*PROTOCOLS[1:], "surrogate.models.perturbation"),
    ("surrogate.models",),
    ("surrogate.config",),
    ("surrogate.gp",),
    ("surrogate.simulate",),
    ("surrogate.evaluate",),
    ("surrogate.kinds",),
    # measurement, diagnosis and advice below the stages (plain values and typed options)
    ("surrogate.diagnosis",),
    # the contract test classes every plug-in's tests inherit (they run kinds, layers, models)
    ("surrogate.testing",),
    ("surrogate.stages",),
    ("surrogate.benchmarks", "surrogate.sweep", "surrogate.cli"),
)


def _layer(module: str) -> int | None:
    """The index in :data:`LAYERS` of ``module``'s layer (None: in none)."""
    found = [(len(name), i) for i, layer in enumerate(LAYERS) for name in layer
             if module == name or (name != "surrogate" and module.startswith(f"{name}."))]  # fmt: skip
    return max(found)[1] if found else None


def test_no_import_runs_up_a_layer() -> None:
    """Every module has a layer, and no import (at the top level, type-only or inside a
    function) goes from a lower layer to a higher one: the layers of docs/architecture.md,
    with no arrow back up."""
    files = sorted(PACKAGE.rglob("*.py"))
    unplaced = [_module_name(f) for f in files if _layer(_module_name(f)) is None]
    assert not unplaced, f"modules in no layer (add them to LAYERS): {unplaced}"
    offences = [
        f"{f.relative_to(PACKAGE.parent)} (layer {mine}) imports {m} (layer {theirs})"
        for f in files
        if (mine := _layer(_module_name(f))) is not None
        for m in _imports(f)
        if m.split(".")[0] == "surrogate"
        and (theirs := _layer(m)) is not None and theirs > mine
    ]  # fmt: skip
    assert not offences, "\n".join(offences)


def test_the_layer_check_sees_an_arrow_back_up(tmp_path: Path, monkeypatch) -> None:
    """A model that imports, only for typing, a module of the engine above it (the old
    ``decision_kernel``'s place) runs up a layer; a module in no layer is named."""
    package = tmp_path / "surrogate"
    (package / "models").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "models" / "__init__.py").write_text("")
    (package / "models" / "base.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from surrogate.gp import x\n"
    )
    (package / "gp.py").write_text("from surrogate.models.base import B\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    with pytest.raises(AssertionError, match="models/base.py .* imports surrogate.gp"):
        test_no_import_runs_up_a_layer()
    (package / "models" / "base.py").write_text("B = 1\n")
    test_no_import_runs_up_a_layer()
    (package / "new.py").write_text("")
    with pytest.raises(AssertionError, match="in no layer .*surrogate.new"):
        test_no_import_runs_up_a_layer()


#: the concrete models, and E. coli's body in the library (it runs the E. coli signalling)
CONCRETE_MODELS = ("surrogate.models.ecoli", "surrogate.models.ecoli_phospho",
                   "surrogate.models.bodies.chemotaxis")  # fmt: skip
#: where a concrete model may be imported: the models themselves, E. coli's body and the
#: library's body registry (``kind: chemotaxis``)
CONCRETE_HOMES = ("models/ecoli/", "models/ecoli_phospho/", "models/bodies/chemotaxis.py",
                  "models/bodies/registry.py")  # fmt: skip
#: the other modules that import one, each with its reason
CONCRETE_USERS = {
    "surrogate/models/bodies/__init__.py": "re-exports the registry's bodies",
    "surrogate/benchmarks/ssa.py": "times the SSA backends on the E. coli phospho network",
}


def _is_concrete(module: str) -> bool:
    return module.startswith(tuple(f"{c}." for c in CONCRETE_MODELS)) or module in CONCRETE_MODELS


def test_only_the_models_import_a_concrete_model() -> None:
    """Every module of the package outside the concrete models (``models/ecoli*``), E. coli's
    body and the body registry imports no concrete model, not even inside a function: the
    engine, the stages, the generic bodies and the network and SBML models serve any model.
    The few exceptions are listed with their reason (:data:`CONCRETE_USERS`)."""
    offences = [
        f"{rel} imports {m}"
        for f in sorted(PACKAGE.rglob("*.py"))
        if not str(f.relative_to(PACKAGE)).startswith(CONCRETE_HOMES)
        and (rel := str(f.relative_to(PACKAGE.parent))) not in CONCRETE_USERS
        for m in _imports(f)
        if _is_concrete(m)
    ]
    assert not offences, "\n".join(offences)
    stale = [
        rel for rel in CONCRETE_USERS
        if not any(_is_concrete(m) for m in _imports(PACKAGE.parent / rel))
    ]  # fmt: skip
    assert not stale, f"CONCRETE_USERS lists modules that import no concrete model: {stale}"


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


@pytest.mark.parametrize("entry", DIAGNOSIS)
def test_diagnosis_never_imports_a_stage_or_a_concrete_model(entry: str) -> None:
    """:mod:`surrogate.diagnosis` sits below the stages: none of its modules imports a stage
    (not inside a function, not under ``if TYPE_CHECKING:``) nor a concrete model, and none
    hides an import under ``if TYPE_CHECKING:`` (a type it needs lives below it)."""
    offences = [
        f"{f.relative_to(PACKAGE.parent)} imports {m}"
        for f in _files(entry)
        for m in _imports(f)
        if _is_model(m) or m == "surrogate.stages" or m.startswith("surrogate.stages.")
    ] + [
        f"{f.relative_to(PACKAGE.parent)}:{node.lineno} imports under TYPE_CHECKING"
        for f in _files(entry)
        for node in ast.walk(ast.parse(f.read_text()))
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
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
    by a model, a stage imported (under ``if TYPE_CHECKING:``) below the stages and a stage entry
    point outside stages."""
    package = tmp_path / "surrogate"
    for sub in ("gp", "models", "simulate", "stages", "diagnosis"):
        (package / sub).mkdir(parents=True)
    (package / "diagnosis" / "d.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
        "    from surrogate.stages.settings import CollectSettings\n"
    )
    (package / "gp" / "x.py").write_text("from ..models import ecoli\n")
    (package / "models" / "ecoli.py").write_text("")
    (package / "gp" / "stage.py").write_text("def run(cfg): ...\ndef validate(cfg): ...\n")
    (package / "models" / "m.py").write_text("from surrogate.stages import train\n")
    (package / "models" / "k.py").write_text("def f():\n    from ..simulate import loop\n")
    (package / "models" / "bodies").mkdir()
    (package / "models" / "bodies" / "walker.py").write_text(
        "def step():\n    from surrogate.models.ecoli.formulas import tumble_angle\n"
    )
    (package / "stages" / "s.py").write_text("def run(cfg): ...\ndef validate(cfg): ...\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    with pytest.raises(AssertionError, match="gp/x.py imports surrogate.models.ecoli"):
        test_engine_never_imports_a_concrete_model_or_a_stage("gp")
    with pytest.raises(AssertionError, match="models/m.py imports surrogate.stages"):
        test_only_stages_and_the_bench_import_a_stage()
    with pytest.raises(AssertionError, match="diagnosis/d.py imports surrogate.stages.settings"):
        test_diagnosis_never_imports_a_stage_or_a_concrete_model("diagnosis")
    with pytest.raises(AssertionError, match="diagnosis/d.py:2 imports under TYPE_CHECKING"):
        test_diagnosis_never_imports_a_stage_or_a_concrete_model("diagnosis")
    with pytest.raises(AssertionError, match="models/k.py imports surrogate.simulate"):
        test_models_never_import_simulate_or_gp()
    with pytest.raises(AssertionError, match="gp/stage.py"):
        test_every_stage_lives_in_stages()
    monkeypatch.setattr(sys.modules[__name__], "CONCRETE_USERS", {})
    with pytest.raises(AssertionError, match="walker.py imports surrogate.models.ecoli.formulas"):
        test_only_the_models_import_a_concrete_model()


def test_cli_and_sweep_do_not_import_each_other() -> None:
    assert "surrogate.cli" not in _imports(PACKAGE / "sweep.py")
    # cli imports the sweep summary lazily (inside the callback), never at module level
    tree = ast.parse((PACKAGE / "cli.py").read_text())
    top = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    assert all(getattr(n, "module", None) != "surrogate.sweep" for n in top)


def _is_docstring(node: ast.stmt) -> bool:
    return (
        isinstance(node, ast.Expr)
        and isinstance(node.value, ast.Constant)
        and isinstance(node.value.value, str)
    )


def _re_export_only(node: ast.stmt, first: bool) -> bool:
    """Whether ``node`` (a statement at a package ``__init__``'s top level) only re-exports:
    the docstring, an import (also under ``if TYPE_CHECKING:``), ``__all__`` or
    ``__version__``, or a lazy re-export (PEP 562 ``__getattr__``)."""
    if first and _is_docstring(node):
        return True
    if isinstance(node, ast.Import | ast.ImportFrom):
        return True
    if isinstance(node, ast.If) and ast.unparse(node.test) in (
        "TYPE_CHECKING",
        "typing.TYPE_CHECKING",
    ):
        return not node.orelse and all(
            isinstance(n, ast.Import | ast.ImportFrom) for n in node.body
        )
    if isinstance(node, ast.Assign | ast.AugAssign | ast.AnnAssign):
        targets = node.targets if isinstance(node, ast.Assign) else [node.target]
        return all(isinstance(t, ast.Name) and t.id in ("__all__", "__version__") for t in targets)
    return isinstance(node, ast.FunctionDef) and node.name == "__getattr__"


def test_package_inits_only_re_export() -> None:
    """A package's ``__init__.py`` holds a docstring, imports and ``__all__`` (a lazy
    ``__getattr__`` re-export and ``__version__`` allowed): its code lives in a module."""
    offences = [
        f"{f.relative_to(PACKAGE.parent)}:{node.lineno} {ast.unparse(node).splitlines()[0]}"
        for f in sorted(PACKAGE.rglob("__init__.py"))
        for i, node in enumerate(ast.parse(f.read_text()).body)
        if not _re_export_only(node, i == 0)
    ]
    assert not offences, "\n".join(offences)


def _module_level_imports(path: Path, typing: bool = True) -> set[str]:
    """The package's modules that importing ``path`` imports at once (its top level, not inside
    functions; under ``if TYPE_CHECKING:`` too where ``typing``: a circle closed by a type-only
    import is still a circle of the design): ``from p import name`` counts ``p`` (its
    ``__init__`` runs), ``from p import module`` counts ``p.module`` (and ``p`` unless ``p`` is
    a package above ``path``, which is imported first anyway)."""
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]

    def top(body: list[ast.stmt]) -> list[ast.stmt]:
        out: list[ast.stmt] = []
        for n in body:
            if isinstance(n, ast.If) and "TYPE_CHECKING" in ast.unparse(n.test) and not typing:
                out += top(n.orelse)
            elif isinstance(n, ast.If | ast.Try):
                out += top([*n.body, *n.orelse, *getattr(n, "finalbody", [])])
                for handler in getattr(n, "handlers", []):
                    out += top(handler.body)
            else:
                out.append(n)
        return out

    edges: set[str] = set()
    for node in top(ast.parse(path.read_text()).body):
        if isinstance(node, ast.Import):
            edges |= {a.name for a in node.names if a.name.split(".")[0] == "surrogate"}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            if base.split(".")[0] != "surrogate":
                continue
            above = me == base or me.startswith(f"{base}.")
            for a in node.names:
                if _is_module(f"{base}.{a.name}"):
                    edges.add(f"{base}.{a.name}")
                    if not above:
                        edges.add(base)
                else:
                    edges.add(base)
    edges.discard(me)
    return edges


def _import_cycles(typing: bool = True) -> list[list[str]]:
    """The cycles of module-level imports in the package (strongly connected components), the
    type-only imports included where ``typing``."""
    graph = {_module_name(f): _module_level_imports(f, typing)
             for f in sorted(PACKAGE.rglob("*.py"))}  # fmt: skip
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


#: circles closed only by a type-only import (``if TYPE_CHECKING:``) that stay for now, each
#: with its reason; remove an entry when its circle is gone (the test then asks for it)
TYPE_ONLY_CYCLES: dict[tuple[str, ...], str] = {}


def test_no_import_cycles() -> None:
    """No two modules import each other at their top levels, through packages included: a
    submodule importing names from its own package's ``__init__`` that imports it works only
    as long as the ``__init__`` defines them before that import. Type-only imports (under
    ``if TYPE_CHECKING:``) count too: a circle that only typing closes is still two modules
    that need each other (the shared type belongs to the lower one, or to a protocol); the
    few left are listed in :data:`TYPE_ONLY_CYCLES` with their reason."""
    assert not _import_cycles(typing=False)
    cycles = {tuple(c) for c in _import_cycles()}
    assert cycles <= set(TYPE_ONLY_CYCLES), f"new: {sorted(cycles - set(TYPE_ONLY_CYCLES))}"
    stale = set(TYPE_ONLY_CYCLES) - cycles
    assert not stale, f"TYPE_ONLY_CYCLES lists circles that are gone: {sorted(stale)}"


#: function-level imports that hide a cycle (the module they import imports this one at its
#: top level, through packages included), each with the reason it stays; none left (collect's
#: design gets train's settings builder registered by train, not imported)
HIDDEN_CYCLES: dict[str, str] = {}


def _with_parents(module: str) -> list[str]:
    """``a.b.c`` -> ``[a, a.b, a.b.c]``: importing a module runs its packages first."""
    parts = module.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def _function_level_imports() -> list[tuple[str, int, list[str]]]:
    """``(file, line, modules)`` for each import of the package inside a function: the modules
    it runs, parent packages included (``from p import m`` counts ``p.m`` where m is a module,
    else ``p``)."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        me = _module_name(path)
        package = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]
        seen: set[int] = set()
        for fn in ast.walk(ast.parse(path.read_text())):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(fn):
                if id(node) in seen or not isinstance(node, ast.Import | ast.ImportFrom):
                    continue
                seen.add(id(node))
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                else:
                    base = node.module or ""
                    if node.level:
                        anchor = package.split(".")
                        anchor = anchor[: len(anchor) - (node.level - 1)]
                        base = ".".join([*anchor, *([base] if base else [])])
                    names = [f"{base}.{a.name}" if _is_module(f"{base}.{a.name}") else base
                             for a in node.names]  # fmt: skip
                parts = {p for n in names if n.split(".")[0] == "surrogate"
                         for p in _with_parents(n)}  # fmt: skip
                if parts:
                    out.append((str(path.relative_to(PACKAGE.parent)), node.lineno, sorted(parts)))
    return out


def _hidden_cycles() -> dict[str, list[str]]:
    """``{"file -> module": [file, line, ...]}`` for each function-level import of a module
    that imports the importing module back at its top level (directly or through others)."""
    graph = {_module_name(f): _module_level_imports(f) for f in sorted(PACKAGE.rglob("*.py"))}

    def reaches(start: str, goal: str) -> bool:
        seen, todo = {start}, [start]
        while todo:
            for w in graph.get(todo.pop(), ()):
                if w == goal:
                    return True
                if w not in seen:
                    seen.add(w)
                    todo.append(w)
        return False

    hidden: dict[str, list[str]] = {}
    for rel, line, modules in _function_level_imports():
        me = _module_name(PACKAGE.parent / rel)
        mine = set(_with_parents(me))
        for m in modules:
            if m not in mine and reaches(m, me):
                hidden.setdefault(f"{rel} -> {m}", []).append(f"{rel}:{line}")
    return hidden


def test_function_level_imports_hide_no_other_cycle() -> None:
    """An import inside a function is for start-up cost (numba kernels, matplotlib, the GP
    stack imported on demand), never to hide a cycle: each one that does is listed in
    :data:`HIDDEN_CYCLES` with its reason, and the list holds no resolved one."""
    hidden = _hidden_cycles()
    assert set(hidden) == set(HIDDEN_CYCLES), (
        f"new: {sorted(set(hidden) - set(HIDDEN_CYCLES))}; "
        f"resolved (remove from HIDDEN_CYCLES): {sorted(set(HIDDEN_CYCLES) - set(hidden))}"
    )


def test_the_hidden_cycle_check_sees_one(tmp_path: Path, monkeypatch) -> None:
    package = tmp_path / "surrogate"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from surrogate.b import B\n")
    (package / "b.py").write_text("B = 1\ndef f():\n    from surrogate import a\n")
    (package / "c.py").write_text("def g():\n    from surrogate.b import B\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    assert _hidden_cycles() == {"surrogate/b.py -> surrogate.a": ["surrogate/b.py:3"]}


def test_the_cycle_check_sees_a_cycle(tmp_path: Path, monkeypatch) -> None:
    """A package whose ``__init__`` imports a submodule that imports names from the package
    (ecoli_phospho's old layout) is a cycle; the same names imported from their module are not."""
    package = tmp_path / "surrogate"
    (package / "m").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "m" / "constants.py").write_text("C = 1\n")
    (package / "m" / "model.py").write_text("from surrogate.m import C\n")
    (package / "m" / "__init__.py").write_text(
        "from surrogate.m.constants import C\nfrom surrogate.m.model import *\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    assert _import_cycles() == [["surrogate.m", "surrogate.m.model"]]
    (package / "m" / "model.py").write_text("from surrogate.m.constants import C\n")
    assert _import_cycles() == []


def test_the_cycle_check_sees_a_type_only_cycle(tmp_path: Path, monkeypatch) -> None:
    """Two modules importing each other, one of them only under ``if TYPE_CHECKING:``, are a
    circle: the test of the package fails on it (and not once the type is moved down)."""
    package = tmp_path / "surrogate"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "low.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from surrogate.high import H\n"
    )
    (package / "high.py").write_text("from surrogate.low import L\nH = 1\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    assert _import_cycles(typing=False) == []
    assert _import_cycles() == [["surrogate.high", "surrogate.low"]]
    with pytest.raises(AssertionError, match="surrogate.high"):
        test_no_import_cycles()
    (package / "low.py").write_text("L = 1\n")
    (package / "high.py").write_text("from surrogate.low import L\nH = 1\n")
    monkeypatch.setattr(sys.modules[__name__], "TYPE_ONLY_CYCLES", {})
    test_no_import_cycles()


_IMPORT_ALONE = """
import importlib, os, sys, traceback


def forked(job):
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # a process with no module of the package imported
        os.close(read)
        try:
            out = job()
        except BaseException:
            traceback.print_exc()
            os._exit(1)
        os.write(write, out.encode())
        os._exit(0)
    os.close(write)
    with os.fdopen(read) as f:
        out = f.read()
    return os.waitpid(pid, 0)[1] == 0, out


def everything():
    for name in sys.argv[1:]:
        importlib.import_module(name)
    return " ".join(m for m in sys.modules if m.split(".")[0] != "surrogate")


# what the package imports of other libraries, imported once here: the forks pay only for the
# package's own modules
ok, others = forked(everything)
for name in others.split() if ok else []:
    try:
        importlib.import_module(name)
    except BaseException:
        pass


def alone(name):
    return lambda: importlib.import_module(name) and ""


failed = [name for name in sys.argv[1:] if not forked(alone(name))[0]]
print("FAILED", failed)
"""


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_every_module_imports_alone() -> None:
    """Each module of the package imports by itself, in a process where no other module of the
    package was imported first (one fresh interpreter imports the other libraries the package
    uses once, then forks a process per module): an import cycle or a missing import that another
    module's import would hide fails here."""
    import os
    import subprocess

    modules = [_module_name(f) for f in sorted(PACKAGE.rglob("*.py"))]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(PACKAGE.parent), *filter(None, [os.environ.get("PYTHONPATH")])])}  # fmt: skip
    result = subprocess.run(
        [sys.executable, "-c", _IMPORT_ALONE, *modules],
        capture_output=True, text=True, env=env, cwd=PACKAGE.parent, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-4000:]
    assert "FAILED []" in result.stdout, result.stderr[-4000:]


#: libraries that importing the stages must not import (each pays 1.5-2 s in every process,
#: sweep jobs and workers included): the few functions that need them import them
LATE_IMPORTS = ("torch._dynamo", "scipy.stats")


def test_stages_import_without_dynamo_or_scipy_stats() -> None:
    """``import surrogate.stages.reproduce`` (the quick start's whole pipeline) leaves
    torch._dynamo (``torch.compiler.disable`` imports it: CachedPsi applies it under compile
    only) and scipy.stats (imported by the functions that test) unimported."""
    import os
    import subprocess

    code = ("import sys, surrogate.stages.reproduce; "
            f"print([m for m in {LATE_IMPORTS!r} if m in sys.modules])")  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(PACKAGE.parent), *filter(None, [os.environ.get("PYTHONPATH")])])}  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            env=env, cwd=PACKAGE.parent, timeout=600)  # fmt: skip
    assert result.returncode == 0, result.stderr[-4000:]
    assert result.stdout.strip() == "[]"


def test_stages_never_import_the_cli() -> None:
    """The cli sits above the stages (scripts call both): a stage is given what the cli knows
    (the job's config, its threads), it never reaches up for it."""
    offences = [
        f"{f.relative_to(PACKAGE.parent)} imports {m}"
        for f in _files("stages")
        for m in _imports(f)
        if m == "surrogate.cli"
    ]
    assert not offences, "\n".join(offences)


if __name__ == "__main__":  # the listing: python tests/test_architecture.py
    imports = _function_level_imports()
    for rel, line, modules in imports:
        print(f"{rel}:{line} {' '.join(modules)}")
    print(f"{len(imports)} function-level imports of the package; hiding a cycle:")
    for key, where in _hidden_cycles().items():
        print(f"  {key} ({', '.join(where)})")


# ---------------------------------------------------------------------------------------------
# The kind of an abstraction is read from its config strings in the kinds package only (issue
# 40): everywhere else asks the kind object. The budget below may only fall: a new comparison of
# a kind's name goes in surrogate/kinds/. A word that a kind shares but that names something else (a
# recorder's durations mode "none", an inspection's method "exact", the child's "none" of the
# loop benchmark) is a constant of its own module, compared by that name: the counter reads
# literals and cannot tell what the other side of a comparison is (a list of exempt variable
# names would exempt a real kind compared through a variable of that name as well), and the
# constant says at the comparison which word it is.

#: the names of kinds (lumps, history, class moves, decision layers and modes) that code tests
KIND_NAMES = frozenset({"classes", "phi", "age", "none", "learned", "relaxation", "exact",
                        "abstract", "full", "lookup", "classifier"})  # fmt: skip
#: comparisons with a kind's name per module, or per package for a folder (its modules
#: together), measured 2026-11-27 (69 in all at first; 19 once every stage, the benchmarks and
#: the recorders asked the kind objects or named their own words; 17 once the cost model took a
#: flag and the E. coli kernel its packed block's kind; the same 17 once kinds.py was split into
#: the package surrogate/kinds/; 3 once the chain kinds were registered plug-ins, looked up by
#: their strings and checked by their own hooks)
KIND_COMPARISON_BUDGET = {
    # the kinds' own package: the one place a config's kind names are read (a new kind compares
    # its own strings in its module; every other module asks the kind object, a model its flag
    # or block)
    "kinds": 3,
}


def _kind_comparisons(path: Path) -> int:
    """``==``, ``!=``, ``in`` or ``not in`` with a kind's name as a string literal (or in a
    literal tuple, list or set)."""
    count = 0
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.Compare):
            continue
        if not any(isinstance(op, ast.Eq | ast.NotEq | ast.In | ast.NotIn) for op in node.ops):
            continue
        names: list[object] = []
        for side in (node.left, *node.comparators):
            if isinstance(side, ast.Constant):
                names.append(side.value)
            elif isinstance(side, ast.Tuple | ast.List | ast.Set):
                names += [e.value for e in side.elts if isinstance(e, ast.Constant)]
        count += any(isinstance(n, str) and n in KIND_NAMES for n in names)
    return count


def _budget_entry(path: Path) -> str:
    """``path``'s entry in :data:`KIND_COMPARISON_BUDGET`: the folder of a package that has one
    (its modules share it), else the module's own path."""
    rel = path.relative_to(PACKAGE)
    for entry in KIND_COMPARISON_BUDGET:
        if (PACKAGE / entry).is_dir() and rel.is_relative_to(entry):
            return entry
    return str(rel)


def test_kind_string_comparisons_do_not_spread() -> None:
    found: dict[str, int] = {}
    for p in PACKAGE.rglob("*.py"):
        found[_budget_entry(p)] = found.get(_budget_entry(p), 0) + _kind_comparisons(p)
    over = {f: (n, KIND_COMPARISON_BUDGET.get(f, 0)) for f, n in found.items()
            if n > KIND_COMPARISON_BUDGET.get(f, 0)}  # fmt: skip
    assert not over, (
        f"kind names compared as strings beyond each module's budget (found, budget): {over}; "
        "test the kind where it is defined, or make it an object (issue 40)"
    )


def _under(module: str, package: str) -> bool:
    return module == package or module.startswith(f"{package}.")


def test_the_contract_tests_sit_above_the_package_and_below_the_stages() -> None:
    """:mod:`surrogate.testing` (the contract test classes plug-ins inherit) may import any
    module below the stages, but no stage; and no module of the package imports it."""
    offences = []
    for f in sorted(PACKAGE.rglob("*.py")):
        rel = str(f.relative_to(PACKAGE.parent))
        inside = rel.startswith("surrogate/testing/")
        forbidden = "surrogate.stages" if inside else "surrogate.testing"
        offences += [f"{rel} imports {m}" for m in _imports(f) if _under(m, forbidden)]
    assert not offences, "\n".join(offences)
