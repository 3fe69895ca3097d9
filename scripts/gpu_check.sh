#!/usr/bin/env bash
# On a machine with a CUDA GPU, from the repository root, with the Python that has torch (no install needed: the
# checkout runs from PYTHONPATH): the CUDA tests, then the GPU benchmark (benchmarks/gpu.py: scenarios (a) and (b),
# 150 distinct 1280x720 frames in every row, warm and cold columns, the paper's loop both ways; about 8 minutes on
# an H100 by estimate: the paper's loop alone runs 150 frames four times at ~3 frames/s).
#   MASSVIZ_SHARED=/path/to/shared bash scripts/gpu_check.sh [benchmark options, e.g. --frames 60]
# Writes $OUT/tests.log, $OUT/bench.log and $OUT/gpu.json (OUT defaults to out/gpu).
set -uo pipefail
cd "$(dirname "$0")/.."
out="${OUT:-out/gpu}"
mkdir -p "$out"
py="${PYTHON:-python3}"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
shared="${MASSVIZ_SHARED:-../shared}"
export MASSVIZ_WEIGHTS="${MASSVIZ_WEIGHTS:-$shared/weights/corsmal_visual/Encoder_pool_aug_158.torch}"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv,noheader 2>&1 | tee "$out/gpu.txt"
"$py" -c 'import torch, torchvision; print("torch", torch.__version__, "torchvision", torchvision.__version__,
"cuda", torch.cuda.is_available())' 2>&1 | tee -a "$out/gpu.txt"
# the CUDA tests and the device path's CPU tests (what CI runs of it), in one process
"$py" -m pytest -q -p no:cacheprovider -rs -s tests/test_device_path.py tests/test_device_kernels.py \
  tests/test_speed.py -k "cuda or device or window or detect_ahead or resize" 2>&1 | tee "$out/tests.log"
tests=${PIPESTATUS[0]}
"$py" benchmarks/gpu.py --json "$out/gpu.json" "$@" 2>&1 | tee "$out/bench.log"
bench=${PIPESTATUS[0]}
echo "gpu_check: tests exit $tests, benchmark exit $bench"
[ "$tests" = 0 ] && [ "$bench" = 0 ]
