"""The teleop service as a process on a real Zenoh router: no message of any kind stops it."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from services.core import topics
from services.core.robot_types import EefDelta
from services.core.tensors import compressed_image
from services.pb.common_pb2 import Header
from services.pb.sensors_pb2 import ObjectPose, RobotState, TaskState
from services.teleop.base import TeleopDriver
from services.teleop.config import TeleopConfig
from services.teleop.service import TeleopService

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


class LooksAtF(TeleopDriver):
    """A driver of the kind a lab writes (``type: package.module:Class``) that looks at camera F:
    it answers every tick, and keeps the frame it was given."""

    cameras = ("F",)

    def __init__(self):
        self.seen: list[int] = []  # the capture stamp of the F frame of each tick it acted on

    def reset(self, task, episode_id=""):
        pass

    def act(self, state, task, frames):
        self.seen.append(frames["F"].stamp_ns)
        return EefDelta(np.zeros(3), np.zeros(3), 0.0)


def test_a_camera_that_stops_sending_holds_the_arm_still_instead_of_driving_it_blind(make_bus, caplog):
    """(a camera unplugged mid-rollout: the driver got its last frame, older every tick, and drove
    the arm on it for as long as it was gone)"""
    driver = LooksAtF()
    cfg = TeleopConfig(bus=make_bus().cfg, max_frame_gap_s=0.3)
    service = TeleopService(cfg, make_bus(), driver)
    bus = make_bus()
    commands = []
    bus.subscribe(topics.COMMAND, lambda msg, _rx: commands.append(msg.tick))
    states, frames = bus.publisher(topics.ROBOT_STATE), bus.publisher(topics.camera_image("F"))
    stop = threading.Event()
    runner = threading.Thread(target=service.run, args=(stop,))
    runner.start()
    try:
        image = np.zeros((8, 8, 3), np.uint8)
        for tick in range(20):  # 20 Hz; camera F stops after tick 9
            if tick < 10:
                frames.put(compressed_image(image, time.time_ns(), "F"))
            states.put(state(tick, "ep"))
            time.sleep(0.05)
        deadline = time.monotonic() + 5
        while len(driver.seen) + service.errors < 20 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        stop.set()
        runner.join(10)
    # ticks 10-15 come within 0.3 s of F's last frame (the driver gets it again); from tick 16 on,
    # none is answered: no command, and the robot service holds the arm still
    assert 10 <= len(driver.seen) <= 18 and len(driver.seen) + service.errors == 20, (driver.seen, service.errors)
    assert "no new frame from camera F for" in caplog.text
