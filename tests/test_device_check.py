"""scripts/device_check.sh (the GPU check, run where a GPU is lent) is valid bash and names only
test files, scripts and benchmark functions that exist: it cannot be run in CI, so what it
calls is checked here."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "device_check.sh"


def test_the_device_check_is_bash_and_names_what_exists() -> None:
    subprocess.run(["bash", "-n", str(SCRIPT)], check=True)
    text = SCRIPT.read_text()
    paths = set(re.findall(r"(?:tests|scripts)/[\w/]+\.py", text))
    assert len(paths) >= 12
    missing = sorted(p for p in paths if not (ROOT / p).is_file())
    assert not missing, missing
    from surrogate.benchmarks import ssa

    assert callable(ssa.bench_cuda) and callable(ssa.cuda_law_check)
