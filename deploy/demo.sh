#!/usr/bin/env bash
# `make demo`: the whole chain in sim on this machine, with laptop-CPU defaults (about 7 minutes
# on an idle 2-core machine after the install): scripted demos -> pseudo-demos -> a short tiny training -> a policy
# server with three worker processes -> closed-loop episodes from F alone and composed over
# F,FL,FR, through the real services -> a summary table.
# Override with env, e.g. TASK=can EPISODES=20 STEPS=6000 EVAL_EPISODES=50 make demo
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
TASK=${TASK:-lift}
EPISODES=${EPISODES:-20}
RIG=${RIG:-five15}
SPACE=${SPACE:-camera}
STEPS=${STEPS:-2500}
EVAL_EPISODES=${EVAL_EPISODES:-10}
COMPOSE=${COMPOSE:-}  # default: F,FL,FR, or the rig's views where it has no FL, FR
WORKERS=${WORKERS:-3}
OUT=${OUT:-data/demo}
export MUJOCO_GL=${MUJOCO_GL:-egl}
t0=$(date +%s)
stamp() { local s=$(($(date +%s) - t0)); printf '[%02d:%02d]' $((s / 60)) $((s % 60)); }

# Every setting is checked before anything starts: a typo is one line now, not an error after
# minutes of collection and training. Prints the rig's views, the views composed (COMPOSE; by
# default F,FL,FR where the rig has them, else all its views) and the view evaluated alone (F,
# else the rig's first).
plan=$($BIN/python - "$RIG" "$COMPOSE" "$SPACE" "$EPISODES" "$STEPS" "$EVAL_EPISODES" "$WORKERS" <<'EOF'
import sys
from services.core.config import ConfigError
from services.core.rig import load_rig
rig, compose, space, *counts = sys.argv[1:]
try:
    views = list(load_rig(rig).names)
except ConfigError as exc:
    sys.exit(f"error: RIG: {exc}")
for name, value, least in zip(("EPISODES", "STEPS", "EVAL_EPISODES", "WORKERS"), counts, (1, 1, 1, 0)):
    if not value.isdigit() or int(value) < least:
        sys.exit(f"error: {name}={value}: give a whole number, at least {least}")
if space not in ("camera", "base", "eef"):
    sys.exit(f"error: SPACE={space}: one of camera, base, eef")
if compose:
    chosen = compose.split(",")
    missing = [v for v in chosen if v not in views]
    if missing:
        sys.exit(f"error: COMPOSE={compose}: rig {rig} has no camera {', '.join(map(repr, missing))}; its cameras: {', '.join(views)}")
else:
    chosen = ["F", "FL", "FR"] if {"F", "FL", "FR"} <= set(views) else views
print(",".join(views), ",".join(chosen), "F" if "F" in views else views[0])
EOF
) || exit 2
read -r views COMPOSE single <<<"$plan"

# Each run replaces its $OUT: only a folder a demo run made (its marker inside), or an empty one, is
# removed, so that OUT=data (the README's recordings) or OUT=~ loses nothing.
MARK=.viewscale-demo
if [ -e "$OUT" ] && [ ! -f "$OUT/$MARK" ]; then
  if [ ! -d "$OUT" ]; then
    echo "error: OUT=$OUT is a file: choose a folder" >&2
    exit 2
  fi
  # (a summary.md the demo wrote: a run made before the marker)
  if [ -n "$(ls -A "$OUT")" ] && [ "$(head -1 "$OUT/summary.md" 2>/dev/null)" != "# viewscale demo" ]; then
    echo "error: OUT=$OUT holds files no demo run made (no $MARK in it), and a run replaces its OUT:" \
      "choose another OUT, or empty this one yourself" >&2
    exit 2
  fi
fi
rm -rf "$OUT"
mkdir -p "$OUT"
echo "made by deploy/demo.sh (make demo); the next run replaces this folder" >"$OUT/$MARK"

echo "$(stamp) == 1/5 collect: $EPISODES scripted '$TASK' episodes, rig $RIG ($views), 84x84 at 20 Hz"
$BIN/viewscale collect --task "$TASK" --episodes "$EPISODES" --rig "$RIG" --out "$OUT/raw"

