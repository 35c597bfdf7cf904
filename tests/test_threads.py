"""How idle OpenMP threads wait: set at the package's import, before torch loads libgomp."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from surrogate.threads import WAIT_KEYS, passive_wait

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((ROOT / "scripts").glob("*.py"))

# Stops at the first import of torch and prints the wait policy the environment holds then
# (what libgomp reads as torch loads it); "no torch" where the script's imports never load it.
_FIRST_TORCH = """
import os, runpy, sys

class Stop:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            print(os.environ.get("OMP_WAIT_POLICY"), flush=True)
            os._exit(0)
        return None

sys.meta_path.insert(0, Stop())
runpy.run_path(sys.argv[1], run_name="imported")  # the script's imports, not its main()
print("no torch", flush=True)
"""


def _env(**extra: str) -> dict[str, str]:
    """This environment without the wait keys (as a fresh shell's), plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k not in WAIT_KEYS}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return {**env, **extra}


def _run(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], env=env, cwd=ROOT, capture_output=True,
                          text=True, check=True, timeout=300)  # fmt: skip


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.name for s in SCRIPTS])
def test_every_script_sets_the_passive_wait_before_torch_loads(script: Path) -> None:
    """Each script's imports, in a fresh process whose environment says nothing of the wait,
    reach torch only once ``OMP_WAIT_POLICY=PASSIVE`` is set (libgomp reads it then, once)."""
    out = _run("-c", _FIRST_TORCH, str(script), env=_env()).stdout.split()
    assert out in (["PASSIVE"], ["no", "torch"]), (script.name, out)


def test_torchs_openmp_runtime_reads_the_passive_wait() -> None:
    """libgomp, loaded by torch after the package's import, spins 0 times (its default is
    300,000): what it prints of its settings under ``OMP_DISPLAY_ENV=VERBOSE``."""
    code = "import surrogate.gp.training, torch; torch.ones(1)"
    err = _run("-c", code, env=_env(OMP_DISPLAY_ENV="VERBOSE")).stderr
    assert "GOMP_SPINCOUNT = '0'" in err, err


@pytest.mark.parametrize("key,value", [("OMP_WAIT_POLICY", "ACTIVE"), ("GOMP_SPINCOUNT", "1000")])
def test_the_users_wait_is_kept(monkeypatch: pytest.MonkeyPatch, key: str, value: str) -> None:
    """Either wait key in the environment is the user's choice: nothing is set beside it."""
    for k in WAIT_KEYS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv(key, value)
    assert not passive_wait()  # torch is loaded in this process: too late for its runtime
    assert {k: os.environ.get(k) for k in WAIT_KEYS} == {
        k: value if k == key else None for k in WAIT_KEYS
    }
    monkeypatch.delenv(key)
    passive_wait()
    assert os.environ.get("OMP_WAIT_POLICY") == "PASSIVE"
