#!/bin/bash
# One training round of the detector and the pose stage side by side on a machine with one GPU and 16 cores,
# inside a 10-minute call: simulated chunks made in parallel on every core, then both networks fine-tuned from the
# shipped bundle at once (bfloat16 autocast), their checkpoints returned as float16 parts (checkpoint_parts.py).
#
# usage, in the repository root: export/recipes/accelerator_round.sh OUT_DIR REAL_DIR
# env: FRAMES (per chunk, 25), SIM_S (seconds of simulation, 190), TRAIN_MIN (minutes of training, 4.6),
#      DEVICE (cuda), PROCS (16), SEED (21), DET_EPOCHS (7), POSE_EPOCHS (12), BUNDLE (models/epal-default),
#      STAGES ("det pose": which networks to train), DET_INIT / POSE_INIT (a checkpoint or bundle to start from:
#      BUNDLE; DET_INIT=none for a detector started by DET_ARGS, e.g. "--detector-architecture yolox-nano
#      --pretrained data/pretrained/yolox_nano.onnx", with data/pretrained carried), POSE_LR (2e-4), DET_LR
#      (3e-4), CHUNKS_FILE (lines "NAME PRESET SEED [sim args]" instead of the
#      built-in mix), CHUNK_S (seconds a chunk needs: none starts later than that before the simulation's end, 55),
#      DET_REPEAT / POSE_REPEAT (name prefixes of chunks the detector / the pose stage sees twice, e.g. "vo- in-",
#      "faepal-"; none), POSE_CONFIG (edge2-dilated), DET_ARGS (more `pallet6d train detector` flags, e.g.
#      "--detector-activation relu --distill models/epal-default"; none),
#      POSE_ARGS (more `pallet6d train pose` flags, e.g. "--distill models/epal-default --calibrate-share 0.944"
#      with POSE_CONFIG=edge2-pruned, which starts from the bundle's most important layer4 / PSP channels, trains
#      the pose network with it and ends with the floor keeping the shipped networks' share of pallets; none),
#      POSE_WARM_MIN (minutes of a first pose phase, trained with POSE_WARM_ARGS instead of POSE_ARGS for
#      POSE_WARM_EPOCHS epochs at POSE_WARM_LR (POSE_LR), e.g. "--distill models/epal-default --freeze-pose": its
#      last.pt starts the second phase, which gets the rest of TRAIN_MIN; 0: one phase), CACHE_FROM (a folder of
#      caches made beforehand, e.g. the --negatives crops, packed by travel_cache.py and unpacked into the trainers'
#      cache; none), POSE_SLACK_S (seconds the pose phases may run past the detector's hard stop, for their
#      start-ups and the calibration; 0)
# REAL_DIR: imported real photographs (python -m pallet6d.export.real_data import); only its train split is used.
set -u
OUT_DIR=$1 REAL=$2
export FRAMES=${FRAMES:-25} SEED=${SEED:-21}
SIM_S=${SIM_S:-190} TRAIN_MIN=${TRAIN_MIN:-4.6} DEVICE=${DEVICE:-cuda} PROCS=${PROCS:-16}
DET_EPOCHS=${DET_EPOCHS:-7} POSE_EPOCHS=${POSE_EPOCHS:-12} BUNDLE=${BUNDLE:-models/epal-default}
STAGES=${STAGES:-det pose} DET_INIT=${DET_INIT:-$BUNDLE} POSE_INIT=${POSE_INIT:-$BUNDLE}
POSE_LR=${POSE_LR:-2e-4} DET_LR=${DET_LR:-3e-4} POSE_CONFIG=${POSE_CONFIG:-edge2-dilated} POSE_ARGS=${POSE_ARGS:-}
DET_ARGS=${DET_ARGS:-}
POSE_WARM_MIN=${POSE_WARM_MIN:-0} POSE_WARM_ARGS=${POSE_WARM_ARGS:-} POSE_WARM_EPOCHS=${POSE_WARM_EPOCHS:-4}
POSE_WARM_LR=${POSE_WARM_LR:-$POSE_LR}
export RECIPES=$PWD/export/recipes W=${W:-/tmp/p6d}
rm -rf "$W"; mkdir -p "$W/pp/pallet6d" "$W/sim" "$W/cache" "$W/log" "$OUT_DIR"
[ -n "${CACHE_FROM:-}" ] && python3 export/recipes/travel_cache.py unpack "$CACHE_FROM" "$W/cache" >/dev/null
for d in runtime export calib sim; do ln -sfn "$PWD/$d" "$W/pp/pallet6d/$d"; done   # the package, not installed
export PYTHONPATH=$W/pp PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
say() { echo "[$(date +%T)] $*" | tee -a "$OUT_DIR/run.log"; }
say "start: $(nproc --all) cores, $(python3 -c 'import torch; print(torch.__version__, torch.cuda.is_available())')"

