"""Collection at 20 Hz through the real services: achieved rate, drops and CPU per service.

    python bench/collection.py --size 84 --seconds 300     # the issue's 5-minute run
    python bench/collection.py --size 224 --seconds 300

Runs the local stack (router in this process; sim, teleop, recorder as subprocesses), records
scripted-expert episodes back to back for ``--seconds``, and reports the achieved control rate
(from each episode's capture times, as the recorder measures it), recorder drops, stale ticks,
and each process's CPU use (% of one core) over the run.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import psutil  # noqa: E402

from bench.common import report  # noqa: E402
from services.core.bus import Bus  # noqa: E402
from services.session.collect import LocalStack  # noqa: E402
from services.session.config import SessionConfig  # noqa: E402
from services.session.session import Session  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=84)
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--rig", default="five15")
    ap.add_argument("--task", default="lift")
    ap.add_argument("--hz", type=float, default=20.0)
    args = ap.parse_args()

    load0 = round(os.getloadavg()[0], 2)  # other work on the machine skews CPU and rate numbers
    with tempfile.TemporaryDirectory(prefix="vs-bench-") as tmp:
        out = Path(tmp)
        sim = [
            f"rig={args.rig}",
            f"task={args.task}",
            f"width={args.size}",
            f"height={args.size}",
            f"control_hz={args.hz}",
            "realtime=true",
        ]
        with LocalStack(out, None, {"sim": sim, "recorder": [f"out_dir={out}"], "teleop": []}) as stack:
            procs = {c.name: psutil.Process(c.proc.pid) for c in stack.children}
            procs["router+session"] = psutil.Process()
            cfg = SessionConfig(bus=stack.bus_config(), task=args.task, rig=args.rig, control_hz=args.hz, episodes=1)
            with Bus(cfg.bus) as bus:
                session = Session(cfg, bus, progress=lambda s: print(s, file=sys.stderr))
                bus.wait_alive(cfg.services, timeout=cfg.wait_services_s)
                session.warm_up()
                cpu0 = {n: sum(p.cpu_times()[:2]) for n, p in procs.items()}
                t0 = time.monotonic()
                attempts, seed = [], 0
                while time.monotonic() - t0 < args.seconds:
                    attempts.append(session.run_episode(seed))
                    seed += 1
                wall = time.monotonic() - t0
                cpu = {n: round(100 * (sum(p.cpu_times()[:2]) - cpu0[n]) / wall, 1) for n, p in procs.items()}
            stack.check_alive()

    recorded = [a.meta for a in attempts if a.meta is not None]
    ticks = sum(a.ticks for a in attempts)
    report(
        "collection",
        {
            "load_avg_1m_before_after": [load0, round(os.getloadavg()[0], 2)],
            "rig": args.rig,
            "size": args.size,
            "control_hz": args.hz,
            "seconds": round(wall, 1),
            "episodes": len(attempts),
            "recorded": len(recorded),
            "ticks": ticks,
            "achieved_hz_mean": round(sum(m.achieved_hz for m in recorded) / max(1, len(recorded)), 2),
            "achieved_hz_min": round(min((m.achieved_hz for m in recorded), default=0.0), 2),
            "drops": int(sum(sum(m.drops.values()) for m in recorded)),
            "stale_ticks": int(sum(m.stale_ticks for m in recorded)),
            "failed_attempts": len(attempts) - len(recorded),
            "flagged": sum(1 for m in recorded if m.flags),
            "cpu_percent": cpu,
        },
    )


if __name__ == "__main__":
    main()
