#!/usr/bin/env bash
# Issue 30's GPU checks in one device call (about 5 minutes on an H100/H200): the CUDA contract and
# graph tests, PF-PF(LEDH) on seed 000 Table II (100 trials x 500 particles x 40 steps, float64)
# through the runner with the flow loop eager and replayed from a CUDA graph, 500 trials, and the
# bootstrap PF against PyDPF. The device image has torch but no Hydra: carry .whl with hydra-core,
# omegaconf, antlr4-python3-runtime and pydpf wheels (README "GPU"). Results land in $OUT.
set -u
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name())"
timeout 300 python3 -m pytest -q -p no:cacheprovider tests/test_cudagraphs.py tests/filters/test_contract.py \
  tests/test_random.py tests/test_bad_inputs.py -k cuda 2>&1 | tail -15
ledh() {  # name, then runner overrides
  local name=$1; shift
  timeout 300 python3 experiments/run.py experiment=seed000_table2 'filter=[pfpf_ledh]' device=cuda memory_budget_gb=100 \
    hydra.run.dir=/tmp/runs/$name "$@" 2>&1 | grep -E "^\| pfpf|rror|capture" ; cp /tmp/runs/$name/summary.csv "$OUT/$name.csv"
}
ledh eager_100 trials=100 chunk_size=100 tuning.cuda_graphs=0
ledh graph_100 trials=100 chunk_size=100
ledh graph_500 trials=500 chunk_size=500
ledh eager_500 trials=500 chunk_size=500 tuning.cuda_graphs=0
timeout 240 python3 experiments/benchmarks/peer_pydpf_bpf.py --device cuda --out "$OUT/peer_pydpf_bpf.md" 2>&1 | grep -v "^{"