# Simulated chunks, interleaved so that a cut-short phase still has every kind: the forklift's view (all types,
# D435-like; ToF-like; EPAL only), the mixed preset, the paper's three presets (kept level by training on them), and
# pallet-free scenes with their loads set down ("neg-": the detector's negatives; the pose stage has nothing to learn
# there).
chunks() {
  [ -n "${CHUNKS_FILE:-}" ] && { cat "$CHUNKS_FILE"; return; }
  for i in $(seq 0 23); do
    echo "fa-$((6000 + i)) forklift-approach $((6000 + i))"
    [ $((i % 2)) = 0 ] && echo "mixed-$((6300 + i / 2)) mixed $((6300 + i / 2))"
    [ $((i % 3)) = 0 ] && echo "vo-$((6500 + i / 3)) virtual-occluded $((6500 + i / 3))"
    [ $((i % 3)) = 1 ] && echo "in-$((6400 + i / 3)) indoor-noisy $((6400 + i / 3))"
    [ $((i % 4)) = 2 ] && echo "fatof-$((6100 + i / 4)) forklift-approach $((6100 + i / 4)) --sensor tof"
    [ $((i % 4)) = 3 ] && echo "faepal-$((6200 + i / 4)) forklift-approach $((6200 + i / 4)) --pallet-types epal"
    [ $((i % 6)) = 5 ] && echo "vc-$((6600 + i / 6)) virtual-clean $((6600 + i / 6))"
    [ $((i % 6)) = 1 ] && echo "neg-$((6700 + i / 6)) forklift-approach $((6700 + i / 6)) --pallet-free set-down"
    [ $((i % 6)) = 4 ] && echo "neg-$((6750 + i / 6)) virtual-occluded $((6750 + i / 6)) --pallet-free set-down"
  done
}
export CHUNK_S=${CHUNK_S:-55} DEADLINE=$(($(date +%s) + SIM_S))
chunks | xargs -P "$PROCS" -L 1 bash "$RECIPES/sim_chunk.sh"
DIRS=$(for d in "$W"/sim/*/; do [ -f "$d/DONE" ] && echo "${d%/}"; done)
say "simulated: $(echo $DIRS | wc -w) of $(chunks | wc -l) chunks of $FRAMES frames"
DET_DIRS=$DIRS
POSE_DIRS=$(for d in $DIRS; do case $(basename "$d") in neg-*) ;; *) echo "$d";; esac; done)
# a name prefix in DET_REPEAT / POSE_REPEAT: those chunks are named twice, trained twice (held out from once)
named() { for d in $DIRS; do case $(basename "$d") in "$1"*) echo "$d";; esac; done; }
for p in ${DET_REPEAT:-}; do DET_DIRS="$DET_DIRS $(named "$p")"; done
for p in ${POSE_REPEAT:-}; do POSE_DIRS="$POSE_DIRS $(named "$p")"; done
[ -n "$DIRS" ] || { tail -n 20 "$W"/log/*.log | tee -a "$OUT_DIR/run.log"; exit 1; }

HARD=$(python3 -c "print(int($TRAIN_MIN * 60 + 75))")   # a pose phase's start-up and calibration: POSE_SLACK_S more
POSE_HARD=$((HARD + ${POSE_SLACK_S:-0}))
export OMP_NUM_THREADS=3
DET_INIT_ARGS=(--init "$DET_INIT"); [ "$DET_INIT" = none ] && DET_INIT_ARGS=()
[[ " $STAGES " == *" det "* ]] && timeout "$HARD" python3 -m pallet6d.runtime.cli train detector --config edge2-dilated "${DET_INIT_ARGS[@]}" \
  --data $DET_DIRS --real "$REAL" --real-repeat-large 3 --select near_f1 \
  --detector-input-sizes 192x640,256x480,288x416,320x384 --epochs "$DET_EPOCHS" --batch 16 --lr "$DET_LR" \
  --seed "$SEED" --device "$DEVICE" --amp --loader-threads 10 --max-minutes "$TRAIN_MIN" --no-progress \
  --cache-dir "$W/cache" --out "$W/det" $DET_ARGS >"$OUT_DIR/det.log" 2>&1 &
# train_pose INIT EPOCHS LR MINUTES OUT ARGS...: one pose phase
train_pose() {
  local init=$1 epochs=$2 lr=$3 minutes=$4 out=$5; shift 5
  python3 -m pallet6d.runtime.cli train pose --config "$POSE_CONFIG" --init "$init" --data $POSE_DIRS \
    --epochs "$epochs" --batch 32 --lr "$lr" --variants 2 --seed "$SEED" --device "$DEVICE" --amp "$@" \
    --max-minutes "$minutes" --no-progress --cache-dir "$W/cache" --out "$out" >>"$OUT_DIR/run.log" 2>&1
}
pose_phases() {
  if [ "$POSE_WARM_MIN" = 0 ]; then
    train_pose "$POSE_INIT" "$POSE_EPOCHS" "$POSE_LR" "$TRAIN_MIN" "$W/pose" $POSE_ARGS; return
  fi
  train_pose "$POSE_INIT" "$POSE_WARM_EPOCHS" "$POSE_WARM_LR" "$POSE_WARM_MIN" "$W/pose-warm" $POSE_WARM_ARGS
  say "pose warm phase: $(ls "$W/pose-warm" | tr '\n' ' ')"
  [ -f "$W/pose-warm/last.pt" ] || return 1
  local rest; rest=$(python3 -c "print($TRAIN_MIN - $POSE_WARM_MIN)")
  train_pose "$W/pose-warm/last.pt" "$POSE_EPOCHS" "$POSE_LR" "$rest" "$W/pose" $POSE_ARGS
}
export POSE_CONFIG POSE_DIRS POSE_LR DEVICE OUT_DIR POSE_INIT POSE_EPOCHS TRAIN_MIN POSE_ARGS POSE_WARM_MIN \
  POSE_WARM_ARGS POSE_WARM_EPOCHS POSE_WARM_LR
export -f train_pose pose_phases say
[[ " $STAGES " == *" pose "* ]] && timeout "$POSE_HARD" bash -c pose_phases &
wait
say "trained"
# a call returns at most 8 files: the warm phase's checkpoints only where the second phase left none
if [ ! -d "$W/pose" ] && [ -d "$W/pose-warm" ]; then
  say "pose: the warm phase's checkpoints"; mv "$W/pose-warm" "$W/pose"
fi
for run in det pose; do
  for c in best last; do
    [ -f "$W/$run/$c.pt" ] && python3 "$RECIPES/checkpoint_parts.py" split "$W/$run/$c.pt" "$OUT_DIR/$run-$c"
  done
done
rm -f "$OUT_DIR"/det-*.fusion.pt "$OUT_DIR"/det-*.pose.pt   # a detector checkpoint holds the detector alone
say "done: $(ls "$OUT_DIR" | tr '\n' ' ')"
