"""Closed-loop success of a `tiny` policy trained on this machine, through the real services.

    python bench/closed_loop.py --task lift                  # collect 20, build, train 6000, eval 50 (about 1 h)
    python bench/closed_loop.py --task can --checkpoint runs/can-tiny-6k        # evaluate a trained run
    python bench/closed_loop.py --task can --checkpoint runs/can-tiny-6k --eval-report runs/eval-can/report.json

Every stage is the `viewscale` command a user runs (collect -> dataset build -> train -> eval, the
evaluation on the task's fixed held-out seeds, view F by default). With ``--checkpoint`` the first
three stages are skipped and the training time is read from the run's ``log.jsonl`` (the sum of
the logged step times: compute, not wall clock); with ``--eval-report`` an evaluation already run
by ``viewscale eval`` on that checkpoint is recorded instead of running another. Prints one JSON
line and appends it to bench/RESULTS.md, with the issue's target (lift >= 80 %, can >= 50 %, square
none) and whether it was met.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402

TARGETS = {"lift": 0.8, "can": 0.5}  # success rate from F, N = 20 five-view demos, under an hour of training


def viewscale(*args: str) -> float:
    """Run one `viewscale` command, its output passed through to stderr; returns its wall time."""
    t0 = time.monotonic()
    cmd = [sys.executable, "-m", "services.cli", *args]
    print(f"$ viewscale {' '.join(args)}", file=sys.stderr, flush=True)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.run(cmd, cwd=ROOT, stdout=sys.stderr, stderr=sys.stderr, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"viewscale {args[0]} failed (exit {proc.returncode})")
    return time.monotonic() - t0


def train_facts(run: Path) -> dict:
    """Steps, mean it/s and the summed step time from a training run's log.jsonl."""
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    rows = [r for r in rows if r.get("it_s")]
    if not rows:
        raise SystemExit(f"{run}/log.jsonl has no training steps")
    cfg = json.loads((run / "config.json").read_text())
    every = int(cfg.get("log_every", 10))
    return {
        "steps": rows[-1]["step"],
        "steps_planned": cfg.get("steps"),
        "it_s_mean": round(sum(r["it_s"] for r in rows) / len(rows), 3),
        "train_s_from_log": round(sum(every / r["it_s"] for r in rows), 1),
        "batch_size": cfg.get("batch_size"),
        "preset": cfg.get("preset"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="lift", choices=["lift", "can", "square"])
    ap.add_argument("--demos", type=int, default=20)
    ap.add_argument("--rig", default="five15")
    ap.add_argument("--space", default="camera")
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--views", default="F", help="evaluation views (composed if several)")
    ap.add_argument("--out", default="runs/bench-closed-loop")
    ap.add_argument("--checkpoint", help="a trained run or checkpoint: evaluate it only")
    ap.add_argument("--eval-report", help="report.json of a `viewscale eval` of --checkpoint: record it")
    args = ap.parse_args()
    out = ROOT / args.out / args.task
    stages: dict[str, float] = {}
    if args.checkpoint:
        ckpt = Path(args.checkpoint).resolve()
        run = ckpt if (ckpt / "log.jsonl").is_file() else ckpt.parent.parent
    else:
        from services.core.rig import load_rig

        views = ",".join(load_rig(args.rig).names)
        stages["collect_s"] = viewscale(
            "collect", "--task", args.task, "--episodes", str(args.demos), "--rig", args.rig, "--out", str(out / "raw")
        )
        stages["build_s"] = viewscale(
            "dataset", "build", "--raw", str(out / "raw"), "--views", views, "--space", args.space,
            "--out", str(out / "ds"), "--force",
        )  # fmt: skip
        run = ckpt = out / "run"
        stages["train_s"] = viewscale(
            "train", "--data", str(out / "ds"), "--preset", "tiny", "--steps", str(args.steps), "--out", str(run)
        )
    if args.eval_report:
        rep = json.loads(Path(args.eval_report).read_text())["summary"]
        if not str(Path(rep["checkpoint"]).resolve()).startswith(str(run.resolve())):
            raise SystemExit(f"{args.eval_report} evaluated {rep['checkpoint']}, not {ckpt}")
    else:
        ev = out / f"eval-{args.views.replace(',', '+')}-{time.strftime('%Y%m%dT%H%M%S')}"
        stages["eval_s"] = viewscale(
            "eval", "--checkpoint", str(ckpt), "--task", args.task, "--episodes", str(args.episodes),
            "--views", args.views, "--out", str(ev),
        )  # fmt: skip
        rep = json.loads((ev / "report.json").read_text())["summary"]
    target = TARGETS.get(args.task)
    report(
        "closed_loop",
        {
            "task": args.task,
            "checkpoint": rep["checkpoint"],
            "train": train_facts(run),
            "eval_views": rep["views"],
            "successes": rep["successes"],
            "episodes": rep["episodes"],
            "success_rate": round(rep["success_rate"], 3),
            "wilson95": rep["wilson95"],
            "seeds": rep["seeds"],
            "getaction_ms_p50": rep["getaction_ms_p50"],
            "getaction_ms_p99": rep["getaction_ms_p99"],
            "eval_wall_s": rep["wall_s"],
            **{k: round(v, 1) for k, v in stages.items()},
            "target_success_rate": target,
            "target_met": None if target is None else rep["success_rate"] >= target,
        },
    )


if __name__ == "__main__":
    main()
