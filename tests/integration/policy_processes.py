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
    return ready(launch(args, kind, env, prefix, module))


def launch(
    args: list[str], kind: str, env=None, prefix: tuple[str, ...] = (), module: str = "services.policy"
) -> subprocess.Popen:
    """``start`` without the wait for its ready line (``ready``): several launched first and then
    waited for start side by side."""
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
    proc.kind = kind
    log.close()
    return proc


def ready(proc: subprocess.Popen) -> tuple[subprocess.Popen, str]:
    """(process, address) once a launched process prints its ready line."""
    for line in proc.stdout:
        if line.startswith(f"ready {proc.kind} "):
            return proc, line.split()[2]
    proc.wait()
    raise AssertionError(f"{proc.kind} did not start: {proc.log_path.read_text()[-3000:]}")


def side_by_side(procs: list[subprocess.Popen]) -> list[tuple[subprocess.Popen, str]]:
    """(process, address) of each launched process once all are ready: processes launched together
    start side by side (each imports torch for a second or two). All stopped if one fails."""
    try:
        return [ready(p) for p in procs]
    except BaseException:
        stop_all(procs)
        raise


def launch_worker(ckpt: Path, *args: str, port: int = 0, env=None, prefix: tuple[str, ...] = ()) -> subprocess.Popen:
    return launch(_worker_args(ckpt, args, port), "worker", env, prefix)


def launch_server(ckpt: Path, *args: str, env=None) -> subprocess.Popen:
    return launch(_server_args(ckpt, args), "policy", env)


def start_worker(
    ckpt: Path, *args: str, port: int = 0, env=None, prefix: tuple[str, ...] = ()
) -> tuple[subprocess.Popen, str]:
    return start(_worker_args(ckpt, args, port), "worker", env, prefix)


def _worker_args(ckpt: Path, args, port: int = 0) -> list[str]:
    return ["worker", "--checkpoint", str(ckpt), "--listen", f"127.0.0.1:{port}", *args]


def start_server(ckpt: Path, *args: str, env=None) -> tuple[subprocess.Popen, str]:
    return start(_server_args(ckpt, args), "policy", env)


def _server_args(ckpt: Path, args) -> list[str]:
    return ["serve", "--checkpoint", str(ckpt), "--listen", "127.0.0.1:0", *args]


def worker_flags(workers: list[tuple[subprocess.Popen, str]]) -> list[str]:
    """``--worker ADDR`` for each started worker (start_worker's results), for start_server."""
    return [flag for _, address in workers for flag in ("--worker", address)]


def worker_info(address: str) -> policy_pb2.WorkerInfo:
    with grpc.insecure_channel(address) as ch:
        return policy_pb2_grpc.DenoiseWorkerStub(ch).GetWorkerInfo(policy_pb2.WorkerInfoRequest(), timeout=10)


def stop_all(procs) -> None:
    """``stop`` for each of several processes (or (process, address) pairs), signalled together."""
    procs = [p[0] if isinstance(p, tuple) else p for p in procs]
    for proc in procs:
        _terminate(proc)
    for proc in procs:
        _reap(proc)


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM (SIGCONT first, for a process a test froze), SIGKILL after 20 s; its log removed."""
    _terminate(proc)
    _reap(proc)


def _terminate(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.send_signal(signal.SIGTERM)


def _reap(proc: subprocess.Popen) -> None:
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
