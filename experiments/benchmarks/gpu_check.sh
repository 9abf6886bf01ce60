#!/usr/bin/env bash
# The GPU checks in one device call (under 9 minutes on an H100/H200). Each step runs under its own
# cap (its own limit or what is left of BUDGET seconds), so a slow step keeps the others; a table
# of the rows goes to $OUT/gpu_check.md, the test lines to $OUT/cuda_tests.txt.
#
#   1. the CUDA contract tests (every filter on CUDA, with and without missing observations, the
#      smoothers, the fused kernels in both forms, the graphed flow loop and particle-filter step,
#      the random streams and bad inputs), first;
#   2. the run command as a user runs it: acoustic tracking, PF-PF(LEDH) and the bootstrap PF,
#      100 trials x 500 particles x 40 steps, float64, on a fresh machine (cold: the kernels compile)
#      then again (warm), then one chunk of 100 trials, then float32 (the kernel in float64 arithmetic,
#      then in float32: tuning.kernel_float32=1); wall time of each command and
#      the filters' own seconds per trial-step and warm-up from its summary.csv, the phases of its
#      wall time from its log, float32 against float64 paired per trial (experiments.benchmarks.paired),
#      and the start-up (imports, CUDA initialisation) on the machine;
#   3. bench_gpu's PF-PF(LEDH) rows (one call of 100 and of 500 trials: the kernels' time);
#   4. Lorenz-96 at d = 4000, 10^5 and 10^6 with the ETKF and LETKF (RMSE and seconds per step), and
#      the run command with a bootstrap PF of 10^7 particles (acoustic, one trial).
#
# The device image has torch and Triton but no Hydra: carry .whl with the hydra-core, omegaconf and
# antlr4-python3-runtime wheels (docs/guide/gpu.md), e.g. run(command="bash experiments/benchmarks/gpu_check.sh",
# carry=[".whl"]).
#
# PARTS (default "tests commands bench") picks what runs, so the checks can be split over two device
# calls when the CUDA tests take long: PARTS=tests, PARTS=commands (the run command's rows, start-up,
# float32 pairs), PARTS=bench (bench_gpu, Lorenz-96, a bootstrap PF with 10^7 particles).
set -u
export PYTHONUNBUFFERED=1
PARTS=${PARTS:-"tests commands bench"}
want() { case " $PARTS " in *" $1 "*) return 0 ;; esac; return 1; }
END=$((SECONDS + ${BUDGET:-500}))
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
# byte-compile as `pip install` does for a user (the working tree arrives without __pycache__; compiling
# it at the first import cost 5.4 s of that command's wall time on 2026-11-27, which no user pays)
python3 -m compileall -q -j 0 torchflow experiments /tmp/site > /dev/null
export PYTHONPATH=/tmp/site:$PWD
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
MD="$OUT/gpu_check.md"
left() { echo $((END - SECONDS)); }
cap() { local l; l=$(left); [ "$1" -lt "$l" ] && echo "$1" || echo "$l"; }
now() { date +%s.%N; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$MD"
python3 -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__)" | tee -a "$MD"

if want tests; then
echo "== CUDA contract tests ($(left) s left)"; date
timeout "$(cap 300)" python3 -m pytest -q -p no:cacheprovider -rfE tests/filters/test_contract.py tests/flows/test_fused.py \
  tests/test_cudagraphs.py tests/test_graph_step.py tests/test_random.py tests/test_bad_inputs.py tests/test_philox_fused.py \
  tests/models/test_model_contract.py tests/filters/test_missing.py tests/test_smoothing.py \
  tests/filters/test_marginal.py tests/test_per_trial.py tests/test_inference.py \
  $(ls tests/filters/test_ensemble.py 2>/dev/null) -k "cuda or model_contract" 2>&1 | tail -25 > "$OUT/cuda_tests.txt"
tail -4 "$OUT/cuda_tests.txt"; { echo; echo "## CUDA tests"; tail -1 "$OUT/cuda_tests.txt"; } >> "$MD"
fi

run_cmd() {  # label, cap, extra settings...
  local label=$1 limit=$2; shift 2
  local dir=/tmp/runs/$label t0 t1
  t0=$(now)
  timeout "$(cap "$limit")" python3 -m torchflow model=acoustic 'filter=[pfpf_ledh,bpf]' trials=100 device=cuda plots=false \
    progress=false hydra.run.dir=$dir "$@" > "$OUT/run_$label.log" 2>&1
  local rc=$?
  t1=$(now)
  printf '| %s | %s | %s |' "$label" "$rc" "$(python3 -c "print(f'{$t1 - $t0:.1f}')")" >> "$MD"
  python3 - "$dir/summary.csv" >> "$MD" <<'EOF'
import csv, sys
try:
    rows = list(csv.DictReader(open(sys.argv[1])))
except OSError:
    rows = []
print(" " + " ; ".join(f"{r.get('filter')}: {float(r.get('sec_per_step') or 'nan'):.3g} s per trial-step, "
                        f"warm-up {float(r.get('warmup_sec') or 'nan'):.2f} s, OMAT {float(r.get('omat') or 'nan'):.3f}"
                        + (f", error {r['error']}" if r.get('error') else "") for r in rows) + " |")
EOF
  grep -iE "compil|error|warn|capture" "$OUT/run_$label.log" | head -3
  grep -E "wall seconds:|memory budget" "$OUT/run_$label.log" | sed "s/^/    $label: /" | tee -a "$OUT/phases.txt"
}
if want commands; then
{ echo; echo "## The run command (acoustic, [pfpf_ledh, bpf], 100 x 500 x 40)"; echo;
  echo "| run | exit | wall s | filters |"; echo "|---|---|---|---|"; } >> "$MD"
