#!/bin/bash
# One simulated training chunk, then its sample caches; a DONE marker when both finished before $DEADLINE.
# usage (env W, FRAMES, SEED, DEADLINE, RECIPES): sim_chunk.sh NAME PRESET SIM_SEED [pallet6d sim args...]
name=$1 preset=$2 simseed=$3; shift 3
left=$((DEADLINE - $(date +%s)))
[ "$left" -gt "${CHUNK_S:-55}" ] || exit 0   # do not start a chunk that cannot finish (25 frames: about 50 s a core)
log=$W/log/$name.log
timeout "$left" python3 -m pallet6d.runtime.cli sim --preset "$preset" --frames "$FRAMES" --seed "$simseed" \
    --out "$W/sim/$name" "$@" >"$log" 2>&1 || exit 0
left=$((DEADLINE + 30 - $(date +%s)))
timeout "$left" python3 "$RECIPES/prep_chunk.py" "$W/sim/$name" "$W/cache" "$SEED" >>"$log" 2>&1 \
    && touch "$W/sim/$name/DONE"
