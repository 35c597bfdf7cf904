"""How idle OpenMP threads wait: set at the package's import, before torch loads libgomp."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from surrogate.benchmarks.threads import busy_loops
from surrogate.threads import WAIT_KEYS, other_runnable, passive_wait, wait_policy

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((ROOT / "scripts").glob("*.py"))

# Stops at the first import of torch and prints whether the package has chosen the wait by
# then (what libgomp reads as torch loads it); "no torch" where the script's imports never
# load it.
_FIRST_TORCH = """
import os, runpy, sys

class Stop:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            print("surrogate.threads" in sys.modules, flush=True)
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
def test_every_script_chooses_the_wait_before_torch_loads(script: Path) -> None:
    """Each script's imports, in a fresh process whose environment says nothing of the wait,
    reach torch only once the package has chosen it (libgomp reads it then, once)."""
    out = _run("-c", _FIRST_TORCH, str(script), env=_env()).stdout.split()
    assert out in (["True"], ["no", "torch"]), (script.name, out)


def test_on_a_busy_machine_torchs_openmp_runtime_sleeps_at_once() -> None:
    """Beside two busy processes (on any machine of up to 3 cores) the package's import sets
    the passive wait and libgomp, loaded by torch after it, spins 0 times (its default is
    300,000): what it prints of its settings under ``OMP_DISPLAY_ENV=VERBOSE``."""
    if len(os.sched_getaffinity(0)) > 3:
        pytest.skip("two busy processes leave this machine's cores free")
    code = "import surrogate.gp.training, torch; torch.ones(1)"
    with busy_loops(2):
        err = _run("-c", code, env=_env(OMP_DISPLAY_ENV="VERBOSE")).stderr
    assert "GOMP_SPINCOUNT = '0'" in err, err


def test_the_wait_follows_the_other_runnable_processes() -> None:
    """Sleeping where others leave fewer than two cores free, libgomp's spin elsewhere; where
    the count cannot be read, nothing is set."""
    assert wait_policy(0, 2) is None and wait_policy(1, 2) == "PASSIVE"
    assert wait_policy(2, 2) == "PASSIVE" and wait_policy(14, 16) is None
    assert wait_policy(15, 16) == "PASSIVE" and wait_policy(0, 1) == "PASSIVE"
    assert wait_policy(None, 2) is None
    with busy_loops(1):
        assert (other_runnable() or 0) >= 1  # a busy loop is in every read


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
    passive_wait(others=5)  # a busy machine
    assert os.environ.get("OMP_WAIT_POLICY") == "PASSIVE"
    monkeypatch.delenv("OMP_WAIT_POLICY")
    passive_wait(others=0)  # a quiet one: libgomp's default
    assert os.environ.get("OMP_WAIT_POLICY") is None
