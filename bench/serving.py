"""GetAction latency through the real policy server: in-process against fan-out to workers.

    python bench/serving.py                                  # tiny: V = 1, 3, 5; 1/4/8 clients
    python bench/serving.py --presets tiny,paper --paper-requests 3
    python bench/serving.py --presets paper --device cuda --precision fp32,bf16   # on a GPU
    python bench/serving.py --views 3 --fanout-workers 3 --placements pack,spread

Records two scripted lift episodes with the five15 rig, builds a camera-space dataset, and makes
a checkpoint per preset (one training step: latency does not depend on the weights; DDIM 10).
For each preset it starts servers on loopback -- computing every view in-process, or fanning out
to worker processes (``--fanout-workers``, default 1: the same compute as in-process, one model
with one intra-op thread, so that the difference is the fan-out alone) -- and then, in
interleaved rounds so that the machine's load hits both alike, has 1, 4 or 8 client threads call
GetAction composing the first V of F, FL, FR, FU, FD. Reports per (backend, V, clients) the
client-measured p50/p99 latency and the server's p50 step time, and the two targets: the
fan-out's extra time per denoising step over in-process (from the request latency, and from the
server's step time alone, which leaves out opening and closing the streams), and V=3 composed
against V=1 (both in-process).

``--placements pack,spread`` (with ``--fanout-workers 3``) compares how a request's views are
put on several workers, one fan-out backend per placement (``fan-out-pack``, ...).

Each backend runs as ``--replicas`` separate server processes (each with its own workers), pooled:
two processes of the same code differ by up to 0.7 ms per step on a 2-core VM (measured, A/A),
which is as large as the effect measured.

The floor under the fan-out's extra time is one gRPC round trip per step: in the same rounds the
bench times a bare ``DenoiseWorker.Denoise`` stream to an echo process (``--echo-server``: the same
step messages, no model) from a ``grpc.aio`` client, as the server calls its workers: answered at
once (row ``grpc-echo``, target ``grpc_round_trip_floor_ms``), and answered after an idle gap as
long as a step's compute (row ``grpc-echo-idle``, target ``grpc_round_trip_after_idle_ms``, the gap
taken off): waking an idle process costs more than a hot round trip, and every step pays it.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402

VIEWS = ["F", "FL", "FR", "FU", "FD"]


def make_dataset(root: Path, size: int) -> Path:
    from services.cli import main as viewscale

    raw, ds = root / "raw", root / "ds"
    collect = ["collect", "--task", "lift", "--episodes", "2", "--rig", "five15", "--out", str(raw)]
    if viewscale([*collect, "--size", str(size), "--fast"]) != 0:
        raise SystemExit("collect failed")
    build = ["dataset", "build", "--raw", str(raw), "--views", ",".join(VIEWS), "--out", str(ds)]
    if viewscale([*build, "--image-size", f"{size}x{size}", "--contact-episodes", "0"]) != 0:
        raise SystemExit("dataset build failed")
    return ds


def make_checkpoint(ds: Path, out: Path, preset: str, device: str) -> Path:
    from services.trainer.config import train_config_from_dict
    from services.trainer.train import train

    cfg = {
        "preset": preset,
        "data": str(ds),
        "out": str(out),
        "steps": 1,
        "batch_size": 2,
        "num_workers": 0,
        "progress": False,
        "val_every": 0,
        "checkpoint_every": 0,
        "validation": False,
        "device": device,
        "model": {"noise": {"num_inference_steps": 10}},
    }
    train(train_config_from_dict(cfg))
    return out


def start(
    args: list[str], kind: str, command: tuple[str, ...] = ("-m", "services.policy")
) -> tuple[subprocess.Popen, str]:
    """Start ``python COMMAND ARGS`` and wait for its ``ready KIND ADDRESS`` line."""
    proc = subprocess.Popen(
        [sys.executable, *command, *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    for line in proc.stdout:
        if line.startswith(f"ready {kind} "):
            return proc, line.split()[2]
    raise SystemExit(f"{kind} did not start: {args}")


def observation(ds: Path):
    from services.policy.client import State
    from services.recorder.reader import read_episode

    ep = read_episode(sorted((ds.parent / "raw").glob("*.mcap"))[0])
    st = [r.msg for r in ep.messages("/robot/state")][4:6]
    states = [State(list(s.eef_pos), list(s.eef_quat_wxyz), s.gripper, s.header.stamp_ns) for s in st]
    frames = {c: [(r.msg.data, r.publish_time) for r in ep.messages(f"/camera/{c}/image")][4:6] for c in VIEWS}
    return frames, states


def run_round(addr: str, frames, states, views: list[str], clients: int, requests: int) -> list[tuple[float, float]]:
    """(client latency s, server step p50 ms) of ``requests`` calls from each of ``clients`` threads."""
    from services.policy.client import PolicyClient

    out: list[tuple[float, float]] = []
    lock = threading.Lock()

    def one(i: int) -> None:
        with PolicyClient(addr, session_id=f"bench-{i}", timeout_s=600.0) as c:
            for _ in range(requests):
                chunk = c.get_action({v: frames[v] for v in views}, states, views=views)
                with lock:
                    out.append((chunk.latency_s, chunk.timing["step_p50_ms"]))

    threads = [threading.Thread(target=one, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return out


async def _echo_serve(gap_s: float) -> None:
    import asyncio
    import time

    import grpc

    from services.pb import policy_pb2, policy_pb2_grpc

    class Echo(policy_pb2_grpc.DenoiseWorkerServicer):
        async def Denoise(self, request_iterator, context):
            while True:
                req = await context.read()
                if req is grpc.aio.EOF:
                    return
                if not req.HasField("step"):
                    await context.write(policy_pb2.DenoiseReply())
                    continue
                t = time.perf_counter()
                if gap_s:
                    await asyncio.sleep(gap_s)  # the worker computing: this process idles meanwhile
                # the gap as slept (a timer overshoots), so that the client can take exactly it off
                await context.write(policy_pb2.DenoiseReply(eps=req.step.x, compute_ms=(time.perf_counter() - t) * 1e3))

    server = grpc.aio.server()
    policy_pb2_grpc.add_DenoiseWorkerServicer_to_server(Echo(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    print(f"ready echo 127.0.0.1:{port}", flush=True)
    await asyncio.Event().wait()


def echo_round(addr: str, n: int, tp: int = 16) -> list[float]:
    """Round trips (ms) of ``n`` step messages of a (tp, 7) float32 chunk over one Denoise stream,
    less the time the echo waited before each answer (its ``compute_ms``)."""
    import asyncio
    import time

    import grpc
    import numpy as np

    from services.core.tensors import from_tensor, to_tensor
    from services.pb import policy_pb2, policy_pb2_grpc

    async def go() -> list[float]:
        async with grpc.aio.insecure_channel(addr) as ch:
            call = policy_pb2_grpc.DenoiseWorkerStub(ch).Denoise()
            x = np.random.default_rng(0).standard_normal((tp, 7)).astype(np.float32)
            out = []
            for i in range(n + 1):  # the first opens the stream: not timed
                t = time.perf_counter()
                await call.write(policy_pb2.DenoiseRequest(step=policy_pb2.DenoiseStep(k=i, x=to_tensor(x))))
                reply = await call.read()
                from_tensor(reply.eps)
                if i:
                    out.append((time.perf_counter() - t) * 1e3 - reply.compute_ms)
            await call.done_writing()
            return out

    return asyncio.run(go())


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, round(q * (len(xs) - 1)))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="tiny")
    ap.add_argument("--views", default="1,3,5", help="numbers of composed views")
    ap.add_argument("--clients", default="1,4,8", help="numbers of concurrent clients")
    ap.add_argument("--rounds", type=int, default=6, help="interleaved rounds per configuration")
    ap.add_argument("--requests", type=int, default=3, help="requests per client per round")
    ap.add_argument("--paper-requests", type=int, default=1, help="requests per client per round for paper presets")
    ap.add_argument("--paper-clients", default="1", help="clients for paper presets")
    ap.add_argument("--size", type=int, default=84)
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--precision",
        default="fp32",
        help="fp32, bf16 (bfloat16 autocast), or both: fp32,bf16 (the bf16 rows' preset: PRESET-bf16)",
    )
    ap.add_argument("--fanout-workers", type=int, default=1, help="worker processes per fan-out server")
    ap.add_argument(
        "--placements", default="auto", help="fan-out placements to compare (auto, pack, spread; comma-separated)"
    )
    ap.add_argument("--replicas", type=int, default=2, help="server processes per backend, pooled")
    ap.add_argument("--echo-gap-ms", type=float, default=4.0, help="idle gap of the grpc-echo-idle row")
    ap.add_argument("--echo-server", action="store_true", help=argparse.SUPPRESS)  # the bench's echo process
    args = ap.parse_args()
    if args.echo_server:
        import asyncio

        asyncio.run(_echo_serve(args.echo_gap_ms / 1e3))
        return

    with tempfile.TemporaryDirectory(prefix="vs-serve-bench-") as tmp:
        ds = make_dataset(Path(tmp), args.size)
        frames, states = observation(ds)
        rows = []
        checkpoints: dict[str, Path] = {}
        for preset, precision in [(p, a) for p in args.presets.split(",") for a in args.precision.split(",")]:
            if preset not in checkpoints:
                checkpoints[preset] = make_checkpoint(ds, Path(tmp) / preset, preset, args.device)
            ckpt = checkpoints[preset]
            label = preset if precision == "fp32" else f"{preset}-{precision}"  # the rows' "preset"
            paper = preset.startswith("paper")
            clients_list = [int(c) for c in (args.paper_clients if paper else args.clients).split(",")]
            requests = args.paper_requests if paper else args.requests
            dev = ["--device", args.device, "--precision", precision]
            bench_py = (str(Path(__file__).resolve()),)
            echo, echo_addr = start(["--echo-server", "--echo-gap-ms", "0"], "echo", bench_py)
            idle, idle_addr = start(["--echo-server", "--echo-gap-ms", str(args.echo_gap_ms)], "echo", bench_py)
            procs = [echo, idle]
            placements = args.placements.split(",")
            fanouts = {pl: "fan-out" if len(placements) == 1 else f"fan-out-{pl}" for pl in placements}
            servers: dict[str, list[str]] = {"in-process": [], **{name: [] for name in fanouts.values()}}
            for _ in range(args.replicas):
                srv = ["serve", "--checkpoint", str(ckpt), "--listen", "127.0.0.1:0"]
                proc, addr = start([*srv, "--in-process", *dev], "policy")
                procs.append(proc)
                servers["in-process"].append(addr)
                for placement, name in fanouts.items():
                    wcmd = ["worker", "--checkpoint", str(ckpt), *dev]
                    workers = [start(wcmd, "worker") for _ in range(args.fanout_workers)]
                    procs += [p for p, _ in workers]
                    to = sum((["--worker", a] for _, a in workers), [])
                    proc, addr = start(
                        [*srv, *to, "--precision", precision, "--set", f"placement={placement}"], "policy"
                    )
                    procs.append(proc)
                    servers[name].append(addr)
            try:
                results: dict[tuple, list] = {}
                echo_ms: list[float] = []
                idle_ms: list[float] = []
                for addrs in servers.values():  # warm-up: first calls pay for allocations
                    for addr in addrs:
                        run_round(addr, frames, states, VIEWS, 1, 2)
                for _ in range(args.rounds):
                    echo_ms += echo_round(echo_addr, 10 * requests)
                    idle_ms += echo_round(idle_addr, 10 * requests)
                    for n_views in [int(v) for v in args.views.split(",")]:
                        for clients in clients_list:
                            for replica in range(args.replicas):
                                for name, addrs in servers.items():
                                    key = (name, n_views, clients)
                                    results.setdefault(key, []).extend(
                                        run_round(addrs[replica], frames, states, VIEWS[:n_views], clients, requests)
                                    )
                for (name, n_views, clients), got in sorted(results.items()):
                    lat = [g[0] * 1e3 for g in got]
                    rows.append(
                        {
                            "preset": label,
                            "precision": precision,
                            "backend": name,
                            "views": n_views,
                            "clients": clients,
                            "n": len(lat),
                            "p50_ms": round(pct(lat, 0.5), 2),
                            "p99_ms": round(pct(lat, 0.99), 2),
                            "step_p50_ms": round(statistics.median(g[1] for g in got), 3),
                        }
                    )
                for backend, ms in (("grpc-echo", echo_ms), ("grpc-echo-idle", idle_ms)):
                    rows.append(
                        {
                            "preset": label,
                            "precision": precision,
                            "backend": backend,
                            "n": len(ms),
                            "rtt_p50_ms": round(pct(ms, 0.5), 3),
                            "rtt_p99_ms": round(pct(ms, 0.99), 3),
                        }
                    )
            finally:
                for proc in procs:
                    proc.terminate()
                    proc.wait(timeout=30)

    def row(preset, backend, views, clients):
        return next(
            (
                r
                for r in rows
                if (r["preset"], r["backend"], r.get("views"), r.get("clients")) == (preset, backend, views, clients)
            ),
            None,
        )

    targets = {}
    for preset in dict.fromkeys(r["preset"] for r in rows):  # each preset and precision, in run order
        key = preset.replace("-", "_")
        for name in sorted({r["backend"] for r in rows if r["backend"].startswith("fan-out")}):
            tag = name.replace("fan-out", "fanout").replace("-", "_")  # fanout, or fanout_pack, ...
            for v in (1, 3, 5):
                a, b = row(preset, name, v, 1), row(preset, "in-process", v, 1)
                if a and b:
                    targets[f"{key}_{tag}_extra_ms_per_step_V{v}"] = round((a["p50_ms"] - b["p50_ms"]) / 10, 3)
                    targets[f"{key}_{tag}_extra_step_p50_ms_V{v}"] = round(a["step_p50_ms"] - b["step_p50_ms"], 3)
        for backend, target in (("grpc-echo", "round_trip_floor_ms"), ("grpc-echo-idle", "round_trip_after_idle_ms")):
            floor = next((r for r in rows if r["preset"] == preset and r["backend"] == backend), None)
            if floor:
                targets[f"{key}_grpc_{target}"] = floor["rtt_p50_ms"]
        one, three = row(preset, "in-process", 1, 1), row(preset, "in-process", 3, 1)
        if one and three:
            targets[f"{key}_V3_over_V1_in_process"] = round(three["p50_ms"] / one["p50_ms"], 3)
    settings = {
        "fanout_workers": args.fanout_workers,
        "placements": args.placements,
        "replicas": args.replicas,
        "echo_gap_ms": args.echo_gap_ms,
    }
    report(
        "serving",
        {"device": args.device, "ddim_steps": 10, "size": args.size, **settings, "targets": targets, "rows": rows},
    )


if __name__ == "__main__":
    main()
