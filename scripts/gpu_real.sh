#!/usr/bin/env bash
# Train on real WOMD scenes mixed with urban procedural ones (configs/train/real_mix.yaml, the shipped policy's recipe),
# one run per GPU of the machine, then evaluate every run on the held-out real scenes (every collision mode)
# and on held-out procedural scenes (seed 90000, the procedural bar), beside the shipped policy and the
# expert replay.
#   (cd /tmp && [PHASE=train|eval|all] [PLAN=file] bash REPO/scripts/gpu_real.sh STORES OUT_DIR [UPDATES])
# PHASE all (the default) trains and evaluates in one go: a device machine keeps /tmp only while warm.
# Training longer than one device call: PHASE=train TIME_LIMIT=480 first, then, back to back on the warm machine,
# RESUME=1 PHASE=train TIME_LIMIT=900 (each run continues from its checkpoint in $RUNS to 900 s in all), then PHASE=eval.
# GPUS (e.g. "2 3", default every GPU) are the GPUs the runs take in turn; TIME_LIMIT (s, default 470) bounds each training; EVAL_SEEDS (default 0) the sampling seeds of the held-out
# evaluation in ignore mode; URBAN_EXTRA (e.g. ",long_vehicles=0.1") adds generator knobs to the
# urban procedural part of every run. The plan (PLAN names a file of such lines; the default below is the
# data-scaling curve): one run per line, "name real-store extra-settings [urban-extra]", where real-store is a store name under STORES
# (womd_dev_train, womd_dev_train_5, ...; womd_dev_train+fast20 gives 20 % of the worlds to procedural scenes at
# real speeds, taken from the urban half) or - for procedural scenes alone,
# extra-settings a comma-separated list of --set KEY=VALUE (or -), and urban-extra generator knobs added to
# this run's urban part after URBAN_EXTRA's (e.g. ",long_vehicles=0.1"). A run whose name starts with "wm"
# first fine-tunes the shipped world model on the same real scenes and the procedural mix, on roads
# simplified as real_mix.yaml's (teacher
# forcing, then one closed-loop round) and trains with it as the magnet; its traffic rates on the held-out
# scenes (scripts/wm_traffic.py) go to OUT_DIR too.
# STORES holds the stores of scripts/split_dev.py (womd_dev_train*, womd_dev_heldout). Run it outside
# the checkout, with the package installed (the device README). OUT_DIR gets rates.jsonl (one evaluation
# per line), the runs' curves, a tarball of their metrics and configs, and each run's policy (scripts/slim_checkpoints.py).
set -uo pipefail
stores=$1 out=$2 updates=${3:-300}
repo=$(cd "$(dirname "$0")/.." && pwd)
runs=${RUNS:-/tmp/runs}
phase=${PHASE:-all}
tg="python3 -m tg_gpudrive.cli"
held=$stores/womd_dev_heldout
urban_knobs="procedural:all[parking=0.8,stop_lines=0.5,kerb_stops=0.5,lane_offset=0.4,park_reach=1.5,pedestrians=2,lane_changes=0.5,crossings=2${URBAN_EXTRA:-}"
read -ra gpus <<< "${GPUS:-$(seq -s' ' 0 $(($(nvidia-smi -L | wc -l) - 1)))}"
plan="real0 - -
real5 womd_dev_train_5 -
real15 womd_dev_train_15 -
real30 womd_dev_train_30 -
real44 womd_dev_train -"
[ -z "${PLAN:-}" ] || plan=$(grep -v '^#' "$PLAN")
mkdir -p "$out" "$runs"

