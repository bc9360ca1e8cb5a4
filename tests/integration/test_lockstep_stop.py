"""A lockstep service stopped while a tick waits for its command: the sim (or a robot service) in
lockstep waits up to ``command_timeout_s`` for each tick's command, and `viewscale eval` sets that
to 120 s for slow policies. Stopped mid-episode, its teleop gone, it waited that out: `viewscale
eval` interrupted with Ctrl-C then took 21 to 41 s to end (its stack's 20 s per service, then
SIGKILL). Real processes on a real router; the tick's wait must end with the stop signal."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.core import topics
from services.core.runtime import child_env
from services.pb.episode_pb2 import SimCommand, SimControlReply, SimControlRequest

ROOT = Path(__file__).resolve().parents[2]
LOCKSTEP = ("--set", "realtime=false", "--set", "command_timeout_s=120")


def _start(module: str, endpoint: str, log: Path, *sets: str) -> subprocess.Popen:
    with open(log, "w") as f:
        proc = subprocess.Popen(
            [sys.executable, "-m", module, "--set", "bus.mode=client", "--set", f"bus.connect=[{endpoint}]", *sets],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=f,
            text=True,
            env=child_env(),
        )
    line = proc.stdout.readline()
    assert line.startswith("ready "), (line, log.read_text()[-2000:])
    return proc


def _stopped_within(proc: subprocess.Popen, seconds: float, log: Path) -> float:
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"still running {seconds} s after SIGTERM:\n{log.read_text()[-2000:]}") from None
    return time.monotonic() - t0


@pytest.mark.parametrize("module", ["sim", "services.robot"])
def test_a_lockstep_tick_waiting_for_its_command_ends_with_the_stop_signal(module, zenoh_endpoint, make_bus, tmp_path):
    log = tmp_path / f"{module}.log"
    if module == "sim":
        proc = _start(
            module, zenoh_endpoint, log, *LOCKSTEP, "--set", "rig=front", "--set", "width=32", "--set", "height=32"
        )
        bus = make_bus()
        for command in (SimCommand.SIM_COMMAND_RESET, SimCommand.SIM_COMMAND_RUN):  # an episode under way, no teleop
            raw = bus.query(
                topics.SIM_CONTROL, SimControlRequest(command=command, task="lift").SerializeToString(), 20.0
            )
            assert SimControlReply.FromString(raw).ok
        said = "sim stopped at tick 1 (1 stale ticks"  # tick 0 waited for its command and held
    else:
        proc = _start(module, zenoh_endpoint, log, *LOCKSTEP, "--set", "driver.type=sim", "--set", "driver.task=lift")
        said = "control loop stopped at tick 1 (1 stale ticks"
    time.sleep(1.0)  # the first tick is waiting for its command
    took = _stopped_within(proc, 10.0, log)
    assert proc.returncode == 0 and said in log.read_text(), log.read_text()[-2000:]
    assert took < 5.0, f"{took:.1f} s to stop"
