#!/usr/bin/env bash
# Every GPU measurement in one call (benchmarks/gpu_suite.py; JSON under $OUT, default
# benchmarks/results/). Prepare on a machine with open3d first, from the repository root:
#   python benchmarks/gpu_suite.py --prepare        # .gpu_data/demo.npz, the demo's rays and poses
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       -d .whl ml-collections==1.1.0             # where the GPU image lacks it (a pure-Python wheel)
# then run this script there (bash benchmarks/gpu_suite.sh [--budget_s=450] [--sections=...]).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! python3 -c "import ml_collections" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
if [ ! -f .gpu_data/demo.npz ]; then
  echo "error: .gpu_data/demo.npz is missing: run 'python benchmarks/gpu_suite.py --prepare' first" >&2
  exit 1
fi
# This checkout's package, whether or not the image has it installed
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export PYTHONUNBUFFERED=1
# JAX takes 75% of the GPU's memory by default; the torch peer (a subprocess) needs room too.
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.5}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
exec python3 benchmarks/gpu_suite.py "$@"