echo "== run command: cold ($(left) s left)"; date
run_cmd cold 150
echo "== run command: warm ($(left) s left)"; date
run_cmd warm 70
echo "== run command: one chunk of 100 ($(left) s left)"; date
run_cmd chunk100 60 chunk_size=100
echo "== run command: float32 ($(left) s left)"; date
run_cmd float32 60 dtype=float32
echo "== run command: float32 in float32 arithmetic ($(left) s left)"; date
run_cmd float32_k32 60 dtype=float32 tuning.kernel_float32=1
tail -6 "$MD"
{ echo; echo "### Where a command's wall time goes (phases from its log)"; echo; echo '```'; cat "$OUT/phases.txt"; echo '```';
  echo; echo "### float32 against float64, paired per trial (the warm run and the float32 run: same seed, same trials)"; echo;
  python3 -m experiments.benchmarks.paired /tmp/runs/warm /tmp/runs/float32 --labels float64,float32 2>&1; echo;
  echo "with the kernel in float32 arithmetic (tuning.kernel_float32=1):"; echo;
  python3 -m experiments.benchmarks.paired /tmp/runs/warm /tmp/runs/float32_k32 --labels float64,float32k 2>&1; } >> "$MD"
{ echo; echo "### Start-up on this machine"; echo; echo '```';
  python3 -X importtime -c "import torchflow.app.cli" 2>&1 | tail -1 | sed 's/^/import torchflow.app.cli (us, cumulative): /';
  python3 -c "import time; t = time.perf_counter(); import torch; a = time.perf_counter(); torch.zeros(1, device='cuda'); torch.cuda.synchronize(); print(f'import torch {a - t:.2f} s, CUDA init {time.perf_counter() - a:.2f} s')";
  echo '```'; } >> "$MD"
fi

if want bench; then
echo "== bench_gpu PF-PF(LEDH) ($(left) s left)"; date
timeout "$(cap 120)" python3 -m experiments.benchmarks.bench_gpu --device cuda --reps 2 --tests 0 --gpfis-trials 0 \
  --bpf-ns 200 > "$OUT/bench_gpu.log" 2>&1
grep -E "^\| " "$OUT/bench_gpu.log" | tail -10 | tee -a "$MD"
grep -iE "capture failed|not replayed|warn" "$OUT/bench_gpu.log" | head -5 | sed 's/^/    /' | tee -a "$MD"
cp experiments/benchmarks/results/results_gpu.json "$OUT/" 2>/dev/null

echo "== Lorenz-96 d-scaling on the GPU: ETKF, LETKF ($(left) s left)"; date
{ echo; echo "## Lorenz-96 on the GPU (ETKF N = 28, LETKF N = 20, 100 steps, RMSE after 25)"; echo;
  echo "| d | filter | trials | RMSE | s/step | device |"; echo "|---|---|---|---|---|---|"; } >> "$MD"
timeout "$(cap 150)" python3 -m experiments.benchmarks.bench_lorenz96 --scaling-only --device cuda \
  --dims 4000 100000 1000000 --scaling-steps 100 --out "$OUT/lorenz96_gpu" 2>&1 | grep -E "^\| " | tee -a "$MD"

echo "== a bootstrap PF with 10^7 particles ($(left) s left)"; date
{ echo; echo "## Bootstrap PF, acoustic, 10^7 particles, 1 trial x 40 steps"; echo; echo "| run | exit | wall s | filters |";
  echo "|---|---|---|---|"; } >> "$MD"
t0=$(now)
timeout "$(cap 120)" python3 -m torchflow model=acoustic 'filter=[bpf]' n_particles=10000000 trials=1 device=cuda \
  plots=false progress=false hydra.run.dir=/tmp/runs/bpf1e7 > "$OUT/run_bpf1e7.log" 2>&1
rc=$?
printf '| bpf 1e7 | %s | %s | %s |\n' "$rc" "$(python3 -c "print(f'{$(now) - $t0:.1f}')")" \
  "$(grep -E '^\| bpf' "$OUT/run_bpf1e7.log" | head -1 | tr '|' ' ' | tr -s ' ')" >> "$MD"
cp /tmp/runs/bpf1e7/summary.csv "$OUT/bpf1e7_summary.csv" 2>/dev/null
fi
date
