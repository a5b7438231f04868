#!/usr/bin/env bash
# LeRobot for `iorthand export --format lerobot` and its tests, into the venv of the python given ($1).
# - lerobot 0.4.4 is the newest for Python 3.11 (0.5 and later need 3.12); it writes the v3 dataset format.
# - torch 2.14.1 with torchvision 0.29.1: lerobot.datasets imports torchvision, and the torchvision whose wheel
#   this machine holds for the CPU torch 2.13.0 (0.28.0) does not load with it. The pair installs from the
#   local pip cache (~1 min, ~4.7 GB: a CUDA build, which runs on the CPU).
# - lerobot itself goes in with --no-deps after the pieces it uses: its declared dependencies would replace
#   rerun-sdk and OpenCV and pull another torch (so `pip check` lists lerobot's unmet extras: expected).
# Best effort: a failure leaves lerobot out, and the tests that need it skip with the reason.
set -u
py=${1:?usage: install-lerobot.sh PYTHON}
if "$py" -c "import lerobot.datasets.lerobot_dataset" >/dev/null 2>&1; then
  exit 0
fi
echo "install-lerobot: installing torch, torchvision, torchcodec and lerobot 0.4.4 (about a minute)" >&2
if "$py" -m pip install --quiet torch==2.14.1 torchvision==0.29.1 torchcodec==0.17.0 "datasets>=4,<5" \
     "huggingface-hub>=0.34.2,<0.36" "accelerate>=1.10,<2" "av>=15,<16" "jsonlines>=4,<5" pandas \
   && "$py" -m pip install --quiet --no-deps lerobot==0.4.4; then
  exit 0
fi
echo "install-lerobot: could not install lerobot; the LeRobot export tests will skip" >&2
exit 1
