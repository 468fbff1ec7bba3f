#!/usr/bin/env bash
# Fine-tune the shipped policy on real WOMD scenes mixed with urban procedural ones (configs/train/real_mix.yaml)
# for the data-scaling curve: one run per number of real training scenes (0 = procedural alone, then the
# nested subsets of scripts/split_dev.py --subsets 5,15,30 and the whole training split), plus the whole
# split with the 120-degree view cone; runs are spread over the GPUs the machine has. Then evaluate every
# run on the held-out real scenes and on held-out procedural scenes (seed 90000, the procedural bar), and
# the whole-split run, the shipped policy and the expert replay in every collision mode.
#   (cd /tmp && [PHASE=train|eval|all] [ONLY="real0 real44"] bash REPO/scripts/gpu_real.sh STORES OUT_DIR [UPDATES])
# PHASE all (the default) trains and evaluates in one go: a device machine keeps /tmp only while warm.
# ONLY picks some of the runs below; TIME_LIMIT (s, default 470) bounds each training.
# STORES holds womd_dev_train, womd_dev_train_{5,15,30} and womd_dev_heldout (scripts/split_dev.py). Run it
# outside the checkout, with the package installed (the device README). OUT_DIR gets rates.jsonl (one
# evaluation per line), the runs' curves and a tarball of their metrics and configs.
set -uo pipefail
stores=$1 out=$2 updates=${3:-300}
repo=$(cd "$(dirname "$0")/.." && pwd)
runs=${RUNS:-/tmp/runs}
phase=${PHASE:-all}
tg="python3 -m tg_gpudrive.cli"
held=$stores/womd_dev_heldout
proc="procedural:all[parking=0.8,stop_lines=0.5,kerb_stops=0.5,lane_offset=0.4,park_reach=1.5,pedestrians=2,lane_changes=0.5]"
ngpu=$(nvidia-smi -L | wc -l)
# name  real store (- for none)  view angle
plan="real0 - 360
real5 $stores/womd_dev_train_5 360
real15 $stores/womd_dev_train_15 360
real30 $stores/womd_dev_train_30 360
real44 $stores/womd_dev_train 360
real44_v120 $stores/womd_dev_train 120"
[ -z "${ONLY:-}" ] || plan=$(grep -wE "^($(tr ' ' '|' <<< "$ONLY"))" <<< "$plan")
mkdir -p "$out" "$runs"
if [ "$phase" != eval ]; then
  k=0
  while read -r name store view; do
    scenes=$proc
    [ "$store" = - ] || scenes="mix:$proc=0.5,$store=0.5"
    CUDA_VISIBLE_DEVICES=$((k % ngpu)) $tg train --config "$repo/configs/train/real_mix.yaml" --set "scenes=$scenes" \
      --set updates="$updates" --set time_limit_s="${TIME_LIMIT:-470}" --set env.view_angle="$view" --out "$runs/$name" --overwrite \
      --json > "$out/train_$name.json" 2> "$out/train_$name.log" &
    k=$((k + 1))
  done <<< "$plan"
  wait
  [ "$phase" = train ] && exit 0
fi
rates() {  # gpu who scenes extra...
  local gpu=$1 who=$2 scenes=$3; shift 3
  CUDA_VISIBLE_DEVICES=$gpu $tg evaluate $who --scenes "$scenes" --device cuda --json "$@" 2>/dev/null | tail -1 |
    python3 -c "import json,sys; d=json.load(sys.stdin); print(json.dumps({'who': '$who', 'scenes': '$scenes', 'args': '$*', **{k: d.get(k) for k in ('collision_mode','agent_episodes','goal_rate','collision_rate','offroad_rate','score_rate','ci95','agents_dropped','agents_log_infeasible','max_agents')}}))" >> "$out/rates.jsonl"
}
k=0
while read -r name store view; do
  ( rates $((k % ngpu)) "--checkpoint $runs/$name" "$held" --episodes 17 --seed 0
    rates $((k % ngpu)) "--checkpoint $runs/$name" procedural:all --num-scenes 256 --episodes 256 --seed 90000 ) &
  k=$((k + 1))
done <<< "$plan"
( for mode in ignore stop remove; do
    rates 0 "--policy expert" "$held" --episodes 17 --seed 0 --collision-mode $mode
    rates 0 "--checkpoint shipped" "$held" --episodes 17 --seed 0 --collision-mode $mode
  done
  rates 0 "--checkpoint shipped" procedural:all --num-scenes 256 --episodes 256 --seed 90000 ) &
( for mode in stop remove; do
    rates 1 "--checkpoint $runs/real44" "$held" --episodes 17 --seed 0 --collision-mode $mode
  done
  rates 1 "--checkpoint $runs/real44" "$held" --episodes 17 --seed 0 --deterministic ) &
for f in "$out"/train_*.log; do tail -c 300 "$f" > "$f.tail" && mv "$f.tail" "$f"; done
wait
for name in $(cut -d' ' -f1 <<< "$plan"); do
  cp "$runs/$name/curves.png" "$out/curves_$name.png" 2>/dev/null
done
(cd "$runs" && tar czf "$out/runs.tgz" */metrics.csv */config.json)
cp "$runs/real44/checkpoint.pt" "$out/real44.pt" 2>/dev/null
ls -la "$out"
