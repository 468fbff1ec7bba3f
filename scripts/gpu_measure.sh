#!/usr/bin/env bash
# The GPU figures of BENCHMARKS.md, in the order they were taken. Run from the repo root on a
# machine where the project is importable (pip install -e . or PYTHONPATH), with $OUT a folder
# for the files that come back. Stage "a": tests + engine/env/store benchmarks; "b": training
# throughput and time to quality; "c": the beta x alpha flexibility grid.
set -u
R=$(pwd)
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
stage=${1:-a}
cd /tmp
if [ "$stage" = a ]; then
  python3 -m pytest -q -p no:cacheprovider "$R"/tests/test_kernels.py "$R"/tests/test_engine.py \
    "$R"/tests/test_envs.py "$R"/tests/test_losses.py -k cuda 2>&1 | tail -3
  python3 -m tg_gpudrive.cli benchmark --scenes procedural:all --device cuda --json \
    --worlds 1 64 1024 4096 8192 16384 --steps 50 2>/dev/null | tee "$OUT/bench_procedural.jsonl"
  python3 -m tg_gpudrive.cli benchmark --scenes "$R"/tests/data --num-scenes 2 --device cuda --json \
    --worlds 1024 4096 8192 --steps 50 2>/dev/null | tee "$OUT/bench_womd.jsonl"
  python3 -m tg_gpudrive.cli benchmark --scenes procedural:all --device cuda --json --no-graph \
    --worlds 4096 --steps 50 2>/dev/null | tee "$OUT/bench_nograph.jsonl"
  python3 "$R"/scripts/bench_envs.py --device cuda --worlds 1024 --steps 100 2>/dev/null | tee "$OUT/bench_envs.json"
  python3 -m tg_gpudrive.cli simulate --scenes procedural:all --worlds 1024 --num-scenes 120 --device cuda \
    --policy expert --json 2>/dev/null | tee "$OUT/simulate_expert.json"
  python3 "$R"/scripts/bench_store.py --n 10000 --worlds 4096 --workers 16 --out /tmp/store10k 2>&1 \
    | tail -3 | tee "$OUT/bench_store.txt"
fi
if [ "$stage" = b ]; then
  timeout ${TRAIN_SECONDS:-500} python3 -m tg_gpudrive.cli train --config "$R"/configs/train/gpu.yaml --out /tmp/run_gpu \
    --set checkpoint_every=10 2>&1 | tr '\r' '\n' | grep -v "^$" | tail -3
  cp /tmp/run_gpu/metrics.csv "$OUT/train_gpu_metrics.csv"
  python3 -c "from tg_gpudrive.learn.plots import plot_curves; plot_curves('/tmp/run_gpu/metrics.csv', '$OUT/train_gpu_curves.png')"
fi
if [ "$stage" = c ]; then
  python3 "$R"/scripts/run_grid.py --base "$R"/configs/train/gpu.yaml --grid "$R"/configs/train/grid.yaml --out /tmp/grid \
    --set scenes=procedural:dense_intersection --set control=nearest_conflict --set control_k=5 \
    --set num_scenes=256 --set num_worlds=256 --set updates=${GRID_UPDATES:-25} --set resample_every=0 \
    --set checkpoint_every=1000 2>"$OUT/grid_stderr.txt" | tail -20; tail -5 "$OUT/grid_stderr.txt"
  cp /tmp/grid/grid.json /tmp/grid/grid.md "$OUT/"
fi
if [ "$stage" = d ]; then  # 1 vs 2 GPUs (nvidia-h200-x2)
  for n in 1 2; do
    timeout 200 python3 -m tg_gpudrive.cli train --config "$R"/configs/train/gpu.yaml --out /tmp/scale$n \
      --nproc $n --set updates=${SCALE_UPDATES:-12} --set resample_every=0 --set num_scenes=256 \
      --set checkpoint_every=1000 2>&1 | tr '\r' '\n' | grep -v "^$" | tail -1
    cp /tmp/scale$n/metrics.csv "$OUT/scale_${n}gpu.csv"
  done
fi
