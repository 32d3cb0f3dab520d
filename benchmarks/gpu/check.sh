#!/usr/bin/env bash
# The GPU check as run on a lent machine, from the repository root, into OUT (its first argument):
# gpu-check --full into OUT/gpu and its output into OUT/stdout.txt. docs/gpu_check_plan.md fixes how
# the record is read. Needs torch with CUDA (Triton for the fused search), numpy, scipy, Pillow, tqdm
# and PyYAML; no VTK (the data are made by the torch renderer) and no network.
set -u
OUT=${1:?usage: benchmarks/gpu/check.sh OUT}
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 MPLBACKEND=agg
GEODEPTH_LITE_HOME=$(mktemp -d)
export GEODEPTH_LITE_HOME
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -m geodepth_lite gpu-check --full --no-pytest --full-timeout 330 --many-timeout 90 --out "$OUT/gpu" \
    2>&1 | tee "$OUT/stdout.txt"
