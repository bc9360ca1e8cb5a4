"""Policy servers and denoising workers as real processes on loopback: the serving tests' helpers."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import grpc

from services.pb import policy_pb2, policy_pb2_grpc

ROOT = Path(__file__).resolve().parents[2]


def start(args: list[str], kind: str, env=None) -> tuple[subprocess.Popen, str]:
    """``python -m services.policy ARGS``, once it prints ``ready KIND ADDRESS``: (process, address)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.policy", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    for line in proc.stdout:
        if line.startswith(f"ready {kind} "):
            return proc, line.split()[2]
    raise AssertionError(f"{kind} did not start: {proc.stderr.read()[-3000:]}")


def start_worker(ckpt: Path, *args: str, port: int = 0, env=None) -> tuple[subprocess.Popen, str]:
    return start(["worker", "--checkpoint", str(ckpt), "--listen", f"127.0.0.1:{port}", *args], "worker", env)


def start_server(ckpt: Path, *args: str, env=None) -> tuple[subprocess.Popen, str]:
    return start(["serve", "--checkpoint", str(ckpt), "--listen", "127.0.0.1:0", *args], "policy", env)


def worker_info(address: str) -> policy_pb2.WorkerInfo:
    with grpc.insecure_channel(address) as ch:
        return policy_pb2_grpc.DenoiseWorkerStub(ch).GetWorkerInfo(policy_pb2.WorkerInfoRequest(), timeout=10)


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM (SIGCONT first, for a process a test froze), SIGKILL after 20 s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
