"""Scripted-expert success over seeds: the rate and the ticks to success per task.

    python bench/expert_success.py                 # 50 seeds of each task (about 10 s)
    python bench/expert_success.py --seeds 200 --tasks square

Runs each task's expert in a SimWorld (no rendering) from seed 0 to seeds-1 until success or
the task's horizon, and prints one JSON line: per task the success rate, the mean ticks of the
successful episodes, the longest one, and the seeds that failed.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import report  # noqa: E402
from services.core.rig import load_rig  # noqa: E402
from sim.experts import make_expert  # noqa: E402
from sim.world import TASKS, SimWorld  # noqa: E402


def run_task(task: str, seeds: int) -> dict:
    expert = make_expert(task)
    ticks, failed = [], []
    t0 = time.perf_counter()
    with SimWorld(task, load_rig("front")) as world:
        for seed in range(seeds):
            world.reset(seed)
            expert.reset()
            for tick in range(1, world.horizon + 1):
                world.step(*expert.act(world.robot(), world.objects()))
                if world.success():
                    ticks.append(tick)
                    break
            else:
                failed.append(seed)
    return {
        "success": round(len(ticks) / seeds, 3),
        "mean_ticks": round(sum(ticks) / max(1, len(ticks)), 1),
        "max_ticks": max(ticks, default=0),
        "horizon": world.horizon,
        "failed_seeds": failed,
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    args = ap.parse_args()
    report("expert_success", {"seeds": args.seeds, **{t: run_task(t, args.seeds) for t in args.tasks}})


if __name__ == "__main__":
    main()
