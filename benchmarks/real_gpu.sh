#!/usr/bin/env bash
# The training step of benchmarks/real_gpu.py on a GPU machine whose image lacks open3d (and perhaps ml-collections).
# Prepare here first, from the repository root, for each finished run of a real sequence:
#   python benchmarks/real_gpu.py --prepare --run_dir=RUN [--name=NAME]     # .gpu_data/NAME.pkl
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       -d .whl ml-collections==1.1.0                                        # where the GPU image lacks it
# then run this script there (bash benchmarks/real_gpu.sh [--names=a,b] [--max_train_s=150] [--budget_s=480]);
# it writes $OUT/NAME_trained.npz and $OUT/real_gpu.json.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! python3 -c "import ml_collections" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
# This checkout's package, whether or not the image has it installed
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
exec python3 benchmarks/real_gpu.py "$@"
