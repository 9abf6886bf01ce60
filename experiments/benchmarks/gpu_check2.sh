#!/usr/bin/env bash
# Issue 30, second GPU call of 2026-11-26 (seventh session): the CUDA tests with the graphed
# bootstrap step and the GPU tile bound, the GPU goals table again (bench_gpu: the BPF against
# PyDPF with per-trial streams, replayed from a CUDA graph, and with a torch.Generator), then
# seed 000 Table II rows owed at 500 trials until the deadline. Carry .whl (RESULTS.md "GPU").
set -u
export PYTHONUNBUFFERED=1
END=$((SECONDS + ${BUDGET:-370}))
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
F() { grep -v -E "USDT|_warn_once|Profiler clears"; }
echo "== CUDA tests"; date
# the quick files first: on a fresh machine Triton compiles every kernel, and the contract tests'
# share of that took most of 150 s (2026-11-26); -v names each test as it passes
timeout ${TESTS_S:-240} python3 -m pytest -v -p no:cacheprovider -rfEw --durations=12 tests/test_random.py \
  tests/test_bad_inputs.py tests/test_philox_fused.py tests/test_graph_step.py tests/flows/test_fused.py \
  tests/test_cudagraphs.py tests/filters/test_contract.py -k cuda 2>&1 | grep -E "PASS|FAIL|ERROR|SKIP|passed|failed|s call" \
  > "$OUT/cuda_tests.txt"; grep -c PASSED "$OUT/cuda_tests.txt"; grep -E "FAIL|ERROR|passed|failed" "$OUT/cuda_tests.txt" | tail -12
echo "== bench_gpu"; date
timeout 100 python3 -m experiments.benchmarks.bench_gpu --device cuda --reps 2 --tests 0 2>&1 | F | grep -E "^\{|^\| " | tail -14
cp experiments/benchmarks/results_gpu.md experiments/benchmarks/results_gpu.json "$OUT/" 2>/dev/null
run() {  # name, then the runner's arguments
  local name=$1; shift
  local left=$((END - SECONDS))
  if [ $left -lt 25 ]; then echo "skip $name ($left s left)"; return; fi
  echo "== $name ($left s left)"; date
  timeout $left python3 experiments/run.py experiment=seed000_table2 trials=500 device=cuda memory_budget_gb=70 \
    plots=false progress=false hydra.run.dir=/tmp/runs/$name "$@" 2>&1 | grep -E "^\| |rror" | cut -c1-260
  cp /tmp/runs/$name/per_trial.csv "$OUT/s000_$name.csv" 2>/dev/null
}
run ledh_flows "filter=[ledh]" chunk_size=500
run gpfis "filter=[gpfis]" chunk_size=100
run sw0001 "filter=[pfpf_ledh,ekf,ukf]" model.sigma_w=0.001 chunk_size=500
run geodesic_flows "filter=[geodesic]" chunk_size=100
date