mix() {  # store [urban-extra]: the training scenes of a real store (- for none); store+fastNN gives NN % of
  # the worlds to $fast, the procedural part at real speeds: longer arms, desired speeds N(16, 4) m/s, vehicles
  # placed up to 120 m upstream (against the urban mix, vehicle steps above 10 m/s rise from 7 % to 26 %, real
  # logs 26 %)
  local store=${1%+fast*} share=0 proc="$urban_knobs${2:-}]"
  local fast="${proc%]},speed_mean=16,speed_std=4,size_scale=2,spawn_range=120]"
  [[ $1 == *+fast* ]] && share=${1##*+fast}
  local urbanw fastw; read -r urbanw fastw <<< "$(python3 -c "print(round(0.5 - $share / 100, 2), $share / 100)")"
  if [ "$store" = - ]; then echo "$proc"
  elif [ "$share" = 0 ]; then echo "mix:$proc=0.5,$stores/$store=0.5"
  else echo "mix:$proc=$urbanw,$fast=$fastw,$stores/$store=0.5"; fi
}

world_model() {  # name store [urban-extra]: the shipped world model fine-tuned on the run's scenes -> $runs/name_wm/model.pt
  local name=$1 scenes; scenes=$(mix "$2" "${3:-}")
  rm -rf "$runs/${name}_wm_tf" "$runs/${name}_wm"  # train-world-model writes into a fresh directory
  $tg train-world-model --config "$repo/configs/worldmodel/gpu.yaml" --set init_model=shipped --set steps=1500 \
    --set env.road_simplify=0.1 --set "scenes=$scenes" --out "$runs/${name}_wm_tf" > "$out/wm_$name.log" 2>&1 &&
  $tg train-world-model --config "$repo/configs/worldmodel/gpu.yaml" --set init_model="$runs/${name}_wm_tf/model.pt" \
    --set steps=0 --set num_scenes=600 --set closed_loop_steps=600 --set closed_loop_rounds=1 \
    --set env.road_simplify=0.1 --set "scenes=$scenes" --out "$runs/${name}_wm" >> "$out/wm_$name.log" 2>&1
  tail -c 2000 "$out/wm_$name.log" > "$out/wm_$name.tail" && mv "$out/wm_$name.tail" "$out/wm_$name.log"
}

train() {  # gpu name store sets [urban-extra]
  local gpu=$1 name=$2 store=$3 sets=$4 urban=${5:-} extra=()
  [ "$sets" = - ] || IFS=, read -ra kv <<< "$sets"
  for s in "${kv[@]:-}"; do [ -z "$s" ] || extra+=(--set "$s"); done
  export CUDA_VISIBLE_DEVICES=$gpu
  if [[ $name == wm* ]]; then
    world_model "$name" "$store" "$urban" && extra+=(--set "prior_model=$runs/${name}_wm/model.pt")
    python3 "$repo/scripts/wm_traffic.py" --models shipped "$runs/${name}_wm/model.pt" --scenes "$held" \
      --num-scenes 17 --seeds 0 1 --json > "$out/wm_traffic_$name.json" 2>/dev/null
  fi
  if [ -n "${RESUME:-}" ] && [ -f "$runs/$name/checkpoint.pt" ]; then  # on to TIME_LIMIT s of training in all
    $tg train --resume "$runs/$name" --set updates="$updates" --set time_limit_s="${TIME_LIMIT:-470}" \
      --json > "$out/train_$name.json" 2> "$out/train_$name.log"
  else
    $tg train --config "$repo/configs/train/real_mix.yaml" --set "scenes=$(mix "$store" "$urban")" --set updates="$updates" \
      --set time_limit_s="${TIME_LIMIT:-470}" "${extra[@]}" --out "$runs/$name" --overwrite \
      --json > "$out/train_$name.json" 2> "$out/train_$name.log"
  fi
  tail -c 600 "$out/train_$name.log" > "$out/train_$name.tail" && mv "$out/train_$name.tail" "$out/train_$name.log"
}

rates() {  # gpu who scenes extra...
  local gpu=$1 who=$2 scenes=$3; shift 3
  CUDA_VISIBLE_DEVICES=$gpu $tg evaluate $who --scenes "$scenes" --device cuda --json "$@" 2>/dev/null | tail -1 |
    python3 -c "import json,sys; d=json.load(sys.stdin); print(json.dumps({'who': '$who', 'scenes': '$scenes', 'args': '$*', **{k: d.get(k) for k in ('collision_mode','agent_episodes','goal_rate','collision_rate','offroad_rate','score_rate','ci95','agents_dropped','agents_log_infeasible','max_agents')}}))" >> "$out/rates.jsonl"
}

evaluate() {  # gpu name
  local gpu=$1 name=$2
  for seed in ${EVAL_SEEDS:-0}; do
    rates "$gpu" "--checkpoint $runs/$name" "$held" --episodes 17 --seed "$seed" --collision-mode ignore
  done
  for mode in stop remove; do
    rates "$gpu" "--checkpoint $runs/$name" "$held" --episodes 17 --seed 0 --collision-mode $mode
  done
  # greedy actions: the policy without its sampling noise
  rates "$gpu" "--checkpoint $runs/$name --deterministic" "$held" --episodes 17 --seed 0 --collision-mode ignore
  # the training scenes, unaugmented: the rates to choose between runs by, leaving the held-out ones for the report
  rates "$gpu" "--checkpoint $runs/$name" "$stores/womd_dev_train" --episodes 44 --seed 0 --collision-mode ignore
  rates "$gpu" "--checkpoint $runs/$name" procedural:all --num-scenes 256 --episodes 256 --seed 90000
}

k=0
while read -r name store sets urban; do
  gpu=${gpus[$((k % ${#gpus[@]}))]}
  ( [ "$phase" = eval ] || train $gpu "$name" "$store" "$sets" "$urban"
    [ "$phase" = train ] || evaluate $gpu "$name" ) &
  k=$((k + 1))
done <<< "$plan"
if [ "$phase" != train ]; then
  ( for mode in ignore stop remove; do
      rates "${gpus[0]}" "--policy expert" "$held" --episodes 17 --seed 0 --collision-mode $mode
      rates "${gpus[0]}" "--checkpoint shipped" "$held" --episodes 17 --seed 0 --collision-mode $mode
    done ) &
fi
wait
for name in $(cut -d' ' -f1 <<< "$plan"); do
  cp "$runs/$name/curves.png" "$out/curves_$name.png" 2>/dev/null
done
(cd "$runs" && tar czf "$out/runs.tgz" */metrics.csv */config.json 2>/dev/null)
if [ "$phase" != train ]; then  # a train phase keeps the whole checkpoints in $runs, for a RESUME=1 call after it
  python3 "$repo/scripts/slim_checkpoints.py" "$runs"  # each run's policy, about 1 MB
  for name in $(cut -d' ' -f1 <<< "$plan"); do
    cp "$runs/$name/checkpoint.pt" "$out/$name.pt" 2>/dev/null
  done
fi
ls -la "$out"
