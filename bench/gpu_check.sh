#!/usr/bin/env bash
# One call on a fresh GPU machine whose python3 has jax with CUDA and CuPy (the device tool's
# image): issue 46's step figures and the README's main job on the GPU, alone, then the `gpu`
# tests beside the default test tier on the GPU, cut at the budget. Everything it writes goes to
# $OUT (default bench/results/gpu): logs and gpu_step_gpu.json with the device named.
#
#   bash bench/gpu_check.sh     # wheels in .whl/ (pythoncdt, cholespy, jaxopt) are installed first
#
# BUDGET_S (default 550) bounds the whole script: each phase's timeout is its own cap or what is
# left, whichever is less; the tier gets the rest. Its log has one line per test (-v), so a tier
# cut at the budget still says what passed and failed.
set -uo pipefail
cd "$(dirname "$0")/.."
START=$SECONDS
BUDGET_S=${BUDGET_S:-550}
OUT=${OUT:-bench/results/gpu}
mkdir -p "$OUT"
cap() { local left=$((BUDGET_S - (SECONDS - START))); ((left < $1)) && echo $((left > 5 ? left : 5)) || echo "$1"; }
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
# JAX preallocates 75% of the card by default; CuPy's pool takes what gDel2D needs from the rest.
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.6}
{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  nproc
  python3 -c "import jax, cupy; print('jax', jax.__version__, jax.devices()); print('cupy', cupy.__version__)"
  python3 -c "import jaxgeom.tessellation._triangulators as t; print('auto in 2D:', t.resolve_triangulator('auto', 2))"
  # tests/conftest.py's compile flags: an XLA that does not know one aborts, so one small test
  # under the real conftest probes them first
  timeout 120 python3 -m pytest -q -p no:cacheprovider -o addopts="" -k device_check_finds \
    tests/tessellation/test_gpu_triangulator.py >/dev/null 2>&1 && echo "conftest XLA flags ok" || echo "conftest XLA flags refused"
} 2>&1 | tee "$OUT/environment.log"
grep -q "flags ok" "$OUT/environment.log" || export JAXGEOM_TEST_XLA_OPT=default

echo "== step figures ($(cap 260) s)"
timeout "$(cap 260)" python3 bench/gpu_step.py --sizes ${SIZES:-100000 1000000} --triangulators cupy cdt --steps 10 --repeat 3 \
  --parts ${SIZES:-100000 1000000} --out "$OUT/gpu_step_gpu.json" >"$OUT/gpu_step.log" 2>&1
echo "rc=$?"; grep -E '^\{' "$OUT/gpu_step.log" | cut -c1-400

echo "== the README's main job (the compile cache in a fresh directory: a cold run, then a warm one)"
export JAXGEOM_COMPILE_CACHE_DIR=$(mktemp -d)
for run in cold warm; do
  TIMEFORMAT="$run %R s"
  { time timeout "$(cap 70)" python3 -m jaxgeom.cli simulate --no-progress 2>&1 | tail -4; } 2>&1 | tee -a "$OUT/main_job.log"
done
unset JAXGEOM_COMPILE_CACHE_DIR

echo "== gpu tests and the default tier on the GPU (float64), $(cap 600) s left"
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # many processes share the card
timeout "$(cap 600)" python3 -m pytest -q -p no:cacheprovider -o addopts="" -m gpu -rA \
  tests/tessellation/test_gpu_triangulator.py >"$OUT/gpu_tests.log" 2>&1 &
timeout "$(cap 600)" python3 -m pytest -p no:cacheprovider -o addopts="" -n 12 --dist worksteal -v --timeout 150 \
  -m "not slow and not notebooks and not multidevice and not gpu" -rfE ${TIER:-tests} >"$OUT/default_tier.log" 2>&1
echo "tier rc=$? (124: cut at the budget)"
wait
tail -4 "$OUT/gpu_tests.log"
grep -cE " PASSED " "$OUT/default_tier.log" | sed 's/^/tier passed so far: /'
grep -E " (FAILED|ERROR) " "$OUT/default_tier.log" | sed 's/^.*\(FAILED\|ERROR\) /\1 /' | sort -u | head -60
tail -3 "$OUT/default_tier.log"
