#!/usr/bin/env bash
# Install surrogate into the active Python environment.
# - Keeps an existing torch (e.g. your CUDA build). With no torch present it installs
#   torch==2.13.0, which on machines with a local CPU wheel (PIP_FIND_LINKS) takes the CPU build
#   instead of pulling gigabytes of CUDA packages; elsewhere it is the standard PyPI build.
# - Then installs the package in editable mode with its test and lint extras, and
#   byte-compiles it.
set -euo pipefail
cd "$(dirname "$0")"
PY="${PYTHON:-python3}"
if "$PY" -c "import torch" >/dev/null 2>&1; then
  echo "setup: keeping installed torch $("$PY" -c 'import torch; print(torch.__version__)')"
else
  echo "setup: installing torch==2.13.0"
  "$PY" -m pip install --quiet "torch==2.13.0"
fi
"$PY" -m pip install --quiet -e ".[dev]"
# An editable install leaves the package uncompiled: byte-compile it once, as a regular install
# does, so no run recompiles it (~0.3 s per process where PYTHONDONTWRITEBYTECODE is set)
"$PY" -m compileall -q surrogate scripts >/dev/null
echo "setup: done ($("$PY" -c 'import surrogate, torch, gpytorch; print("surrogate", surrogate.__version__, "torch", torch.__version__, "gpytorch", gpytorch.__version__)'))"
