#!/usr/bin/env bash
# One call on a fresh GPU machine whose python3 has jax with CUDA and CuPy (the device tool's
# image): the `gpu` tests, issue 46's step figures and the README's main job on the GPU, then
# the default test tier on the GPU under a time budget. Everything it writes goes to $OUT
# (default bench/results/gpu): logs and *_gpu.json with the device named.
#
#   bash bench/gpu_check.sh            # wheels in .whl/ (pythoncdt, cholespy, jaxopt) are installed first
#
# Budget: ~9 minutes (gpu tests ~1, steps ~4, main job ~1, default tier the rest, cut at TIER_S).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-bench/results/gpu}
TIER_S=${TIER_S:-200}
mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
# JAX preallocates 75% of the card; CuPy's pool takes what gDel2D needs from the rest.
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.6}
{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import jax, cupy; print('jax', jax.__version__, jax.devices()); print('cupy', cupy.__version__)"
} 2>&1 | tee "$OUT/environment.log"

echo "== gpu tests" | tee "$OUT/gpu_tests.log"
timeout 240 python3 -m pytest -q -p no:cacheprovider -o addopts="" -m gpu tests/tessellation/test_gpu_triangulator.py \
  2>&1 | tee -a "$OUT/gpu_tests.log" | tail -3

echo "== step figures"
timeout 300 python3 bench/gpu_step.py --sizes 100000 1000000 --triangulators cupy cdt --steps 10 --repeat 3 \
  --out "$OUT/gpu_step_gpu.json" 2>&1 | tee "$OUT/gpu_step.log" | tail -4

echo "== the README's main job (the compile cache in a fresh directory: a cold run, then a warm one)"
export JAXGEOM_COMPILE_CACHE_DIR=$(mktemp -d)
for run in cold warm; do
  /usr/bin/time -f "$run %e s" timeout 120 python3 -m jaxgeom.cli simulate --no-progress \
    2>&1 | tail -2 | tee -a "$OUT/main_job.log"
done

echo "== default tier on the GPU, float64, ${TIER_S} s budget"
timeout "$TIER_S" python3 -m pytest -q -p no:cacheprovider -o addopts="" -n 8 -m "not slow and not notebooks and not multidevice" \
  -rf tests/geometry tests/tessellation tests/swarm 2>&1 | tee "$OUT/default_tier.log" | tail -15
echo "rc=$? (124: cut at the budget; the counts so far are in $OUT/default_tier.log)"
