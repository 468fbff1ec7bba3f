#!/usr/bin/env bash
# The GPU figures of BENCHMARKS.md. Run from the repo root on a machine where the project is
# importable (pip install -e . or PYTHONPATH); every stage leaves its files in /tmp/res/<stage>
# and packs them into $OUT/<stage>.tgz (the device tool brings back at most 8 files).
# On 2 x H200 two stages run side by side, one per GPU (GPU=0 / GPU=1):
#   a         CUDA tests + engine / env / store benchmarks
#   perf      training throughput per config (scripts/bench_train.py), then the world-model bench
#   quality   CCE-MAPPO and plain PPO (QUALITY_VARIANTS) trained for QUALITY_SECONDS each, held-out rates
#             (QUALITY_TRANSFER=1: also urban and real-scene rates, as the urban stage)
#   sweep     learning variants of gpu.yaml side by side on one GPU (goal rate per update; their
#             wall-clock shares the GPU, so compare updates, not seconds)
#   ttq       time to a 95 % goal rate on 1,000 procedural scenes (configs/train/gpu.yaml)
#   graphs    the CUDA-graph steps (cuda_graphs) and the compiled loss (compile_update): CUDA tests, then the
#             profile eager, with graphs, compiled, and both
#   ttqside   variants of gpu.yaml side by side, one per GPU or GPU group, each to the held-out quality stop
#             (goal >= 0.95, collision <= 0.05, off-road <= 0.02 on the window and on 256 held-out scenes);
#             VARIANTS="name|gpus|nproc|--set k=v ...;name|..." e.g. "lr2|0|1|--set lr=0.002;two|1,2|2|"
#   storebuild  a 10,000-scene procedural store in /tmp/store (CPU only: runs beside GPU stages)
#   store10k  training on that store with resampling (STORE_NPROC GPUs), held-out rates per collision mode
#   grid      the beta x alpha experiment grid and its report (scripts/run_experiments.py); on two GPUs
#             GRID_GPUS=0,1 GRID_BATCH=8 trains four cells on each at a time, and the report runs in
#             GRID_REPORT_PER_GPU parts per GPU
#   generate  `tg-gpudrive generate` under two constraint recipes (GEN_RECIPES: builtin = its default, shipped = the
#             shipped policy's own; or grid yamls) at beta 2 / 6 x alpha 0.125 / 0.875 (GEN_BETAS, GEN_ALPHAS), all
#             at once on one GPU (GEN_SEEDS: each seed's cells on the next GPU of GEN_GPUS), GEN_SECONDS of
#             fine-tuning each on GEN_SCENES scenes, once more per GEN_VARIANTS (train overrides); the policies
#             come back slim, for a report on their own scenes (--scene-seed -1)
#   ccegap    the CCE-gap in both games of runs carried in (GAP_RUNS, e.g. generate's fine-tunes) on their own
#             scenes, beside plain MAPPO trained from scratch in their game (GAP_MAPPO_SEEDS)
#   wm        world models on the GPU (discrete + closed-loop fine-tuning, continuous) and as traffic
#   scale     both GPUs: 1 vs 2 processes, the same worlds per GPU, with each rank's phases (timing.csv)
#   urban     real-scene transfer: world model and CCE-MAPPO on a mix with parked cars, stop-line
#             queues and kerb stops; held-out plain / urban / real rates beside the shipped policy
#   (time to quality on 2 GPUs: store10k with STORE_NPROC=2 STORE_GPUS=0,1 STORE_TARGET=0.95: training stops
#   once goal >= 0.95 with collision <= 0.05 and off-road <= 0.02 over the last 10 updates; summarize prints
#   the 10-update-window time to quality of BENCHMARKS.md; STORE_HELDOUT=procedural:all also asks 256 held-out
#   scenes to meet it, config target_heldout)
# Sizes and time limits come from the environment (defaults: the figures in BENCHMARKS.md);
# TRAIN_SET adds `--set` overrides to every training run (a CPU dry run shrinks everything).
set -u
R=$(pwd)
OUT=${OUT:-/tmp/out}
stage=${1:?stage}
RES=/tmp/res/$stage
mkdir -p "$OUT" "$RES"
export CUDA_VISIBLE_DEVICES=${GPU:-${CUDA_VISIBLE_DEVICES:-0}}
export PYTHONUNBUFFERED=1
# Python's bytecode cached as an installed torch has it: a machine that sets PYTHONDONTWRITEBYTECODE over a
# venv without .pyc files compiles torch's compiler modules from source in every process, seconds of a first
# update that compiles (BENCHMARKS.md)
unset PYTHONDONTWRITEBYTECODE
export PYTHONPYCACHEPREFIX=${PYTHONPYCACHEPREFIX:-/tmp/pyc}
CFG="$R"/configs/train/gpu.yaml
SETS=()
for s in ${TRAIN_SET:-}; do SETS+=(--set "$s"); done
cd /tmp
cli() { python3 -m tg_gpudrive.cli "$@"; }
# a training run's progress bar, one line per update, without the carriage returns
bar() { tr '\r' '\n' | grep -v '^\s*$' | grep -E 'reached|update|Error|error' | tail -${1:-3}; }
# checkpoints over 4 MB (with the engine state) and the previous ones do not come back: the tool returns 16 MB a file
# nor does the report's cache (tens of MB per policy: every rollout): it stays on the machine for a resumed report
# an archive over 15 MB comes back in parts: cat $stage.tgz.part_* | tar xz
pack() { find "$RES" \( -name 'checkpoint.pt*' -size +4M -o -name 'checkpoint.prev.pt' \) -delete
         tar czf "$OUT/$stage.tgz" --exclude=cache -C /tmp/res "$stage"
         if [ "$(stat -c %s "$OUT/$stage.tgz")" -gt 15728640 ]; then
           (cd "$OUT" && split -b 15M "$stage.tgz" "$stage.tgz.part_" && rm "$stage.tgz"); fi; }

