#!/usr/bin/env bash
# Engine and training throughput of an earlier tree against this one, on the same GPU, interleaved
# (old, new, old, new) so drift on the machine hits both: the check that a refactor costs no speed.
#   bash scripts/gpu_compare.sh OLD.tgz OUT_DIR      (run from this checkout's root, on the device)
# OLD.tgz: `git archive REV tg_gpudrive kernels pyproject.toml scripts configs | gzip > OLD.tgz`.
# OUT_DIR gets compare.jsonl: one line per measurement, {"tree", "round", "bench", ...the benchmark's JSON}.
# Engine: `tg-gpudrive benchmark --device cuda --json --steps 200`; training: scripts/bench_train.py on
# configs/train/gpu.yaml (8 updates, the median after two warm-up updates). ROUNDS (default 2) and
# TRAIN_UPDATES (default 8) buy a tighter comparison with more device time.
set -uo pipefail
old_tgz=$1 out=$2
mkdir -p "$out" /tmp/tree_old
tar xzf "$old_tgz" -C /tmp/tree_old
python3 -m pip install -q --no-deps --no-build-isolation --target /tmp/site_old /tmp/tree_old > /dev/null 2>&1 || exit 1
python3 -m pip install -q --no-deps --no-build-isolation --target /tmp/site_new . > /dev/null 2>&1 || exit 1
base=${PYTHONPATH:-}
for round in $(seq 1 "${ROUNDS:-2}"); do
  for tree in old new; do
    src=$([ $tree = old ] && echo /tmp/tree_old || pwd)
    export PYTHONPATH=/tmp/site_$tree${base:+:$base}
    (cd /tmp && python3 -m tg_gpudrive.cli benchmark --env-config "$src/configs/env/default.yaml" --device cuda --json --steps 200 2>>"$out/engine_$tree.err" | tail -1) |
      python3 -c "import json,sys; print(json.dumps({'tree': '$tree', 'round': $round, 'bench': 'engine', 'result': json.load(sys.stdin)}))" >> "$out/compare.jsonl"
    (cd /tmp && python3 "$src/scripts/bench_train.py" --config "$src/configs/train/gpu.yaml" --updates "${TRAIN_UPDATES:-8}" --variant base: 2>>"$out/train_$tree.err" | tail -1) |
      python3 -c "import json,sys; print(json.dumps({'tree': '$tree', 'round': $round, 'bench': 'train', 'result': json.load(sys.stdin)}))" >> "$out/compare.jsonl"
  done
done
cat "$out/compare.jsonl"
