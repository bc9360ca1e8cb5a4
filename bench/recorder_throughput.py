"""Recorder alone: the message and byte rates it sustains before dropping, against raw disk speed.

    .venv/bin/python bench/recorder_throughput.py [--seconds 4] [--out-dir data/bench/recorder]

Runs a loopback zenoh router in this process, ``python -m services.recorder`` as its own
process (as deployed) and a synthetic source here that publishes, per tick, one RobotState and
one JPEG per camera (pre-encoded, all distinct, so the source costs little and zstd cannot
dedupe frames). For each workload the tick rate doubles until an episode shows drops (or the
source cannot reach the rate), then bisects between the last clean and the first dropping rate.
An episode is clean when nothing was dropped and every channel holds all the ticks sent. Raw disk
speed is measured first in the same directory: 1 MiB writes then fsync, like the recorder's
chunked writes plus its close. Prints one JSON line and appends it to bench/RESULTS.md
(``bench/common.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import machine, report  # noqa: E402
from services.core import topics  # noqa: E402
from services.core.bus import Bus, BusConfig, free_tcp_port, router  # noqa: E402
from services.core.tensors import compressed_image  # noqa: E402
from services.pb.episode_pb2 import (  # noqa: E402
    EPISODE_COMMAND_START,
    EPISODE_COMMAND_STOP,
    EpisodeReply,
    EpisodeRequest,
)
from services.pb.sensors_pb2 import RobotState  # noqa: E402


def disk_write_mbps(directory: Path, total_mb: int = 512) -> float:
    """Sequential 1 MiB writes of incompressible bytes, then fsync: MB/s (1 MB = 1e6 bytes)."""
    path = directory / "disk_probe.bin"
    block = os.urandom(1 << 20)
    t = time.perf_counter()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        for _ in range(total_mb):
            os.write(fd, block)
        os.fsync(fd)
    finally:
        os.close(fd)
    elapsed = time.perf_counter() - t
    path.unlink()
    return total_mb * (1 << 20) / elapsed / 1e6


class Harness:
    def __init__(self, out_dir: Path, decode_images: bool, log: Path):
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.router = router([self.endpoint])
        self.bus = Bus(BusConfig(mode="client", connect=[self.endpoint]))
        self.out_dir = out_dir
        self._log = open(log, "a")
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.recorder",
                "--set",
                "bus.mode=client",
                "--set",
                f"bus.connect=[{self.endpoint}]",
                "--set",
                f"out_dir={out_dir}",
                "--set",
                f"decode_images={str(decode_images).lower()}",
                "--set",
                "stop_grace_s=10",
                "--set",
                "log_level=WARNING",
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
        )
        ready = self.proc.stdout.readline()
        if not ready.startswith("ready recorder"):
            raise SystemExit(f"recorder did not start (see {log})")
        threading.Thread(target=self.proc.stdout.read, daemon=True).start()
        self.bus.wait_alive(["recorder"], timeout=30)
        self.episode = 0

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=30)
        self.bus.close()
        self.router.close()
        self._log.close()

    def control(self, command: int, **fields) -> EpisodeReply:
        req = EpisodeRequest(command=command, **fields)
        return EpisodeReply.FromString(self.bus.query(topics.EPISODE_CONTROL, req.SerializeToString(), timeout=60))

    def run_episode(self, frames: list[list[bytes]], cameras: list[str], tick_hz: float, seconds: float) -> dict:
        """Publish at ``tick_hz`` for ``seconds``; return what the recorder made of it."""
        self.episode += 1
        episode_id = f"bench{self.episode:03d}"
        state_pub = self.bus.publisher(topics.ROBOT_STATE)
        image_pubs = [self.bus.publisher(topics.camera_image(c)) for c in cameras]
        reply = self.control(EPISODE_COMMAND_START, episode_id=episode_id, task="bench", control_hz=tick_hz)
        assert reply.ok, reply.error
        ticks = int(tick_hz * seconds)
        sent_bytes = 0
        state = RobotState(
            eef_pos=[0.4, 0.0, 0.2], eef_quat_wxyz=[1, 0, 0, 0], joint_pos=[0.0] * 7, joint_vel=[0.0] * 7
        )
        t0 = time.perf_counter()
        for i in range(ticks):
            # Absolute schedule; when behind, publish straight away (the source is then the limit).
            delay = t0 + i / tick_hz - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            state.tick = i
            state.header.stamp_ns, state.header.seq = time.time_ns(), i
            data = state.SerializeToString()
            state_pub.put(data)
            sent_bytes += len(data)
            for pub, cam_frames in zip(image_pubs, frames):
                data = cam_frames[i % len(cam_frames)]
                pub.put(data)
                sent_bytes += len(data)
        publish_s = time.perf_counter() - t0
        reply = self.control(EPISODE_COMMAND_STOP, episode_id=episode_id, success=True, ticks=ticks)
        assert reply.ok, reply.error
        meta = reply.meta
        path = Path(meta.path)
        file_bytes = path.stat().st_size
        path.unlink()
        # Clean: nothing dropped, and every camera and the state channel hold all ticks (else flagged).
        complete = all(meta.frames.get(c, 0) == ticks for c in cameras) and not any(
            f.startswith("robot/state:") for f in meta.flags
        )
        return {
            "tick_hz": tick_hz,
            "achieved_tick_hz": ticks / publish_s,
            "clean": complete and not meta.drops,
            "drops": sum(meta.drops.values()),
            "malformed": sum(meta.malformed.values()),
            "msgs_per_s": ticks * (1 + len(cameras)) / publish_s,
            "MBps": sent_bytes / publish_s / 1e6,
            "file_MBps": file_bytes / publish_s / 1e6,
        }


def make_frames(cameras: int, per_camera: int, size: int, rng: np.random.Generator) -> list[list[bytes]]:
    """Distinct camera-like JPEG messages: a smooth gradient scene plus sensor noise."""
    yy, xx = np.mgrid[0:size, 0:size]
    base = np.stack([xx, yy, (xx + yy) // 2], axis=-1).astype(np.float32) * (255.0 / (2 * size))
    out = []
    for c in range(cameras):
        frames = []
        for i in range(per_camera):
            noise = rng.normal(0, 6, base.shape)
            img = np.clip(base + 40 * c + noise + i % 50, 0, 255).astype(np.uint8)
            frames.append(compressed_image(img, time.time_ns(), f"C{c}").SerializeToString())
        out.append(frames)
    return out


def sustained(h: Harness, frames, cameras, seconds: float, start_hz: float, max_hz: float) -> dict:
    """Highest tick rate with a clean episode: doubling, then three bisection steps."""
    good, bad, trials = None, None, []
    hz = start_hz
    while hz <= max_hz:
        r = h.run_episode(frames, cameras, hz, seconds)
        trials.append(r)
        clean = r["clean"]
        source_limited = r["achieved_tick_hz"] < 0.95 * hz
        if clean:
            good = r
        else:
            bad = r
            break
        if source_limited:
            break
        hz *= 2
    if good is not None and bad is not None:
        lo, hi = good["tick_hz"], bad["tick_hz"]
        for _ in range(3):
            mid = (lo + hi) / 2
            r = h.run_episode(frames, cameras, mid, seconds)
            trials.append(r)
            if r["clean"]:
                good, lo = r, mid
            else:
                hi = mid
    if good is None:
        limited = "recorder (drops even at the lowest rate tried)"
    elif bad is not None:
        limited = "recorder (drops above this)"
    else:
        limited = "source (could not publish faster)"
    best = good or trials[0]
    return {"sustained": best, "limited_by": limited, "trials": len(trials)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="length of each trial episode")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "data" / "bench" / "recorder")
    parser.add_argument("--cameras", type=int, default=5)
    parser.add_argument("--size", type=int, default=256, help="square frame size in pixels")
    parser.add_argument("--no-results", action="store_true", help="do not append to bench/RESULTS.md")
    args = parser.parse_args()
    out_dir = args.out_dir
    shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir(parents=True)
    rng = np.random.default_rng(0)
    load_before = round(os.getloadavg()[0], 2)
    disk = disk_write_mbps(out_dir)
    frames = make_frames(args.cameras, 64, args.size, rng)
    cameras = [f"C{c}" for c in range(args.cameras)]
    frame_kb = float(np.mean([len(f) for cam in frames for f in cam])) / 1e3
    runs = {}
    for decode in (True, False):
        h = Harness(out_dir, decode, out_dir / "recorder.log")
        try:
            runs[f"images_decode_{str(decode).lower()}"] = sustained(h, frames, cameras, args.seconds, 25, 3200)
            if decode:
                runs["states_only"] = sustained(h, [], [], args.seconds, 500, 64000)
        finally:
            h.close()
    result = {
        "disk_write_MBps": round(disk, 1),
        "workload": f"per tick: 1 RobotState + {args.cameras} JPEG {args.size}x{args.size} (~{frame_kb:.1f} kB)",
        "load_avg_1m": [load_before, round(os.getloadavg()[0], 2)],  # shared machine: before, after
        "results": {
            name: {
                "limited_by": r["limited_by"],
                "ticks_per_s": round(r["sustained"]["achieved_tick_hz"], 1),
                "msgs_per_s": round(r["sustained"]["msgs_per_s"], 1),
                "MBps": round(r["sustained"]["MBps"], 2),
                "file_MBps": round(r["sustained"]["file_MBps"], 2),
                "fraction_of_disk": round(r["sustained"]["file_MBps"] / disk, 4),
            }
            for name, r in runs.items()
        },
    }
    if args.no_results:
        print(json.dumps({"bench": "recorder_throughput", "machine": machine(), **result}), flush=True)
    else:
        report("recorder_throughput", result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