# slim checkpoints (weights + config, a few MB) so they come back and load in evaluate / report
slim() { python3 "$R"/scripts/slim_checkpoints.py "$RES"; }

# per policy run: goal / collision / off-road over the episodes that ended in the last 10 updates, and
# the time to quality (goal >= 0.95 with collision <= 0.05 and off-road <= 0.02, 10-update window)
summarize() { python3 "$R"/scripts/summarize_runs.py "$RES"; }

# held-out rates per collision mode of trained runs beside the shipped policy: plain procedural scenes and
# urban ones (parked cars, stop-line queues, kerb stops; URBAN_EVAL), then the two real WOMD scenes;
# HELDOUT_CONTROL=vehicles drives every vehicle whatever control a run was trained with (evaluate does)
URB=${URBAN_EVAL:-"procedural:all[parking=0.8,stop_lines=0.5,kerb_stops=0.5,lane_offset=0.4,park_reach=1.5]"}
transfer_eval() {
  for spec in procedural:all "$URB"; do
    timeout ${EVAL_SECONDS:-200} python3 "$R"/scripts/heldout_eval.py --runs "$@" shipped --scenes "$spec" \
      --modes ignore stop remove --num-scenes ${EVAL_N:-1024} --device ${EVAL_DEVICE:-cuda} --out "$RES/heldout.jsonl" \
      ${HELDOUT_CONTROL:+--control $HELDOUT_CONTROL} 2>>"$RES/heldout.err" | tail -7
  done
  for mode in ignore stop remove; do
    for run in "$@" shipped; do
      timeout 120 python3 -m tg_gpudrive.cli evaluate --checkpoint "$run" --scenes "$R"/tests/data --num-scenes 2 \
        --worlds ${REAL_WORLDS:-64} --episodes ${REAL_WORLDS:-64} --collision-mode $mode --json 2>>"$RES/real.err" | tee -a "$RES/real.jsonl" | head -c 300; echo
    done
  done
}

case "$stage" in
a)
  python3 -m pytest -q -p no:cacheprovider "$R"/tests/test_kernels.py "$R"/tests/test_engine.py \
    "$R"/tests/test_envs.py "$R"/tests/test_losses.py "$R"/tests/test_train.py -k cuda 2>&1 | tail -3
  cli benchmark --scenes procedural:all --device cuda --json --worlds 1024 4096 16384 --steps 50 \
    2>/dev/null | tee "$RES/bench_procedural.jsonl"
  ;;
