#!/usr/bin/env bash
# The GPU checks in one call of a few minutes, on a machine with an NVIDIA GPU and torch, numba and numba-cuda
# installed (run from a checkout): the tests that need a GPU apart from the CUDA kernel target's (whose first
# compile takes far longer), then the throughput of the GPU default (the torch target) at batches of 2^14 to 2^20
# beside the CPU kernels. Output goes to stdout and, where OUT is set, to $OUT/gpu-check.log.
#
#   bash scripts/gpu-check.sh             # the few-minute run
#   KERNELS=1 bash scripts/gpu-check.sh   # also the CUDA kernel target: its tests, its compile and throughput
set -uo pipefail
cd "$(dirname "$0")/.."
log="${OUT:-/tmp}/gpu-check.log"
export PYTHONUNBUFFERED=1
{
  python -c "import torch; print('torch', torch.__version__, 'CUDA', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"
  pip install -q --no-deps -e . 2>/dev/null || export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
  timeout 300 python -m pytest -q -m cuda -p no:cacheprovider tests/test_torch_target.py
  if [ "${KERNELS:-0}" = 1 ]; then
    timeout 1800 python -m pytest -q -m cuda -p no:cacheprovider tests/test_cuda.py
    timeout 1800 python -m torchrod bench gpu --skip-tests
  else
    timeout 300 python -m torchrod bench gpu --skip-tests --skip-kernels
  fi
} 2>&1 | tee "$log"
