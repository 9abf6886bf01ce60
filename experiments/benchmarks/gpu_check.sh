#!/usr/bin/env bash
# Issue 30's GPU checks in one device call (~5 minutes on an H100/H200): the fused pseudo-step's
# variants side by side (ab_fused), where PF-PF(LEDH)'s time goes (profile_step), seed 000 Table
# II's LEDH row through the runner, and the GPU goals table (bench_gpu: PF-PF(LEDH) at 100 and 500
# trials, GPFIS against it, the bootstrap PF against PyDPF, the CUDA contract, graph, fused-kernel
# and fused-Philox tests). The device image has torch and Triton but no Hydra: carry .whl with
# hydra-core, omegaconf, antlr4-python3-runtime and pydpf wheels (RESULTS.md "GPU"). Results land
# in $OUT.
set -u
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
F() { grep -v -E "USDT|_warn_once|Profiler clears"; }
python3 -c "import torch, triton; print(torch.__version__, triton.__version__, torch.cuda.get_device_name())"
timeout 90 python3 -m experiments.benchmarks.ab_fused --device cuda --trials 100 --steps 10 2>&1 | F | tee "$OUT/ab_fused.txt"
timeout 40 python3 -m experiments.benchmarks.profile_step --device cuda --top 30 2>&1 | F > "$OUT/profile_ledh.txt"
cut -c1-60,150-200 "$OUT/profile_ledh.txt" | head -24
timeout 60 python3 experiments/run.py experiment=seed000_table2 'filter=[pfpf_ledh]' device=cuda memory_budget_gb=60 \
  hydra.run.dir=/tmp/runs/ledh_100 trials=100 chunk_size=100 2>&1 | grep -E "^\| pfpf|rror"
cp /tmp/runs/ledh_100/per_trial.csv "$OUT/ledh_100.csv"
timeout 200 python3 -m experiments.benchmarks.bench_gpu --device cuda --reps 1 2>&1 | F | tail -22
cp experiments/benchmarks/results_gpu.md experiments/benchmarks/results_gpu.json "$OUT/"
