"""The teleop service as a process on a real Zenoh router: no message of any kind stops it."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

from services.core import topics
from services.pb.common_pb2 import Header
from services.pb.sensors_pb2 import ObjectPose, RobotState, TaskState

ROOT = Path(__file__).resolve().parents[2]


def state(tick: int, episode: str) -> RobotState:
    return RobotState(
        header=Header(stamp_ns=time.time_ns(), seq=tick + 1),
        tick=tick,
        eef_pos=[0.45, 0.0, 0.25],
        eef_quat_wxyz=[0, 1, 0, 0],
        joint_pos=[0.0] * 6,
        joint_vel=[0.0] * 6,
        gripper=0.0,
        episode_id=episode,
    )


def test_a_state_of_an_episode_without_task_state_does_not_stop_the_teleop(zenoh_endpoint, make_bus):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.teleop",
            "--set",
            "bus.mode=client",
            "--set",
            f"bus.connect=[{zenoh_endpoint}]",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().startswith("ready teleop"), proc.stderr.read()
        bus = make_bus()
        bus.wait_alive({"teleop"}, timeout=30)
        commands = []
        got = threading.Event()

        def on_command(msg, _rx):
            commands.append(msg)
            got.set()

        bus.subscribe(topics.COMMAND, on_command)
        states, tasks = bus.publisher(topics.ROBOT_STATE), bus.publisher(topics.TASK_STATE)
        ghost = state(0, "ghost")  # well formed, but no TaskState ever names its episode
        assert len(ghost.SerializeToString()) < 200
        states.put(ghost)
        time.sleep(0.5)  # long past its task-state wait: the reset of "ghost" failed inside the tick
        assert proc.poll() is None, proc.stderr.read()
        task = TaskState(
            header=Header(stamp_ns=time.time_ns(), seq=1),
            tick=3,
            task="lift",
            episode_id="real",
            objects=[ObjectPose(name="cube", pos=[0.5, 0.0, 0.02], quat_wxyz=[1, 0, 0, 0])],
        )
        deadline = time.monotonic() + 30
        while not got.is_set():  # the next real episode is answered
            assert time.monotonic() < deadline and proc.poll() is None
            tasks.put(task)
            states.put(state(3, "real"))
            got.wait(0.5)
        assert commands[0].tick == 3 and commands[0].source == "scripted"
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    assert "teleop driver failed at tick 0 of ghost" in proc.stderr.read()
