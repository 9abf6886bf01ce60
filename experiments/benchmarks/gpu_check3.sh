#!/usr/bin/env bash
# Issue 30, GPU call of the eighth session (2026-11-26): the fused LEDH kernel in information form
# (tuning.fused_info) against the row form in one process (ab_fused), its CUDA test, the four CUDA
# tests the seventh session did not reach and the graph step's (after its review fixes), the GPU
# goals table (bench_gpu), a profile of PF-PF(LEDH), then the CUDA contract tests until the
# deadline. Each step under its own timeout; results to $OUT. Carry .whl (RESULTS.md "GPU").
set -u
export PYTHONUNBUFFERED=1
END=$((SECONDS + ${BUDGET:-540}))
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
F() { grep -v -E "USDT|_warn_once|Profiler clears|RuntimeWarning|output = op"; }
left() { echo $((END - SECONDS)); }
cap() { local l; l=$(left); [ "$1" -lt "$l" ] && echo "$1" || echo "$l"; }  # a step's limit: its own or what is left
T() { python3 -m pytest -v -p no:cacheprovider -rfEw "$@" 2>&1 | grep -E "PASS|FAIL|ERROR|SKIP|passed|failed|Error|assert"; }
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
echo "== ab_fused ($(left) s left)"; date
timeout "$(cap 170)" python3 -m experiments.benchmarks.ab_fused --device cuda --trials 100 --short 2>&1 | F | tail -8 \
  | tee "$OUT/ab_fused.txt"
echo "== fused kernel on CUDA, both forms ($(left) s left)"; date
timeout "$(cap 150)" bash -c "$(declare -f T); T tests/flows/test_fused.py -k 'cuda and measurement'" | tee "$OUT/cuda_fused.txt"
echo "== CUDA tests not run last session, graph step ($(left) s left)"; date
timeout "$(cap 90)" bash -c "$(declare -f T); T tests/test_random.py tests/test_bad_inputs.py tests/test_philox_fused.py \
  tests/test_graph_step.py -k cuda" | tee "$OUT/cuda_tests.txt"
echo "== bench_gpu ($(left) s left)"; date
timeout "$(cap 110)" python3 -m experiments.benchmarks.bench_gpu --device cuda --reps 2 --tests 0 --gpfis-trials 0 2>&1 | F \
  | grep -E "^\{|^\| " | tail -14
cp experiments/benchmarks/results_gpu.md experiments/benchmarks/results_gpu.json "$OUT/" 2>/dev/null
echo "== profile PF-PF(LEDH) ($(left) s left)"; date
timeout "$(cap 60)" python3 -m experiments.benchmarks.profile_step --device cuda --top 30 2>&1 | F > "$OUT/profile_ledh.txt"
head -3 "$OUT/profile_ledh.txt"
echo "== CUDA contract and graph tests ($(left) s left)"; date
timeout "$(cap 400)" bash -c "$(declare -f T); T tests/filters/test_contract.py tests/test_cudagraphs.py -k cuda" \
  | tee "$OUT/cuda_contract.txt" | grep -E "FAIL|ERROR|passed|failed" | tail -12
date
