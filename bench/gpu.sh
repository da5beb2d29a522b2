#!/usr/bin/env bash
# The GPU session's measurements in one call of at most 8 minutes (issue 36): tests/test_gpu.py, `kinetix bench
# env|engine` at s, m, l x 256, 2,048, 16,384 and 65,536 (and the control-flow A/B at 2,048, profiled),
# `kinetix bench train` at 1,024 and 8,192 envs, then the general agent's run (issue 33's 200M-step SFL run,
# kinetix/agents/general/sfl-ln; TRAIN_RUNS names others), resumed at a GPU's batch (TRAIN_ARGS, default
# "--num-envs 4096 --num-minibatches 32": 8x the envs, the same samples per minibatch), until the budget ends. Results:
# $OUT/results.jsonl, $OUT/gpu.png, $OUT/tests.log, $OUT/log.txt, and two archives (the resumed runs, compacted;
# worker, training and profile logs). kinetix/bench/gpu.py says how it is planned.
#
#   OUT=/tmp/gpu-out bash bench/gpu.sh             # on the GPU machine (JAX with CUDA installed)
#   OUT=/tmp/gpu-out bash bench/gpu.sh --quick     # the dry run on a CPU: small batches, same code, no training
#   OUT=... TRAIN=0 bash bench/gpu.sh --no-flows --no-train-bench   # the grid only (kinetix.bench.gpu run -h)
#
# Works where viser, mcap and fastapi are missing (nothing here imports the server). The reference levels are
# read from $KINETIX_LEVELS (a kinetix-levels directory), else ../shared/kinetix-levels, else the project's
# stand-ins. BUDGET (seconds, default 470) bounds the Python part.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:?set OUT to the directory for the results}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
QUICK=()
WORKERS=${WORKERS:-10}
TEST_ARGS="tests/test_gpu.py -n 3"
PLATFORMS=cuda  # the benchmarks trace for the GPU alone (the tests keep the CPU too, to compare with it)
if [[ "${1:-}" == "--quick" ]]; then
  shift
  QUICK=(--quick)
  WORKERS=2
  TEST_ARGS="tests/test_gpu.py"
  PLATFORMS=cpu
fi
LEVELS=${KINETIX_LEVELS:-../shared/kinetix-levels}
[[ -d "$LEVELS" ]] || LEVELS=""
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
export KINETIX_JAX_CACHE=${KINETIX_JAX_CACHE:-$(mktemp -d /tmp/kinetix-gpu-cache.XXXX)}
LOGS=$(mktemp -d /tmp/kinetix-gpu-logs.XXXX)
RUNS=()  # TRAIN=0 (the default with --quick, which would train the repository's run on a CPU): no training
TRAIN_ARGS=${TRAIN_ARGS-"--num-envs 4096 --num-minibatches 32"}
if [[ "${TRAIN:-$(( ${#QUICK[@]} ? 0 : 1 ))}" != 0 ]]; then
  read -ra RUNS <<<"${TRAIN_RUNS:-kinetix/agents/general/sfl-ln}"
fi
{
  date -u; git log -1 --format='commit %H %s' 2>/dev/null || true
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv || true
  "$PY" -c "import jax, flax, optax, numpy; print('jax', jax.__version__, jax.devices(), 'flax', flax.__version__, 'optax', optax.__version__, 'numpy', numpy.__version__)"
  JAX_PLATFORMS=$PLATFORMS "$PY" -m kinetix.bench.gpu run --out "$OUT" --logs "$LOGS" ${LEVELS:+--shared "$LEVELS"} \
    "${QUICK[@]}" --workers "$WORKERS" --budget "${BUDGET:-470}" --tests "$TEST_ARGS" --train "${RUNS[@]}" \
    --train-args="$TRAIN_ARGS" "$@"
  if (( ${#RUNS[@]} )); then
    for run in "${RUNS[@]}"; do "$PY" -m kinetix.agents.resume compact "$run" || echo "compact $run failed"; done
    tar czf "$OUT/runs.tar.gz" "${RUNS[@]}"
  fi
  # The logs without the raw traces (16 MB per file comes back at most); the profiles' summaries are in results.
  tar czf "$OUT/logs.tar.gz" --exclude='*.xplane.pb' -C "$LOGS" .
  date -u
} 2>&1 | tee "$OUT/log.txt"
