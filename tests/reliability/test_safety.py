"""Artefacts are never unpickled, and no config string is evaluated as code."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

from surrogate.errors import ArtefactError
from surrogate.gp import load_psi
from surrogate.io import load_tensors, save_tensors

PACKAGE = Path(__file__).resolve().parents[2] / "surrogate"


class _Payload:
    """Unpickling this runs ``open(marker, "w")``: proof that arbitrary code was executed."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


@pytest.mark.parametrize("wrap", [False, True])
def test_a_pickled_object_in_a_pt_file_is_refused(tmp_path: Path, wrap: bool) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "psi.pt"
    payload = _Payload(marker)
    # plain torch.save (pickle) of an object, bare or hidden inside an innocent-looking dict
    torch.save({"psi": {"format": "surrogate.gp.psi/1", "x": payload}} if wrap else payload, path)
    for load in (load_tensors, load_psi):
        with pytest.raises(ArtefactError, match=f"{path}.*not a safe tensor file"):
            load(path)
    assert not marker.exists(), "unpickling ran code from the artefact"


def test_a_tensor_file_without_a_classifier_is_refused(tmp_path: Path) -> None:
    path = save_tensors(tmp_path / "psi.pt", {"weights": torch.zeros(3)})
    assert torch.equal(load_tensors(path)["weights"], torch.zeros(3))  # plain tensors are fine
    with pytest.raises(ArtefactError, match=f"{path} is not a saved psi classifier"):
        load_psi(path)


def _calls() -> list[tuple[str, int, str, ast.Call]]:
    """Every call in the package: (file, line, dotted callee name, node)."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Call):
                out.append(
                    (str(path.relative_to(PACKAGE.parent)), node.lineno, _name(node.func), node)
                )
    return out


def _name(func: ast.expr) -> str:
    parts = []
    while isinstance(func, ast.Attribute):
        parts.append(func.attr)
        func = func.value
    if isinstance(func, ast.Name):
        parts.append(func.id)
    return ".".join(reversed(parts))


def _imports() -> list[tuple[str, int, str]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            out += [(str(path.relative_to(PACKAGE.parent)), node.lineno, n) for n in names]
    return out


UNSAFE_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "shelve", "marshal"}
UNSAFE_CALLS = {
    "eval",
    "exec",
    "compile",
    "pandas.read_pickle",
    "pd.read_pickle",
    "yaml.load",
    "yaml.unsafe_load",
    "yaml.full_load",
    "joblib.load",
    "numpy.load",
    "np.load",
}


def test_no_unsafe_deserialisation_or_eval_in_the_package() -> None:
    offences = [
        f"{f}:{line}: import {m}" for f, line, m in _imports() if m.split(".")[0] in UNSAFE_MODULES
    ]
    for f, line, name, _ in _calls():
        if name in UNSAFE_CALLS or name.endswith(".read_pickle"):
            offences.append(f"{f}:{line}: {name}(...)")
        # OmegaConf resolvers run at interpolation time: none may evaluate strings
        if name.endswith("register_new_resolver"):
            offences.append(f"{f}:{line}: custom resolver (check it does not eval)")
    assert not offences, "\n".join(offences)


def test_generated_code_is_loaded_in_one_place_only() -> None:
    """Source generated from validated expression trees (propensities, SSA kernels, field
    formulas and the kernel's field dispatcher) becomes code only through
    surrogate.ctmc.codegen.load_generated; nothing else imports files by path."""
    offences = [
        f"{f}:{line}: {name}(...)"
        for f, line, name, _ in _calls()
        if name.endswith(("spec_from_file_location", "exec_module", "import_module"))
        and f != "surrogate/ctmc/codegen.py"
    ]
    assert not offences, "\n".join(offences)
    callers = {f for f, _, name, _ in _calls() if name.endswith("load_generated")}
    # (the field contract runs a formula's scalar code as Python, loaded the same way)
    assert callers <= {"surrogate/ctmc/compiled.py", "surrogate/ctmc/cuda_ssa.py",
                       "surrogate/ctmc/expr.py", "surrogate/ctmc/kinetics.py",
                       "surrogate/field_formula.py", "surrogate/field_kernel.py",
                       "surrogate/testing/field.py"}, callers  # fmt: skip


def test_torch_load_only_in_load_tensors_with_weights_only() -> None:
    loads = [(f, line, node) for f, line, name, node in _calls() if name == "torch.load"]
    assert [f for f, _, _ in loads] == ["surrogate/io.py"], loads
    keywords = {k.arg: k.value for k in loads[0][2].keywords}
    assert isinstance(keywords.get("weights_only"), ast.Constant)
    assert keywords["weights_only"].value is True
