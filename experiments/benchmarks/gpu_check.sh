#!/usr/bin/env bash
# Issue 30's GPU checks in one device call (~6 minutes on an H100/H200), each step under its own
# timeout and teed to $OUT so that a slow one keeps the others: the CUDA tests (contract, graph,
# fused-kernel, fused-Philox, random and bad-input tests, -k cuda), the GPU goals table (bench_gpu:
# PF-PF(LEDH) at 100 and 500 trials, GPFIS against it, the bootstrap PF against PyDPF), seed 000
# Table II's LEDH row through the runner (with its warm-up), the per-particle EKF update in k x k
# algebra against the Joseph form (tuning.structured_update), and where the time goes
# (profile_step: PF-PF(LEDH) at 100 x 500, the bootstrap PF at 100 x 200). The device image has
# torch and Triton but no Hydra: carry .whl with hydra-core, omegaconf, antlr4-python3-runtime and
# pydpf wheels (RESULTS.md "GPU").
set -u
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
F() { grep -v -E "USDT|_warn_once|Profiler clears"; }
P="python3 -m experiments.benchmarks"
python3 -c "import torch, triton; print(torch.__version__, triton.__version__, torch.cuda.get_device_name())"
echo "== CUDA tests"; date
timeout 240 python3 -m pytest -q -p no:cacheprovider -rfE tests/flows/test_fused.py tests/test_cudagraphs.py \
  tests/filters/test_contract.py tests/test_random.py tests/test_bad_inputs.py tests/test_philox_fused.py \
  -k cuda 2>&1 | tail -40 > "$OUT/cuda_tests.txt"; tail -8 "$OUT/cuda_tests.txt"
echo "== bench_gpu"; date
timeout 200 $P.bench_gpu --device cuda --reps 2 --tests 0 2>&1 | F | tail -16
cp experiments/benchmarks/results_gpu.md experiments/benchmarks/results_gpu.json "$OUT/" 2>/dev/null
echo "== runner"; date
timeout 90 python3 experiments/run.py experiment=seed000_table2 'filter=[pfpf_ledh]' device=cuda memory_budget_gb=60 \
  hydra.run.dir=/tmp/runs/ledh_100 trials=100 chunk_size=100 plots=false 2>&1 | grep -E "^\| pfpf|rror|warm"
cp /tmp/runs/ledh_100/summary.csv "$OUT/ledh_100_summary.csv" 2>/dev/null
echo "== structured_update A/B"; date
for su in 0 1; do timeout 50 $P.profile_step --device cuda --trials 100 --steps 10 --top 0 --structured-update $su 2>&1 | F | tail -1; done
echo "== profiles"; date
timeout 50 $P.profile_step --device cuda --top 30 2>&1 | F > "$OUT/profile_ledh.txt"; cut -c1-60,150-200 "$OUT/profile_ledh.txt" | head -26
timeout 40 $P.profile_step --filter bpf --device cuda --trials 100 --particles 200 --dtype float32 --top 20 2>&1 | F > "$OUT/profile_bpf.txt"
cut -c1-60,150-200 "$OUT/profile_bpf.txt" | head -8
date
