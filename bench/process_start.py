"""Policy process start: from the command to its ``ready`` line, for a worker and a server.

    python bench/process_start.py --checkpoint data/demo/run --rounds 5

Interleaved rounds (the machine's load hits every kind alike) of:
- ``worker``: ``python -m services.policy worker``, to ``ready worker``;
- ``worker+diffusers``: the same worker with diffusers imported first, as every worker did before
  it stopped importing it (diffusers imports torch._dynamo);
- ``server``: ``python -m services.policy serve --in-process``, to ``ready policy``;
- ``2 servers, one after the other`` and ``2 servers side by side``: two such servers, the second
  started once the first is ready, or both started at once (what the serving tests do).
Each process is stopped (SIGTERM) before the next kind starts. Reports the median and the range
of seconds per kind. The checkpoint: any run or checkpoint folder (``make demo`` makes
data/demo/run).
"""

from __future__ import annotations

import argparse
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402


def launch(argv: list[str], with_diffusers: bool = False) -> subprocess.Popen:
    if with_diffusers:
        code = "import diffusers, runpy, sys; sys.argv = sys.argv[1:]; "
        code += "runpy.run_module('services.policy', run_name='__main__')"
        cmd = [sys.executable, "-c", code, "services.policy", *argv]
    else:
        cmd = [sys.executable, "-m", "services.policy", *argv]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def wait_ready(proc: subprocess.Popen, kind: str) -> None:
    for line in proc.stdout:
        if line.startswith(f"ready {kind} "):
            return
    raise SystemExit(f"error: the {kind} exited with code {proc.wait()} before it was ready")


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.send_signal(signal.SIGTERM)
    for p in procs:
        p.wait(timeout=30)
        p.stdout.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="data/demo/run", help="run or checkpoint folder")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    if not (ROOT / args.checkpoint).exists() and not Path(args.checkpoint).exists():
        raise SystemExit(f"error: checkpoint {args.checkpoint} does not exist (make demo makes data/demo/run)")
    worker = ["worker", "--checkpoint", args.checkpoint, "--listen", "127.0.0.1:0"]
    server = ["serve", "--checkpoint", args.checkpoint, "--listen", "127.0.0.1:0", "--in-process"]

    def one(argv, kind, with_diffusers=False) -> float:
        t0 = time.perf_counter()
        p = launch(argv, with_diffusers)
        wait_ready(p, kind)
        took = time.perf_counter() - t0
        stop([p])
        return took

    def two(side_by_side: bool) -> float:
        t0 = time.perf_counter()
        if side_by_side:
            procs = [launch(server), launch(server)]
            for p in procs:
                wait_ready(p, "policy")
        else:
            procs = []
            for _ in range(2):
                procs.append(launch(server))
                wait_ready(procs[-1], "policy")
        took = time.perf_counter() - t0
        stop(procs)
        return took

    kinds = {
        "worker": lambda: one(worker, "worker"),
        "worker+diffusers": lambda: one(worker, "worker", with_diffusers=True),
        "server": lambda: one(server, "policy"),
        "2 servers, one after the other": lambda: two(False),
        "2 servers side by side": lambda: two(True),
    }
    times: dict[str, list[float]] = {k: [] for k in kinds}
    for r in range(args.rounds):
        for name, run in kinds.items():
            times[name].append(run())
        print(
            f"round {r + 1}/{args.rounds}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in times.items()),
            file=sys.stderr,
        )
    report(
        "process_start",
        {
            "checkpoint": args.checkpoint,
            "rounds": args.rounds,
            **{
                f"{k} s": {"p50": round(statistics.median(v), 2), "min": round(min(v), 2), "max": round(max(v), 2)}
                for k, v in times.items()
            },
        },
    )


if __name__ == "__main__":
    main()
