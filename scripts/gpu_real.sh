#!/usr/bin/env bash
# Fine-tune the shipped policy on real WOMD scenes mixed with urban procedural ones (configs/train/real_mix.yaml),
# with and without the 120-degree view cone, side by side on one GPU; then evaluate them, the shipped policy and
# the expert replay on held-out real scenes in every collision mode, and the policies on held-out procedural
# scenes (seed 90000, the procedural bar).
#   (cd /tmp && bash REPO/scripts/gpu_real.sh TRAIN_STORE HELDOUT_STORE OUT_DIR [TIME_LIMIT_S])
# Run it outside the checkout, with the package installed (the device README). OUT_DIR gets rates.jsonl
# (one evaluation per line), the runs' curves and a tarball of their metrics and configs.
set -uo pipefail
train=$1 held=$2 out=$3 tl=${4:-270}
repo=$(cd "$(dirname "$0")/.." && pwd)
runs=${RUNS:-/tmp/runs}
phase=${PHASE:-all}  # train | eval | all: the two halves fit one device call each
tg="python3 -m tg_gpudrive.cli"
mix="mix:procedural:all[parking=0.8,stop_lines=0.5,kerb_stops=0.5,lane_offset=0.4,park_reach=1.5]=0.5,$train=0.5"
mkdir -p "$out"
[ "$phase" = eval ] || for v in 360 120; do
  $tg train --config "$repo/configs/train/real_mix.yaml" --set "scenes=$mix" --set time_limit_s="$tl" \
    --set env.view_angle=$v --out "$runs/real_$v" --overwrite --json > "$out/train_$v.json" 2> "$out/train_$v.log" &
done
wait
[ "$phase" = train ] && { tail -n 3 "$out"/train_*.log; exit 0; }
rates() {  # who scenes extra...
  local who=$1 scenes=$2; shift 2
  $tg evaluate $who --scenes "$scenes" --device cuda --seed 0 --json "$@" 2>/dev/null | tail -1 |
    python3 -c "import json,sys; d=json.load(sys.stdin); print(json.dumps({'who': '$who', 'scenes': '$scenes', 'args': '$*', **{k: d.get(k) for k in ('collision_mode','agent_episodes','goal_rate','collision_rate','offroad_rate','score_rate','ci95','agents_dropped','agents_log_infeasible','max_agents')}}))" >> "$out/rates.jsonl"
}
for mode in ignore stop remove; do
  rates "--policy expert" "$held" --episodes 17 --collision-mode $mode
  for who in shipped "$runs/real_360" "$runs/real_120"; do
    rates "--checkpoint $who" "$held" --episodes 17 --collision-mode $mode
  done
done
for who in shipped "$runs/real_360" "$runs/real_120"; do
  rates "--checkpoint $who" procedural:all --num-scenes 256 --episodes 256
done
for v in 360 120; do
  cp "$runs/real_$v/curves.png" "$out/curves_$v.png"
done
tar czf "$out/runs.tgz" -C "$runs" real_360/metrics.csv real_120/metrics.csv real_360/config.json real_120/config.json
ls -la "$out"
