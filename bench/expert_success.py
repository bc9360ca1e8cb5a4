"""Scripted-expert success over seeds: the rate and the ticks to success per task.

    python bench/expert_success.py                 # 50 seeds of each task (about 10 s)
    python bench/expert_success.py --seeds 200 --tasks square

Runs each task's expert on the sim arm behind the safety layer, as a collection session does
(no rendering), from seed 0 to seeds-1 until success or the task's horizon, and prints one JSON
line: per task the success rate, the mean ticks of the successful episodes, the longest one, the
seeds that failed, and the ticks the safety layer changed (an expert should need none).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from bench.common import report  # noqa: E402
from services.core.rig import load_rig  # noqa: E402
from services.core.robot_types import EefDelta  # noqa: E402
from services.robot.safety import Safety, SafetyConfig  # noqa: E402
from sim.backends import SimRobot  # noqa: E402
from sim.experts import make_expert  # noqa: E402
from sim.world import TASKS, SimWorld  # noqa: E402


def run_task(task: str, seeds: int) -> dict:
    expert = make_expert(task)
    ticks, failed, clipped = [], [], 0
    t0 = time.perf_counter()
    with SimWorld(task, load_rig("front")) as world:
        arm = Safety(SimRobot(world), SafetyConfig(), world.control_hz)
        for seed in range(seeds):
            world.reset(seed)
            expert.reset()
            arm.begin_episode()
            for tick in range(1, world.horizon + 1):
                dp, drot, gripper = expert.act(arm.read(), world.objects())
                clipped += bool(arm.apply(EefDelta(np.asarray(dp), np.asarray(drot), float(gripper))).limits)
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
        "clipped_ticks": clipped,
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