perf)
  timeout ${PERF_SECONDS:-300} python3 "$R"/scripts/bench_train.py --config "$CFG" --updates ${PERF_UPDATES:-8} \
    --out "$RES/bench_train.jsonl" "${SETS[@]}" \
    ${PERF_VARIANTS:---variant w1024_e2mb8: --variant w4096_e2mb32:num_worlds=4096,minibatches=32 --variant w4096_e2mb8:num_worlds=4096 --variant w4096_e1mb8:num_worlds=4096,epochs=1 --variant w4096_e1mb4:num_worlds=4096,epochs=1,minibatches=4} 2>&1 | grep -v Warning
  timeout ${WM_SECONDS:-150} python3 "$R"/scripts/bench_world_model.py ${WM_ARGS:---device cuda --worlds 1024} \
    2>&1 | tail -20 | tee "$RES/bench_world_model.txt"
  ;;
sweep)
  for v in ${SWEEP_VARIANTS:-floor05:prior_floor=0.05 floor0:prior_floor=0.0 floor05_eta01_lr1e3:eta1=0.1,lr=0.001 floor01_eta2:prior_floor=0.01,eta1=2.0}; do
    name=${v%%:*}; kv=${v#*:}
    timeout ${SWEEP_SECONDS:-400} python3 -m tg_gpudrive.cli train --config "$CFG" --out "$RES/$name" \
      --set checkpoint_every=100000 "${SETS[@]}" $(for x in ${kv//,/ }; do echo --set $x; done) \
      > "$RES/$name.log" 2>&1 &
  done
  wait
  summarize
  ;;
quality)
  # variants side by side on one GPU, each stopped after QUALITY_SECONDS of its own training
  # wall-clock (they share the GPU: a run alone gets more updates in the same time), then
  # held-out rates (procedural seed 90000, never used in training) per collision mode
  cli simulate --scenes procedural:merge --worlds 4 --device cuda --json > /dev/null 2>&1  # compile once
  # QSET_<name>: whitespace-separated overrides of one variant whose values hold commas (a scene mix)
  for v in ${QUALITY_VARIANTS:-cce: ppo:eta1=0,constraint=false}; do
    name=${v%%:*}; kv=${v#*:}; own=QSET_$name
    python3 -m tg_gpudrive.cli train --config "$CFG" --out "$RES/$name" --set time_limit_s=${QUALITY_SECONDS:-300} \
      --set checkpoint_every=50 "${SETS[@]}" $(for x in ${kv//,/ } ${!own:-}; do echo --set $x; done) > "$RES/$name.log" 2>&1 &
  done
  wait
  summarize
  slim
  [ "${QUALITY_EVAL:-1}" = 0 ] || timeout ${EVAL_SECONDS:-200} python3 "$R"/scripts/heldout_eval.py --runs $(ls -d "$RES"/*/) ${QUALITY_BASELINES:-constant random} \
    --modes ${QUALITY_MODES:-ignore} --num-scenes ${EVAL_N:-1024} --out "$RES/heldout.jsonl" 2>"$RES/heldout.err" | tail -30
  # QUALITY_TRANSFER=1: also urban and real-scene rates per collision mode, beside the shipped policy
  [ "${QUALITY_TRANSFER:-0}" = 1 ] && HELDOUT_CONTROL=vehicles transfer_eval $(ls -d "$RES"/*/)
  ;;
graphs)
  # the CUDA-graph steps (cuda_graphs): their CUDA tests, then the iteration's profile without and with them at
  # 1,024 worlds (gpu.yaml) and at 4,096 (one epoch of 8 minibatches), each in its own file
  # from /tmp (cd above), so that the installed package, kernels included, is the one imported, not the checkout
  python3 -m pytest -q -p no:cacheprovider "$R"/tests/test_step_graphs.py "$R"/tests/test_learn_collector_update.py \
    > "$RES/pytest.txt" 2>&1; tail -3 "$RES/pytest.txt"
  for size in "1024|" "4096|--set epochs=1 --set minibatches=8"; do
    IFS='|' read -r worlds extra <<< "$size"
    for v in eager:false:false graphs:true:false compiled:false:true graphs_compiled:true:true; do
      IFS=: read -r g graphs compiled <<< "$v"
      knobs="--set cuda_graphs=$graphs --set compile_update=$compiled"
      timeout ${PROFILE_SECONDS:-240} python3 "$R"/scripts/profile_train.py --config "$CFG" --set num_worlds=$worlds \
        $extra $knobs --iters 3 --rows 25 "${SETS[@]}" > "$RES/profile_${worlds}_$g.txt" 2>&1
      echo "== $worlds worlds, $g"; grep -iE "rollout|update|agent-steps" "$RES/profile_${worlds}_$g.txt" | head -4
    done
  done
  ;;
ttq)
  timeout ${TTQ_SECONDS:-450} python3 -m tg_gpudrive.cli train --config "$CFG" --out "$RES/run" \
    --set target_goal_rate=0.95 --set checkpoint_every=100000 "${SETS[@]}" 2>&1 | bar 3
  python3 "$R"/scripts/plot_curves.py "$RES/run/metrics.csv" "$RES/curves.png"
  ;;
ttqside)
  IFS=';' read -ra VS <<< "${VARIANTS:?VARIANTS=name|gpus|nproc|sets;...}"
  for v in "${VS[@]}"; do
    IFS='|' read -r name gpus nproc sets <<< "$v"
    (CUDA_VISIBLE_DEVICES=$gpus timeout $((${TTQ_LIMIT:-300} + 100)) python3 -m tg_gpudrive.cli train --config "$CFG" \
      --nproc "${nproc:-1}" --out "$RES/$name" --set target_goal_rate=0.95 --set target_max_collision=0.05 \
      --set target_max_offroad=0.02 --set target_heldout=procedural:all --set time_limit_s=${TTQ_LIMIT:-300} \
      $sets "${SETS[@]}" 2>&1 | bar 2 | sed "s/^/$name: /") &
  done
  wait
  for v in "${VS[@]}"; do
    t="$RES/${v%%|*}/target.json"
    if [ -f "$t" ]; then echo "${v%%|*}: $(tr -d '\n ' < "$t")"; else echo "${v%%|*}: quality not reached"; fi
  done
  ;;
storebuild)
  [ -f /tmp/store/manifest.json ] || timeout 300 python3 "$R"/scripts/bench_store.py --n ${STORE_N:-10000} \
    --worlds ${STORE_WORLDS:-4096} --workers ${STORE_WORKERS:-8} --out /tmp/store 2>&1 | tail -2 | tee "$RES/bench_store.txt"
  ;;
store10k)
  N=${STORE_N:-10000}
  [ -f /tmp/store/manifest.json ] || (cd "$R" && bash scripts/gpu_measure.sh storebuild)
  CUDA_VISIBLE_DEVICES=${STORE_GPUS:-$CUDA_VISIBLE_DEVICES} timeout ${STORE_TRAIN_SECONDS:-240} python3 -m tg_gpudrive.cli \
    train --config "$CFG" --out "$RES/run" --nproc ${STORE_NPROC:-1} --set scenes=/tmp/store --set num_scenes="$N" \
    --set resample_every=5 --set checkpoint_every=5 --set target_goal_rate=${STORE_TARGET:-0} \
    --set target_max_collision=0.05 --set target_max_offroad=0.02 --set time_limit_s=${STORE_LIMIT:-0} \
    ${STORE_HELDOUT:+--set target_heldout=$STORE_HELDOUT} "${SETS[@]}" 2>&1 | bar 3
  summarize
  for mode in ignore stop remove; do
    timeout ${EVAL_SECONDS:-150} python3 -m tg_gpudrive.cli evaluate --checkpoint "$RES/run" --scenes procedural:all \
      --seed 50000 --num-scenes ${EVAL_N:-1024} --episodes ${EVAL_N:-1024} --worlds ${EVAL_N:-1024} \
      --collision-mode $mode --json 2>"$RES/heldout_$mode.err" | tee "$RES/heldout_$mode.json"
  done
  ;;
