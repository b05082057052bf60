#!/usr/bin/env bash
# The CUDA check, a few minutes on a machine with a GPU (e.g. the device tool's):
#   bash bench/gpu_check.sh [extra bench overrides]
# 1. the CUDA tests (a smoke run per tracker on the GPU, the odometry on CUDA tensors);
# 2. the default benchmark on the cube with trainer=gpu: frames per second and the figures, as JSON in gpu.json.
set -euo pipefail
cd "$(dirname "$0")/.."
python -c "import torch; assert torch.cuda.is_available(), 'no CUDA device'; print('CUDA:', torch.cuda.get_device_name(0), torch.__version__)"
python -m pytest -q -p no:cacheprovider tests/tivne/test_cuda.py tests/tivne/slam/test_odometry.py -k "cuda or CUDA or smoke_run_on_cuda"
python bench/slam.py trainer=gpu "$@" --json gpu.json
python -c "import json; m = json.load(open('gpu.json')); print(f\"GPU: {1 / m['s_per_frame_after_first']:.1f} frames/s after the first frame\")"
