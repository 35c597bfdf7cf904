"""The linters CI holds the code to, run through the suite (CI runs only the README's command).

``ruff check`` and ``ruff format --check`` over the repository, and mypy over the package with
the settings in ``pyproject.toml`` (``[tool.mypy]``: the package's types as it is used, strict
flags on the contract's modules). Both tools come with the ``dev`` extras that ``setup.sh``
installs. mypy keeps its cache in ``.mypy_cache`` (git-ignored): ~40 s from a clean clone on a
busy 2-core box, ~2 s once cached.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(tool: str, *args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    if importlib.util.find_spec(tool) is None:
        pytest.fail(f"{tool} is not installed: `bash setup.sh` installs the dev extras")
    return subprocess.run(
        [sys.executable, "-m", tool, *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_ruff_check_is_clean() -> None:
    result = _run("ruff", "check", "--no-cache", ".", timeout=300)
    assert result.returncode == 0, f"ruff check:\n{result.stdout}{result.stderr}"


def test_ruff_format_is_clean() -> None:
    result = _run("ruff", "format", "--check", "--no-cache", ".", timeout=300)
    assert result.returncode == 0, f"ruff format --check:\n{result.stdout}{result.stderr}"


def test_mypy_is_clean() -> None:
    """mypy over ``surrogate`` (``files`` in pyproject.toml) reports no error."""
    result = _run("mypy", timeout=600)
    assert result.returncode == 0, f"mypy:\n{result.stdout}{result.stderr}"


def test_ruff_holds_the_parameter_and_complexity_limits() -> None:
    """The project's ruff settings refuse a function of 9 parameters (PLR0913, max-args 8) and
    one of complexity 16 (C901, max-complexity 15) in the package, and let 8 and 15 pass."""
    branches = "".join(f"    if x == {i}:\n        return {i}\n" for i in range(15))
    source = (
        "def nine(a, b, c, d, e, f, g, h, i):\n    return a\n\n\n"
        "def eight(a, b, c, d, e, f, g, h):\n    return a\n\n\n"
        f"def sixteen(x):\n{branches}    return -1\n\n\n"
        f"def fifteen(x):\n{branches.split('    if x == 14')[0]}    return -1\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise",
         "--select", "C901,PLR0913", "--stdin-filename", "surrogate/limits.py", "-"],
        cwd=ROOT, input=source, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    flagged = sorted(line.split(": ", 1)[1][:5] for line in result.stdout.splitlines()
                     if line.startswith("surrogate/limits.py"))  # fmt: skip
    assert flagged == ["C901 ", "PLR09"], result.stdout + result.stderr
    assert "`sixteen` is too complex (16 > 15)" in result.stdout
    assert "(9 > 8)" in result.stdout
