#!/usr/bin/env bash
# Issue 30's GPU checks in one device call (3-5 minutes on an H100/H200): the CUDA contract, graph
# and fused-kernel tests, where PF-PF(LEDH)'s time goes (profile_step), seed 000 Table II's LEDH row
# (100 and 500 trials x 500 particles x 40 steps, float64) through the runner with the default
# (fused kernel + CUDA graph) and the plain torch path, and the bootstrap PF against PyDPF. The
# device image has torch and Triton but no Hydra: carry .whl with hydra-core, omegaconf,
# antlr4-python3-runtime and pydpf wheels (RESULTS.md "GPU"). Results land in $OUT.
set -u
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
python3 -c "import torch, triton; print(torch.__version__, triton.__version__, torch.cuda.get_device_name())"
timeout 240 python3 -m pytest -q -p no:cacheprovider tests/flows/test_fused.py tests/test_cudagraphs.py \
  tests/filters/test_contract.py tests/test_random.py tests/test_bad_inputs.py tests/test_philox_fused.py -k "cuda or fused" 2>&1 | tail -8
prof() { timeout 120 python3 -m experiments.benchmarks.profile_step --device cuda "$@" 2>&1 | grep -v -E "USDT|_warn_once|Profiler clears"; }
prof --top 20 | tee "$OUT/profile_ledh_fused.txt" | head -30
prof --top 0 --graphs 0
prof --top 0 --trials 4
prof --top 0 --trials 4 --graphs 0
ledh() {  # name, then runner overrides
  local name=$1; shift
  timeout 300 python3 experiments/run.py experiment=seed000_table2 'filter=[pfpf_ledh]' device=cuda memory_budget_gb=100 \
    hydra.run.dir=/tmp/runs/$name "$@" 2>&1 | grep -E "^\| pfpf|rror|capture" ; cp /tmp/runs/$name/per_trial.csv "$OUT/$name.csv"
}
ledh fused_100 trials=100 chunk_size=100
ledh torch_100 trials=100 chunk_size=100 tuning.fused_flows=0 tuning.cuda_graphs=0
ledh fused_500 trials=500 chunk_size=500
ledh torch_500 trials=500 chunk_size=500 tuning.fused_flows=0 tuning.cuda_graphs=0
