#!/usr/bin/env bash
# The device check (issue 53): everything that needs a CUDA GPU, in one run of <= ~6 minutes on
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
export SURROGATE_CACHE_DIR="${SURROGATE_CACHE_DIR:-$OUT/cache}"
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

# 1. every CUDA test (the CUDA SSA's kernel compiles and runs on the GPU too)
step cuda_tests 150 python3 -m pytest -q -n 8 -p no:cacheprovider tests/ctmc/test_cuda_ssa.py \
  tests/ctmc/test_ssa.py tests/ctmc/test_transition.py tests/gp/test_predictor.py \
  tests/simulate/test_support.py tests/simulate/test_recorders.py tests/simulate/test_coupling.py \
  tests/grid/test_fused.py tests/grid/test_exchange.py tests/stages/test_train_device.py
# 2. the CUDA SSA: its law against the compiled CPU SSA, and its speed on the phospho network
step cuda_ssa 120 python3 -c '
import json
from surrogate.benchmarks.ssa import bench_cuda, cuda_law_check
law = cuda_law_check()
print("law", json.dumps(law))
for cells in (10_000, 100_000):
    r = bench_cuda(cells, t_end=0.15, dt=0.05, repeats=2)
    print(f"phospho CUDA SSA {cells} cells: {r[\"cell_steps_per_s\"]:.3g} cell-steps/s, "
          f"{r[\"events_per_s\"]:.3g} events/s (first window {r[\"first_window_s\"]:.1f} s)")
assert law["within"], law
'
# 3. the main command on the GPU
step reproduce 150 python3 scripts/reproduce.py device=cuda
# 4. best vs best on the GPU: E. coli's full model and abstraction side by side (the speed
#    stage, on reproduce's fit from step 3), and the phospho abstraction's lookup loop
step speed_ecoli 60 python3 scripts/speed.py device=cuda n_cells=100000 steps=200
step lookup_phospho 60 python3 scripts/bench.py device=cuda lookup_only=true \
  model=ecoli_phospho model.burn_in=0 "sizes=[10000,100000]" "threads=[1]"
# 5. the band's field step against the agents' step
step band_bench 60 python3 scripts/bench_field.py device=cuda n_cells=1000000
echo "report: $REPORT"
