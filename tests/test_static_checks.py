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
