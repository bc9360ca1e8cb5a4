"""One service of a kind per bus, as real processes on a real router: a sim started on a session
whose robot service runs (a lab's bus) would publish its arm's state in among the real arm's, a
second teleop would answer every tick too. Each is refused with one line, exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from services.core.runtime import child_env

ROOT = Path(__file__).resolve().parents[2]


def _start(module: str, endpoint: str, *sets: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", module, "--set", "bus.mode=client", "--set", f"bus.connect=[{endpoint}]", *sets],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=child_env(),
    )


def test_a_rival_of_a_running_service_is_refused(zenoh_endpoint):
    robot = _start("services.robot", zenoh_endpoint, "--set", "driver.type=sim", "--set", "driver.task=lift")
    teleop = _start("services.teleop", zenoh_endpoint)
    running = [robot, teleop]
    try:
        assert robot.stdout.readline().startswith("ready robot")
        assert teleop.stdout.readline().startswith("ready teleop")
        for module, sets, says in [
            ("sim", (), "error: a robot service is on this bus (namespace 'vs'): both would publish robot/state;"),
            ("services.robot", ("--set", "driver.type=sim", "--set", "driver.task=lift"), "error: another robot is"),
            ("services.teleop", (), "error: another teleop is on this bus (namespace 'vs'): both would send"),
        ]:
            proc = subprocess.run(
                [sys.executable, "-m", module, "--set", "bus.mode=client", "--set", f"bus.connect=[{zenoh_endpoint}]"]
                + list(sets),
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=60,
                env=child_env(),
            )
            assert proc.returncode == 2 and "ready" not in proc.stdout, (module, proc.stdout, proc.stderr[-500:])
            assert proc.stderr.strip().splitlines()[-1].startswith(says), (module, proc.stderr[-500:])
            assert "Traceback" not in proc.stderr
        # another namespace is another session: taken
        other = _start("services.teleop", zenoh_endpoint, "--set", "bus.namespace=second")
        running.append(other)
        assert other.stdout.readline().startswith("ready teleop")
    finally:
        for p in running:
            p.terminate()
        for p in running:
            p.wait(timeout=20)
