#!/usr/bin/env bash
# The device check (issue 53): everything that needs a CUDA GPU, in one run of <= ~9 minutes on
# one H200, its figures appended to $OUT/device_check.md (default data/device_check/).
#   bash scripts/device_check.sh            # from the repository root, the package installed
# Needs: torch with CUDA, numba-cuda, and the package's dependencies (hydra-core, omegaconf,
# python-libsbml ...: `pip install -e .`, or wheels on a machine without an index).
# Each step has its own time limit; a step that fails or times out is recorded and the next
# runs. Nothing here is timed by a test: this is the benchmark the docs quote.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-data/device_check}"
mkdir -p "$OUT"
REPORT="$OUT/device_check.md"
export PYTHONUNBUFFERED=1
# the runs' data and caches outside $OUT (what comes back is the report and the step logs)
DATA="${DATA:-$(mktemp -d -t surrogate_device.XXXX)}"
export SURROGATE_CACHE_DIR="${SURROGATE_CACHE_DIR:-$DATA/cache}"
{
  echo "# Device check $(date -u +%Y-%m-%dT%H:%MZ), $(git rev-parse --short HEAD 2>/dev/null)"
  python3 -c 'import torch; print("torch", torch.__version__, torch.cuda.get_device_name())'
} | tee "$REPORT"

step() {  # step NAME SECONDS COMMAND...: run it, record rc and wall time
  local name=$1 limit=$2
  shift 2
  local start=$SECONDS
  echo "## $name" | tee -a "$REPORT"
  timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
  local rc=$?
  tail -n 15 "$OUT/$name.log" >> "$REPORT"
  echo "- $name: rc=$rc, $((SECONDS - start)) s (limit $limit s)" | tee -a "$REPORT"
}

# Ordered so that what never ran on a GPU comes first; the limits sum to ~8.5 min.
# 1. the CUDA SSA: its law against the compiled CPU SSA, and its speed on the phospho network
step cuda_ssa 120 python3 -c '
import json
from surrogate.benchmarks.ssa import bench_cuda, cuda_law_check
law = cuda_law_check()
print("law", json.dumps(law))
for cells in (10_000, 100_000):
    r = bench_cuda(cells, t_end=0.15, dt=0.05, repeats=2)
    rate, events, first = r["cell_steps_per_s"], r["events_per_s"], r["first_window_s"]
    print(f"phospho CUDA SSA {cells} cells: {rate:.3g} cell-steps/s, {events:.3g} events/s "
          f"(first window {first:.1f} s)")
assert law["within"], law
'
# 2. every CUDA test (the CUDA SSA's kernel compiles and runs on the GPU too)
step cuda_tests 150 python3 -m pytest -q -n 8 -p no:cacheprovider tests/ctmc/test_cuda_ssa.py \
  tests/ctmc/test_ssa.py tests/ctmc/test_transition.py tests/gp/test_predictor.py \
  tests/simulate/test_support.py tests/simulate/test_recorders.py tests/simulate/test_coupling.py \
  tests/grid/test_fused.py tests/grid/test_exchange.py tests/stages/test_train_device.py
# 3. the expensive network's full model through the simulate stage (its defaults: burn-in and
#    equilibration included), the path that printed nothing in 150 s before the CUDA SSA
step phospho_full 90 python3 scripts/simulate.py experiment=phospho decision=full device=cuda \
  n_cells=10000 t_end=1 data_dir="$DATA"
# 4. the main command on the GPU (collect, the choice, train, simulate, evaluate, report)
step reproduce 170 python3 scripts/reproduce.py device=cuda data_dir="$DATA"
echo "report: $REPORT"
