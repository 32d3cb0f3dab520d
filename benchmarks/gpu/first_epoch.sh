#!/usr/bin/env bash
# The first epoch's breakdown (first_epoch.py) and train-many's throughput for K = 1, 2, 4, 8 runs
# together (one epoch of 400 frames each) on the same frames, as run on a lent machine, from the
# repository root, into OUT (its first argument).
set -u
OUT=${1:?usage: benchmarks/gpu/first_epoch.sh OUT}
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 MPLBACKEND=agg
W=$(mktemp -d)
export GEODEPTH_LITE_HOME=$W
python3 benchmarks/gpu/first_epoch.py --out "$OUT" --device cuda --channels-last --data-dir "$W/data" \
    2>&1 | tee "$OUT/first_epoch.txt"
D=$(dirname "$(find "$W/data" -name manifest.json | head -1)")
python3 -m geodepth_lite train-many --profile paper --cases 4 --dataset "$D" --device cuda --no-progress \
    --channels-last --train-frames 400 --val-frames 20 --epochs 1 --throughput 1 2 4 8 --time-limit 230 \
    --out "$W/many" 2>&1 | tee "$OUT/throughput.txt"
cp "$W/many/throughput.json" "$W/many/throughput.md" "$OUT/" 2>/dev/null
