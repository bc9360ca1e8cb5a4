#!/usr/bin/env bash
# `make demo`: the whole chain in sim on this machine, with laptop-CPU defaults.
# Override with env: TASK=can EPISODES=10 RIG=three15 SPACE=base STEPS=500 make demo
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
TASK=${TASK:-lift}
EPISODES=${EPISODES:-5}
RIG=${RIG:-five15}
SPACE=${SPACE:-camera}
STEPS=${STEPS:-300}
OUT=${OUT:-data/demo}
export MUJOCO_GL=${MUJOCO_GL:-egl}

views=$($BIN/python -c "from services.core.rig import load_rig; print(','.join(load_rig('$RIG').names))")

echo "== 1/3 collect: $EPISODES scripted '$TASK' episodes, rig $RIG ($views), 84x84 at 20 Hz"
rm -rf "$OUT/raw"
$BIN/viewscale collect --task "$TASK" --episodes "$EPISODES" --rig "$RIG" --out "$OUT/raw"

echo
echo "== 2/3 pseudo-demonstrations: $EPISODES episodes x views $views, $SPACE action space"
$BIN/viewscale dataset build --raw "$OUT/raw" --views "$views" --space "$SPACE" --out "$OUT/ds" --force

echo
echo "== 3/3 train: tiny diffusion policy, $STEPS steps on the pseudo-demos (CPU is fine)"
rm -rf "$OUT/run"
$BIN/viewscale train --data "$OUT/ds" --preset tiny --steps "$STEPS" --out "$OUT/run"

echo
echo "done:"
echo "  episodes       $OUT/raw (open them in Foxglove)"
echo "  pseudo-demos   $OUT/ds (contact sheet: $OUT/ds/contact_sheet.png)"
echo "  policy         $OUT/run (loss curve: $OUT/run/loss.png)"
