"""Policy servers and denoising workers as real processes on loopback: the serving tests' helpers."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import grpc

from services.core.runtime import child_env
from services.pb import policy_pb2, policy_pb2_grpc

ROOT = Path(__file__).resolve().parents[2]


def start(
    args: list[str], kind: str, env=None, prefix: tuple[str, ...] = (), module: str = "services.policy"
) -> tuple[subprocess.Popen, str]:
    """``[PREFIX] python -m MODULE ARGS``, once it prints ``ready KIND ADDRESS``: (process,
    address). ``prefix``: a command it runs under (``taskset -c 1``); ``module``: ``services.cli``
    runs it as ``viewscale ARGS``.

    Its log goes to a file (``proc.log_path``), never to a pipe nobody reads: a full pipe would
    block the process at its next log line."""
    log = tempfile.NamedTemporaryFile("w+", prefix=f"vs-{kind}-", suffix=".log", delete=False)
    proc = subprocess.Popen(
        [*prefix, sys.executable, "-m", module, *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=log,
        text=True,
        env=child_env(env),  # dies with the test run, also when a test fails before it stops it
    )
    proc.log_path = Path(log.name)
    log.close()
    for line in proc.stdout:
        if line.startswith(f"ready {kind} "):
            return proc, line.split()[2]
    proc.wait()
    raise AssertionError(f"{kind} did not start: {proc.log_path.read_text()[-3000:]}")


def start_worker(
    ckpt: Path, *args: str, port: int = 0, env=None, prefix: tuple[str, ...] = ()
) -> tuple[subprocess.Popen, str]:
    return start(["worker", "--checkpoint", str(ckpt), "--listen", f"127.0.0.1:{port}", *args], "worker", env, prefix)


def start_server(ckpt: Path, *args: str, env=None) -> tuple[subprocess.Popen, str]:
    return start(["serve", "--checkpoint", str(ckpt), "--listen", "127.0.0.1:0", *args], "policy", env)


def worker_flags(workers: list[tuple[subprocess.Popen, str]]) -> list[str]:
    """``--worker ADDR`` for each started worker (start_worker's results), for start_server."""
    return [flag for _, address in workers for flag in ("--worker", address)]


def worker_info(address: str) -> policy_pb2.WorkerInfo:
    with grpc.insecure_channel(address) as ch:
        return policy_pb2_grpc.DenoiseWorkerStub(ch).GetWorkerInfo(policy_pb2.WorkerInfoRequest(), timeout=10)


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM (SIGCONT first, for a process a test froze), SIGKILL after 20 s; its log removed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if proc.stdout:
        proc.stdout.close()
    log_path = getattr(proc, "log_path", None)
    if log_path is not None and not os.environ.get("VIEWSCALE_KEEP_TEST_LOGS"):
        log_path.unlink(missing_ok=True)
