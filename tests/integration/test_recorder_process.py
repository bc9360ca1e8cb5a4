"""``python -m services.recorder`` as a user runs it: ready line, SIGTERM, kill -9 and recovery."""

from __future__ import annotations

import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from signals import signal_another_thread

from services.core import topics
from services.core.bus import Bus, BusConfig, free_tcp_port, router
from services.core.tensors import compressed_image
from services.pb.episode_pb2 import EPISODE_COMMAND_START, EPISODE_COMMAND_STATUS, EpisodeReply, EpisodeRequest
from services.pb.sensors_pb2 import RobotState
from services.recorder.reader import read_episode
from services.recorder.recover import RECOVERED_FLAG

REPO = Path(__file__).resolve().parents[2]
RNG = np.random.default_rng(2)


class RecorderProcess:
    def __init__(self, endpoint: str, out_dir: Path, log: Path, *sets: str):
        cmd = [
            sys.executable,
            "-m",
            "services.recorder",
            "--set",
            "bus.mode=client",
            "--set",
            f"bus.connect=[{endpoint}]",
            "--set",
            f"out_dir={out_dir}",
        ]
        for item in sets:
            cmd += ["--set", item]
        self.log = log
        self._log_file = open(log, "w")
        self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=self._log_file, text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def wait_ready(self, timeout: float = 30.0) -> str:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"no ready line in {timeout:.0f}s; log:\n{self.log.read_text()}") from None
            if line.startswith("ready recorder"):
                return line

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._log_file.close()


@pytest.fixture
def session(tmp_path):
    """A router, a client session for the test, and a way to start recorder processes on it."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs: list[RecorderProcess] = []
    with router([endpoint]), Bus(BusConfig(mode="client", connect=[endpoint])) as bus:

        def start(*sets: str) -> RecorderProcess:
            proc = RecorderProcess(endpoint, tmp_path / "episodes", tmp_path / f"recorder{len(procs)}.log", *sets)
            procs.append(proc)
            assert proc.wait_ready() == f"ready recorder {tmp_path / 'episodes'}"
            bus.wait_alive(["recorder"], timeout=15)
            return proc

        yield bus, start
        for proc in procs:
            proc.stop()


def control(bus: Bus, command: int, **fields) -> EpisodeReply:
    req = EpisodeRequest(command=command, **fields)
    return EpisodeReply.FromString(bus.query(topics.EPISODE_CONTROL, req.SerializeToString(), timeout=15))


def wait_status(bus: Bus, ticks: int, frames: dict[str, int], timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        meta = control(bus, EPISODE_COMMAND_STATUS).meta
        if meta.ticks == ticks and dict(meta.frames) == frames:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"recorder has {meta.ticks} states, frames {dict(meta.frames)}")
        time.sleep(0.02)


def publish(bus: Bus, ticks: int, cameras=("F", "L"), shape=(32, 48)) -> dict[str, list[int]]:
    """Robot state + a noise JPEG per camera per tick; returns payload sizes per mcap topic, in order."""
    state_pub = bus.publisher(topics.ROBOT_STATE)
    image_pubs = {c: bus.publisher(topics.camera_image(c)) for c in cameras}
    sent: dict[str, list[int]] = {}
    t0 = time.time_ns()
    for i in range(ticks):
        stamp = t0 + i * 20_000_000
        time.sleep(max(0.0, (stamp - time.time_ns()) / 1e9))  # sent when stamped, as a real source's
        state = RobotState(tick=i, eef_pos=[0.4, 0.0, 0.2], eef_quat_wxyz=[1, 0, 0, 0])
        state.header.stamp_ns, state.header.seq = stamp, i
        data = state.SerializeToString()
        state_pub.put(data)
        sent.setdefault(topics.ROBOT_STATE.mcap_topic, []).append(len(data))
        for c, p in image_pubs.items():
            data = compressed_image(RNG.integers(0, 255, (*shape, 3), dtype=np.uint8), stamp, c).SerializeToString()
            p.put(data)
            sent.setdefault(topics.camera_image(c).mcap_topic, []).append(len(data))
    return sent


@pytest.mark.parametrize("thread", ["main", "another"])
def test_sigterm_closes_the_file_completely(session, thread):
    bus, start = session
    proc = start()
    assert control(bus, EPISODE_COMMAND_START, episode_id="term", task="lift", seed=1, rig="front", control_hz=50).ok
    publish(bus, 10)
    wait_status(bus, 10, {"F": 10, "L": 10})
    if thread == "main":
        proc.proc.send_signal(signal.SIGTERM)
    else:  # as the kernel may deliver it (a kill, or `viewscale collect` killed -9): to one of zenoh's threads
        signal_another_thread(proc.proc.pid, signal.SIGTERM)
    assert proc.proc.wait(timeout=30) == 0
    episodes = Path(proc.log).parent / "episodes"
    assert sorted(p.name for p in episodes.iterdir()) == ["term.mcap"]
    ep = read_episode(episodes / "term.mcap")
    assert ep.metadata["frames"] == {"F": 10, "L": 10} and ep.metadata["ticks"] == 10
    assert any(f.startswith("interrupted") for f in ep.flags)
    assert ep.meta.episode_id == "term" and ep.metadata["task"] == "lift"
    assert "received SIGTERM" in proc.log.read_text()


def test_kill9_loses_at_most_the_open_chunk_and_recovers(session):
    bus, start = session
    chunk = 16384
    proc = start(f"chunk_size={chunk}", "flush_interval_s=600")  # only size cuts chunks here
    assert control(bus, EPISODE_COMMAND_START, episode_id="killed", task="push", seed=9, rig="five15", control_hz=50).ok
    sent = publish(bus, 80)
    wait_status(bus, 80, {"F": 80, "L": 80})  # everything is in the writer, nothing left in queues
    proc.proc.send_signal(signal.SIGKILL)
    proc.proc.wait(timeout=10)
    episodes = proc.log.parent / "episodes"
    part = episodes / "killed.mcap.part"
    assert part.is_file() and not (episodes / "killed.mcap").exists()

    run = subprocess.run(
        [sys.executable, "-m", "services.recorder.recover", str(part)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    assert f"-> {episodes / 'killed.mcap'}" in run.stdout and " messages on " in run.stdout
    ep = read_episode(episodes / "killed.mcap")
    assert any(f.startswith(RECOVERED_FLAG) for f in ep.flags)
    assert (ep.metadata["task"], ep.metadata["seed"], ep.metadata["rig"]) == ("push", 9, "five15")
    lost_bytes = 0
    recovered = 0
    for topic, sizes in sent.items():
        recs = ep.messages(topic)
        assert [r.sequence for r in recs] == list(range(len(recs)))  # a prefix of what was written
        recovered += len(recs)
        lost_bytes += sum(sizes[len(recs) :])
    assert recovered > 0 and f"{recovered} messages" in run.stdout
    # The open chunk held less than chunk_size bytes: nothing older than it is missing.
    assert lost_bytes <= chunk, (lost_bytes, recovered)
    assert sum(sum(s) for s in sent.values()) > 10 * chunk  # the episode spanned many chunks


def test_bad_settings_exit_with_a_clear_error(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "services.recorder", "--set", "queue_size=0"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2 and "invalid RecorderConfig" in run.stderr and "queue_size" in run.stderr
