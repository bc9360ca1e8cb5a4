"""Render speed of the sim: camera sets per second for a rig, with and without physics.

    python bench/render.py                         # five15 at 84x84 and 224x224 (about 15 s)
    python bench/render.py --rig three15 --sizes 84 --seconds 5

For each size: ``render_sets_per_s`` renders one state over and over (every camera of the rig
per set, as SimWorld.render returns them); ``step_render_sets_per_s`` alternates one 20 Hz
control tick and one render, which is what a collection session asks of the sim.
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
from sim.world import SimWorld  # noqa: E402


def rate(fn, seconds: float) -> float:
    fn()  # warm up (GL context, first upload)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        fn()
        n += 1
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default="five15")
    ap.add_argument("--task", default="square")
    ap.add_argument("--sizes", nargs="+", type=int, default=[84, 224])
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args()
    rig = load_rig(args.rig)
    zero = np.zeros(3)
    # The box may be shared: the load average says how much of it this run had.
    result = {
        "rig": args.rig,
        "cameras": len(rig.names),
        "task": args.task,
        "gl": os.environ.get("MUJOCO_GL", ""),
        "load_avg_1m_before": round(os.getloadavg()[0], 2),
    }
    for size in args.sizes:
        with SimWorld(args.task, rig, size, size) as world:
            world.reset(0)
            render_only = rate(world.render, args.seconds)

            def tick_and_render():
                world.step(zero, zero, 0.0)
                world.render()

            both = rate(tick_and_render, args.seconds)
        result[f"{size}x{size}"] = {
            "render_sets_per_s": round(render_only, 1),
            "step_render_sets_per_s": round(both, 1),
        }
    result["load_avg_1m_after"] = round(os.getloadavg()[0], 2)
    report("render", result)


if __name__ == "__main__":
    main()
