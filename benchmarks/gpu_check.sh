#!/usr/bin/env bash
# The checks that need a GPU, as one command on a lent device machine (CONTRIBUTING.md, "On a
# GPU"): the CUDA tests (particle BP, limits, the observation's cues, register() against the
# CPU's result) and bench_registration's cross-performer case on cuda and on the CPU, same run.
# Writes tests.log and bench_*.log under $OUT (or /tmp/gpu_check). About 5 minutes on an H100.
#
# That machine's python3 holds a CUDA build of torch but not kornia: carry it as wheels in .whl
# (ignored by git), fetched here once with
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#     --implementation cp --platform manylinux_2_17_x86_64 -d .whl kornia==0.9.0 kornia_rs==0.2.0
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-/tmp/gpu_check}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$out/gpu.txt"
python3 -m pytest -q -p no:cacheprovider -rs \
  tests/pgm/test_particle_bp_cuda.py tests/pgm/test_limits.py \
  tests/motion/body/test_observation_cuda.py tests/motion/registration/test_device.py \
  2>&1 | tee "$out/tests.log"
for device in cuda cpu; do
  timeout 240 python3 benchmarks/bench_registration.py --quick --device "$device" \
    2>&1 | tee "$out/bench_$device.log"
done