grid)
  # GRID_FROM: run directories trained earlier (e.g. a carried folder holding the slim checkpoints an earlier
  # session brought back) copied in first; finished cells are not trained again. GRID_REPORT=0: train only.
  # GRID_SEEDS=S[,S]: those training seeds in place of the config's (one seed's cells per call)
  [ -n "${GRID_FROM:-}" ] && cp -r "$R/$GRID_FROM"/. "$RES"/
  timeout ${GRID_TRAIN_SECONDS:-300} python3 "$R"/scripts/run_experiments.py --config ${GRID_CONFIG:-"$R"/configs/experiments/grid.yaml} --out "$RES" --no-report \
    ${GRID_GPUS:+--gpus $GRID_GPUS} ${GRID_BATCH:+--batch $GRID_BATCH} ${GRID_UPDATES:+--set updates=$GRID_UPDATES} \
    ${GRID_SEEDS:+--seeds $GRID_SEEDS} "${SETS[@]}" 2>&1 | grep -E '^\||exit|failed' | tail -25
  slim
  # the report: with GRID_GPUS one part per GPU fills its cache (policies evaluated, CCE-gaps), then one
  # pass writes it; a part stopped by its timeout keeps what it finished for the next call
  GC=${GRID_CONFIG:-"$R"/configs/experiments/grid.yaml}
  if [ "${GRID_REPORT:-1}" = 0 ]; then pack; exit 0; fi
  # GRID_REPORT_PER_GPU processes share each GPU (default 2: a best response's 80-step play is bound by
  # kernel launches, so two processes keep a GPU busier than one)
  if [ -n "${GRID_GPUS:-}" ]; then
    gpus=(${GRID_GPUS//,/ }); per=${GRID_REPORT_PER_GPU:-2}; n=$((${#gpus[@]} * per))
    for ((k = 0; k < n; k++)); do
      CUDA_VISIBLE_DEVICES=${gpus[$((k % ${#gpus[@]}))]} timeout ${GRID_REPORT_SECONDS:-200} python3 "$R"/scripts/run_experiments.py \
        --config "$GC" --out "$RES" --report-part $k/$n "${SETS[@]}" > "$RES/report_part$k.log" 2>&1 &
    done
    wait
  fi
  timeout ${GRID_REPORT_SECONDS:-200} python3 "$R"/scripts/run_experiments.py --config "$GC" --out "$RES" --report-only \
    "${SETS[@]}" 2>&1 | tail -3
  ;;
generate)
  # GEN_VARIANTS="name|k=v k=v;name2|k=v": each recipe once more per variant with those train overrides, into
  # <recipe>_<name> (e.g. "heads|heads=5;hist|actor_history=10 actor_history_partners=4;n1|cost_nstep=1")
  G=$RES; gpus=(${GEN_GPUS:-0}); k=0
  IFS=';' read -ra variants <<< "${GEN_VARIANTS:-|}"
  for seed in ${GEN_SEEDS:-0}; do gpu=${gpus[$((k % ${#gpus[@]}))]}; k=$((k + 1))
  for rec in ${GEN_RECIPES:-builtin shipped}; do for v in "${variants[@]}"; do
  vname=${v%%|*}; vsets=(); for s in ${v#*|}; do vsets+=(--set "$s"); done
  for b in ${GEN_BETAS:-2 6}; do for a in ${GEN_ALPHAS:-0.125 0.875}; do
    d=$G/$(basename "$rec" .yaml)${vname:+_$vname}/b${b}_a${a}_s$seed; mkdir -p "$d"
    recipe=(); [ "$rec" != builtin ] && recipe=(--recipe "$rec")
    CUDA_VISIBLE_DEVICES=$gpu timeout ${GEN_TIMEOUT:-480} python3 -m tg_gpudrive.cli generate --seed $seed \
      --scenes ${GEN_SPEC:-procedural:all} --num-scenes ${GEN_SCENES:-64} --beta $b --alpha $a --num 10 \
      --seconds ${GEN_SECONDS:-240} --rollout-seeds 4 --no-gif --json --device ${GEN_DEVICE:-cuda} --out "$d" \
      "${recipe[@]}" "${SETS[@]}" "${vsets[@]}" > "$d/generate.json" 2> "$d/generate.err" &
  done; done; done; done; done
  wait
  python3 "$R"/scripts/slim_checkpoints.py "$G"/*/*
  find "$G" -name '*.tfevents*' -delete; find "$G" -path '*/scenarios/*.json' -delete  # the table keeps their risk
  pack
  ;;
ccegap)
  # GAP_RUNS (run directories, e.g. a carried folder of generate's slim fine-tunes): each one report process with
  # the CCE-gap in both games on GAP_SCENES (the runs' own scenes, their config's path rewritten to this
  # machine's), all side by side on GAP_GPUS. GAP_MAPPO_SEEDS: first trains plain MAPPO from scratch in the
  # game of GAP_RUNS' first run (its scenes, control and reward; no magnet, no proximal term, no constraint; the
  # shipped recipe's from-scratch steps) for GAP_MAPPO_SECONDS each, side by side, into $RES/mappo_s<seed>.
  # GAP_REPORT: the directories under $RES to report on (copied runs, mappo_s<seed> of this call or an earlier
  # one on the same machine); GAP_HELDOUT (a store of held-out scenes): on those instead, into report_<dir>_heldout
  gpus=(${GAP_GPUS:-0}); k=0; first=""
  for run in ${GAP_RUNS:-}; do d=$RES/$(basename "$run"); mkdir -p "$d"; first=${first:-$d}
    cp "$R/$run"/* "$d"/
    python3 -c "import json,sys; p=sys.argv[1]; c=json.load(open(p)); c['scenes']=sys.argv[2]; \
                json.dump(c,open(p,'w'))" "$d/config.json" "$R/${GAP_SCENES:?GAP_SCENES}"
  done
  for seed in ${GAP_MAPPO_SEEDS:-}; do gpu=${gpus[$((k % ${#gpus[@]}))]}; k=$((k + 1))
    CUDA_VISIBLE_DEVICES=$gpu timeout $(( ${GAP_MAPPO_SECONDS:-480} + 60 )) python3 -m tg_gpudrive.cli train \
      --config "$first/config.json" --out "$RES/mappo_s$seed" --overwrite --set seed=$seed \
      --set device=${GAP_DEVICE:-cuda} \
      --set eta1=0 --set eta2=.inf --set constraint=false --set init_policy= --set lr=0.004 --set minibatches=16 \
      --set entropy_coef=0.01 --set num_worlds=1024 --set updates=714 --set checkpoint_every=714 \
      --set time_limit_s=${GAP_MAPPO_SECONDS:-480} "${SETS[@]}" --json \
      > "$RES/mappo_s$seed.json" 2> "$RES/mappo_s$seed.err" &
  done
  held=(); [ -n "${GAP_HELDOUT:-}" ] && held=(--eval-scenes "$R/$GAP_HELDOUT")
  for d in ${GAP_REPORT:-}; do gpu=${gpus[$((k % ${#gpus[@]}))]}; k=$((k + 1)); o=report_$d${GAP_HELDOUT:+_heldout}
    CUDA_VISIBLE_DEVICES=$gpu timeout ${GAP_TIMEOUT:-540} python3 -m tg_gpudrive.cli report --runs "$RES/$d" \
      --out "$RES/$o" --scenes 12 --scene-seed -1 --seeds 0 --br-scenes 12 --br-seeds ${GAP_BR_SEEDS:-0 1} \
      --br-iters ${GAP_BR_ITERS:-100} --no-baselines --top 0 --device ${GAP_DEVICE:-cuda} "${held[@]}" \
      > "$RES/$o.log" 2>&1 &
  done
  wait
  slim
  pack
  ;;
wm)
  # the shipped world model's two steps (configs/worldmodel/gpu.yaml) and a continuous one, side by
  # side, then every model as traffic on 512 held-out scenes (scripts/wm_traffic.py); the models
  # stay in /tmp/res/wm/<name>/model.pt for a later stage on the same machine (e.g. quality with
  # QUALITY_VARIANTS="cont:env.action_space=continuous,prior_model=/tmp/res/wm/cont/model.pt")
  WC="$R"/configs/worldmodel/gpu.yaml
  WMS=(); for x in ${WM_SET:-}; do WMS+=(--set "$x"); done  # overrides of every world-model run
  # a run stopped by its time limit (rc 124) still leaves its last model.pt, which the next step starts from
  wmrun() { local name=$1; shift; timeout ${WM_SECONDS:-330} python3 -m tg_gpudrive.worldmodel.cli --config "$WC" \
    --out "$RES/$name" --json "${WMS[@]}" "$@" > "$RES/$name.json" 2> "$RES/$name.err"; echo "$name rc $?"
    [ -f "$RES/$name/model.pt" ]; }
  # WM_HEADS picks the heads trained (default both: "disc cont")
  heads=" ${WM_HEADS:-disc cont} "
  [[ $heads == *" disc "* ]] && (wmrun disc && wmrun dagger --set init_model="$RES/disc/model.pt" --set steps=0 --set num_scenes=1000 \
    --set closed_loop_steps=2000 --set closed_loop_rounds=2) &
  # continuous: closed-loop fine-tuning made the CPU model worse; on the GPU, with roll-outs at the driver's
  # temperature (0.1), two rounds took a 3,000-step model from 0.62 / 0.20 to 0.07 / 0.11 held out
  # (BENCHMARKS.md); WM_CONT_ROUNDS sets the rounds (each ~90 s on an H100: raise WM_SECONDS with them)
  [[ $heads == *" cont "* ]] && (wmrun cont --set env.action_space=continuous && wmrun contdagger --set env.action_space=continuous \
    --set init_model="$RES/cont/model.pt" --set steps=0 --set num_scenes=1000 --set closed_loop_steps=2000 \
    --set closed_loop_rounds=${WM_CONT_ROUNDS:-2} --set closed_loop_temperature=0.1) &
  wait
  M=""; for n in disc dagger; do [ -f "$RES/$n/model.pt" ] && M="$M $RES/$n/model.pt"; done
  for n in cont contdagger; do [ -f "$RES/$n/model.pt" ] && M="$M $RES/$n/model.pt $RES/$n/model.pt:0"; done
  timeout ${WM_EVAL_SECONDS:-150} python3 "$R"/scripts/wm_traffic.py --models shipped $M --num-scenes ${WM_EVAL_N:-512} \
    --seeds 0 1 --device ${WM_DEVICE:-cuda} 2> "$RES/traffic.err" | tee "$RES/traffic.txt"
  find "$RES" -name checkpoint.pt -delete
  ;;
scale)
  for n in 1 2; do
    CUDA_VISIBLE_DEVICES=0,1 timeout 150 python3 -m tg_gpudrive.cli train --config "$CFG" --out "$RES/scale$n" \
      --nproc $n --set updates=${SCALE_UPDATES:-10} --set resample_every=0 --set num_worlds=${SCALE_WORLDS:-4096} --set checkpoint_every=100000 \
      "${SETS[@]}" 2>&1 | bar 1
  done
  # per rank, median over updates 3..: its own rollout, waiting for the slowest rollout, the update
  python3 "$R"/scripts/scale_timing.py "$RES" --glob 'scale*'
  ;;
urban)
  # real-scene transfer: a training mix with street furniture (parked cars, queues at stop
  # lines, kerb stops, drivers off the lane centre), the shipped world model fine-tuned on it as the magnet, CCE-MAPPO trained on it
  # for the shipped policy's time, then held-out rates per collision mode on plain procedural scenes,
  # urban ones (kerb stops apart) and the two real WOMD scenes, beside the shipped policy
  # park_reach 1.5: parked cars as close to the lane centre as in the real scenes (BENCHMARKS.md)
  MIX=${URBAN_MIX:-"mix:procedural:all=0.5,$URB=0.5"}  # half plain, half the urban evaluation spec
  WC="$R"/configs/worldmodel/gpu.yaml
  cli simulate --scenes procedural:merge --worlds 4 --device cuda --json > /dev/null 2>&1  # compile once
  timeout ${URBAN_WM_SECONDS:-200} python3 -m tg_gpudrive.worldmodel.cli --config "$WC" --out "$RES/wm" --json \
    --set init_model=shipped --set scenes="$MIX" --set env.max_agents=64 --set steps=${URBAN_WM_STEPS:-1000} \
    --set closed_loop_steps=${URBAN_WM_CL:-1000} --set closed_loop_rounds=1 ${URBAN_WM_SET:-} > "$RES/wm.json" 2> "$RES/wm.err"
  echo "world model rc $?"; tail -2 "$RES/wm.err"
  PM=shipped; [ -f "$RES/wm/model.pt" ] && PM="$RES/wm/model.pt"
  # 16 partners, not gpu.yaml's 8: among parked cars the 8 nearest leave out 32 % of the moving vehicles
  # within 25 m on the real scenes, 12 % on the urban mix, 16 almost none (BENCHMARKS.md); URBAN_PARTNERS=8
  # changes only the scenes
  timeout $(( ${URBAN_SECONDS:-463} + 120 )) python3 -m tg_gpudrive.cli train --config "$CFG" --out "$RES/cce" \
    --set scenes="$MIX" --set env.max_agents=64 --set env.partner_k=${URBAN_PARTNERS:-16} --set prior_model="$PM" \
    --set time_limit_s=${URBAN_SECONDS:-463} \
    --set checkpoint_every=50 "${SETS[@]}" 2>&1 | bar 3
  summarize
  slim
  transfer_eval "$RES/cce"
  ;;
*) echo "unknown stage $stage"; exit 2 ;;
esac
pack