echo
echo "$(stamp) == 2/5 pseudo-demonstrations: $EPISODES episodes x views $views, $SPACE action space"
$BIN/viewscale dataset build --raw "$OUT/raw" --views "$views" --space "$SPACE" --out "$OUT/ds" --force

echo
echo "$(stamp) == 3/5 train: tiny diffusion policy, $STEPS steps on the pseudo-demos (CPU)"
$BIN/viewscale train --data "$OUT/ds" --preset tiny --steps "$STEPS" --out "$OUT/run"

echo
echo "$(stamp) == 4/5 serve: policy server with $WORKERS worker processes"
mkdir -p "$OUT/serve"
$BIN/viewscale serve --checkpoint "$OUT/run" --listen 127.0.0.1:0 --views "$COMPOSE" --workers "$WORKERS" \
  --log-dir "$OUT/serve" >"$OUT/serve/stdout.log" 2>"$OUT/serve/policy.log" &
server=$!
trap 'kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true' EXIT
address=""
for _ in $(seq 600); do
  address=$(sed -n 's/^ready policy \([^ ]*\).*/\1/p' "$OUT/serve/stdout.log" | head -1)
  [ -n "$address" ] && break
  if ! kill -0 "$server" 2>/dev/null; then
    echo "error: the policy server exited; its log:" >&2
    tail -20 "$OUT/serve/policy.log" >&2
    exit 1
  fi
  sleep 0.5
done
[ -n "$address" ] || { echo "error: the policy server did not start in 5 minutes ($OUT/serve/policy.log)" >&2; exit 1; }
echo "policy server ready on $address (logs: $OUT/serve)"

echo
if [ "$COMPOSE" = "$single" ]; then
  echo "$(stamp) == 5/5 evaluate: $EVAL_EPISODES closed-loop episodes from $single (one view: nothing to compose)"
else
  echo "$(stamp) == 5/5 evaluate: $EVAL_EPISODES closed-loop episodes from $single, then composed over $COMPOSE"
fi
$BIN/viewscale eval --server "$address" --task "$TASK" --episodes "$EVAL_EPISODES" --rig "$RIG" --views "$single" \
  --video 2 --out "$OUT/eval-$single"
if [ "$COMPOSE" != "$single" ]; then
  echo
  $BIN/viewscale eval --server "$address" --task "$TASK" --episodes "$EVAL_EPISODES" --rig "$RIG" --views "$COMPOSE" \
    --video 2 --video-camera "$single" --out "$OUT/eval-composed"
fi
kill "$server" 2>/dev/null || true
wait "$server" 2>/dev/null || true
trap - EXIT

echo
echo "$(stamp) done"
$BIN/python - "$OUT" "$single" <<'EOF'
import json, sys
from pathlib import Path

out = Path(sys.argv[1])
rows = ["| inference views | success | Wilson 95 % | ticks (successes) | GetAction p50 / p99 ms |", "|---|---|---|---|---|"]
for name in (f"eval-{sys.argv[2]}", "eval-composed"):
    if not (out / name).is_dir():  # (one view: no composed evaluation)
        continue
    s = json.loads((out / name / "report.json").read_text())["summary"]
    lo, hi = s["wilson95"]
    ticks = s["ticks_success_mean"] if s["ticks_success_mean"] is not None else "-"
    rows.append(
        f"| {','.join(s['views'])} | {s['successes']}/{s['episodes']} | {100 * lo:.0f}-{100 * hi:.0f} % | {ticks} | "
        f"{s['getaction_ms_p50']:.0f} / {s['getaction_ms_p99']:.0f} |"
    )
table = "\n".join(rows)
(out / "summary.md").write_text(f"# viewscale demo\n\n{table}\n")
print(table)
EOF
cat <<EOF

  episodes       $OUT/raw/*.mcap (open them in Foxglove)
  pseudo-demos   $OUT/ds (contact sheet: $OUT/ds/contact_sheet.png)
  policy         $OUT/run (loss curve: $OUT/run/loss.png; checkpoints: $OUT/run/checkpoints)
  evaluations    $OUT/eval-*/report.md (rollouts: */rollouts/*.mcap)
  videos         $OUT/eval-*/videos
  summary        $OUT/summary.md
EOF
