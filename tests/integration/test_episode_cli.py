"""`viewscale episode` drives a real recorder process over a real router."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from services.core.bus import Bus, BusConfig

ROOT = Path(__file__).resolve().parents[2]


def cli(endpoint: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "episode", *args, "--connect", endpoint],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_start_status_stop_and_errors(zenoh_endpoint, tmp_path):
    rec = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.recorder",
            "--set",
            "bus.mode=client",
            "--set",
            f"bus.connect=[{zenoh_endpoint}]",
            "--set",
            f"out_dir={tmp_path}",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert rec.stdout.readline().startswith("ready recorder")
        started = cli(zenoh_endpoint, "start", "--id", "by-hand", "--task", "pour", "--rig", "five15")
        assert started.returncode == 0, started.stderr
        # where it goes, and that no arm is there to record (before: "0 ticks, 0.0 Hz, ... flags: low
        # rate: robot state at 0.00 Hz", the flags of a closed episode, for one just started)
        assert started.stdout.splitlines()[1:] == [
            f"  -> {tmp_path / 'by-hand.mcap'}",
            "  warning: no robot service or sim on this bus (namespace 'vs'): the episode records no arm "
            "state until one starts",
        ], started.stdout
        again = cli(zenoh_endpoint, "start", "--id", "other")
        assert again.returncode == 2 and again.stderr.startswith("error:")
        assert "recording" in cli(zenoh_endpoint, "status").stdout
        stopped = cli(zenoh_endpoint, "stop", "--id", "by-hand")
        assert stopped.returncode == 0, stopped.stderr
        assert "by-hand" in stopped.stdout
        assert "flags: empty: no robot/state recorded (no robot service or sim publishing it" in stopped.stdout
        assert (tmp_path / "by-hand.mcap").exists()
        assert cli(zenoh_endpoint, "stop").returncode == 2  # nothing is recording now
        discard = cli(zenoh_endpoint, "discard")  # (before: "invalid episode id ''")
        assert discard.returncode == 2
        assert discard.stderr.strip() == (
            "error: not recording; a DISCARD with an episode id deletes that finished episode"
        )
        # neither --task nor --rig (before: the id '--<time>' was refused as invalid)
        arm = Bus(BusConfig(mode="client", connect=[zenoh_endpoint]))
        arm.announce("robot")  # an arm on the bus now: no warning
        plain = cli(zenoh_endpoint, "start")
        arm.close()
        assert plain.returncode == 0, plain.stderr
        assert "warning" not in plain.stdout, plain.stdout
        assert re.search(r"episode episode-\d{8}T\d{6}\.\d{3}\n", plain.stdout), plain.stdout
        assert cli(zenoh_endpoint, "discard").returncode == 0
    finally:
        rec.terminate()
        rec.wait(timeout=20)


def test_no_router_is_one_error_line(tmp_path):
    from services.core.bus import free_tcp_port

    proc = cli(f"tcp/127.0.0.1:{free_tcp_port()}", "status", "--timeout", "1")
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: cannot open a Zenoh client session") and "Traceback" not in proc.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (("--timeout", "-1"), "--timeout must be a positive number of seconds, got -1"),  # was: waited forever
        (("--timeout", "0"), "--timeout must be a positive number of seconds, got 0"),
        (("--timeout", "nan"), "--timeout must be a positive number of seconds, got nan"),
        (("--hz", "0"), "--hz must be a positive number of Hz, got 0"),
        (("--hz", "inf"), "--hz must be a positive number of Hz, got inf"),
        (("--seed", "-3"), "--seed must be an integer from 0 to 2**64-1, got -3"),  # was: a traceback
        (("--seed", str(2**64)), f"--seed must be an integer from 0 to 2**64-1, got {2**64}"),
    ],
)
def test_a_bad_timeout_or_rate_is_refused_before_connecting(args, message):
    from services.core.bus import free_tcp_port

    # no router listens: a negative timeout was zenoh's "retry forever" (it would outlast cli's 60 s)
    proc = cli(f"tcp/127.0.0.1:{free_tcp_port()}", "start", *args)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"error: {message}"
