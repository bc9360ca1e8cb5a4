"""The standalone robot and camera services as processes on a real Zenoh router."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from polling import wait_for

from services.core import topics
from services.core.config import ConfigError
from services.core.rig import Camera, load_rig
from services.core.tensors import decode_jpeg
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import EefAction, EefCommand
from services.robot.base import RobotDriver
from services.robot.config import ROBOT_DRIVERS, RobotConfig

ROOT = Path(__file__).resolve().parents[2]


def start(module: str, endpoint: str, *overrides: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", module, "--set", "bus.mode=client", "--set", f"bus.connect=[{endpoint}]"]
    for item in overrides:
        cmd += ["--set", item]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()  # blocks until the ready line (or EOF if it died)
    assert line.startswith("ready "), f"{module} did not start: {line!r} {proc.stderr.read()}"
    return proc


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    assert proc.wait(timeout=20) == 0


def test_robot_service_follows_commands_and_reports_what_ran(zenoh_endpoint, make_bus):
    proc = start("services.robot", zenoh_endpoint, "driver.type=sim", "control_hz=20")
    try:
        bus = make_bus()
        bus.wait_alive({"robot"}, timeout=30)
        states, applied = [], []
        cv = threading.Condition()
        pub = bus.publisher(topics.COMMAND)

        def on_state(msg, _rx):
            # answer every tick with a 5 mm step along +x
            pub.put(
                EefCommand(
                    header=Header(seq=msg.tick),
                    tick=msg.tick,
                    action=EefAction(dp=[0.005, 0, 0], drot=[0, 0, 0], gripper=0.0),
                )
            )
            with cv:
                states.append(msg)
                cv.notify_all()

        def on_applied(msg, _rx):
            with cv:
                applied.append(msg)
                cv.notify_all()

        bus.subscribe(topics.ROBOT_STATE, on_state)
        bus.subscribe(topics.APPLIED_ACTION, on_applied)
        with cv:
            assert cv.wait_for(lambda: len(states) >= 30, timeout=30)
        ticks = [s.tick for s in states]
        assert ticks == list(range(ticks[0], ticks[0] + len(ticks)))  # no tick skipped
        moved = [a for a in applied if not a.stale]
        assert len(moved) >= 20
        x = np.array([s.eef_pos[0] for s in states])
        assert x[-1] - x[5] > 0.05  # the arm really went along +x
    finally:
        stop(proc)


def test_applied_actions_are_what_ran_after_the_safety_layer(zenoh_endpoint, make_bus):
    # A command of 20 cm in one tick is 4 m/s: the arm moves 3 cm (0.6 m/s at 20 Hz) and
    # robot/applied says so, with the limit that changed it; a recorded demo never claims more.
    proc = start("services.robot", zenoh_endpoint, "driver.type=sim", "control_hz=20")
    try:
        bus = make_bus()
        bus.wait_alive({"robot"}, timeout=30)
        applied = []
        cv = threading.Condition()
        pub = bus.publisher(topics.COMMAND)
        bus.subscribe(
            topics.ROBOT_STATE,
            lambda msg, _rx: pub.put(
                EefCommand(
                    header=Header(seq=msg.tick),
                    tick=msg.tick,
                    action=EefAction(dp=[0.2, 0, 0], drot=[0, 0, 0], gripper=0.0),
                )
            ),
        )

        def on_applied(msg, _rx):
            with cv:
                applied.append(msg)
                cv.notify_all()

        bus.subscribe(topics.APPLIED_ACTION, on_applied)
        with cv:
            assert cv.wait_for(lambda: sum(not a.stale for a in applied) >= 5, timeout=30)
        with cv:
            first = [a for a in applied if not a.stale][:5]  # from home: 15 cm along +x, inside the box
        for a in first:
            assert list(a.limits) == ["speed"]
            assert np.allclose(a.action.dp, [0.6 / 20, 0.0, 0.0], atol=1e-12)
    finally:
        stop(proc)


def test_camera_service_publishes_frames_matching_its_calibration(zenoh_endpoint, make_bus):
    proc = start("services.camera", zenoh_endpoint, "rig=three15", "fps=10", "width=64", "height=48")
    try:
        bus = make_bus()
        got: dict[str, list] = {"image": [], "calibration": [], "pose": []}
        cv = threading.Condition()

        def keep(kind):
            def on_msg(msg, _rx):
                with cv:
                    got[kind].append(msg)
                    cv.notify_all()

            return on_msg

        bus.subscribe(topics.camera_image("FL"), keep("image"))
        bus.subscribe(topics.camera_calibration("FL"), keep("calibration"))
        bus.subscribe(topics.camera_pose("FL"), keep("pose"))
        with cv:
            assert cv.wait_for(lambda: len(got["image"]) >= 5 and got["calibration"] and got["pose"], timeout=30)
        rgb = decode_jpeg(got["image"][0].data)
        assert rgb.shape == (48, 64, 3)
        stamps = [m.timestamp.ToNanoseconds() for m in got["image"]]
        assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
        cam, K = Camera.from_msgs(got["calibration"][0], got["pose"][0])
        ref = load_rig("three15").cameras["FL"]
        assert np.allclose(cam.R_wc, ref.R_wc, atol=1e-9) and np.allclose(K, ref.K(64, 48))
    finally:
        stop(proc)


def test_real_driver_is_chosen_by_import_path():
    from sim.backends import SimRobot

    cfg = RobotConfig.model_validate({"driver": {"type": "sim.backends:SimRobot"}})
    assert ROBOT_DRIVERS.resolve(cfg.driver)[0] is SimRobot
    assert issubclass(SimRobot, RobotDriver)
    with pytest.raises(ValueError, match="package.module:ClassName"):
        RobotConfig.model_validate({"driver": {"type": "no_colon_here"}})
    with pytest.raises(ConfigError, match="cannot be imported"):
        ROBOT_DRIVERS.resolve(RobotConfig.model_validate({"driver": {"type": "mylab.missing:Arm"}}).driver)
    with pytest.raises(ConfigError, match="not a RobotDriver"):
        ROBOT_DRIVERS.resolve(RobotConfig.model_validate({"driver": {"type": "services.core.rig:Rig"}}).driver)


def test_bad_config_is_one_clear_line():
    proc = subprocess.run(
        [sys.executable, "-m", "services.robot", "--set", "control_hz=-1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "control_hz" in proc.stderr and "Traceback" not in proc.stderr


def real_session(tmp_path: Path, section: str, driver: dict) -> Path:
    """deploy/real.yaml (world: real, its bus and sections) with one service's driver replaced."""
    cfg = yaml.safe_load((ROOT / "deploy" / "real.yaml").read_text())
    cfg[section]["driver"] = driver
    path = tmp_path / "real.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.parametrize(
    "module, section, driver",
    [
        ("services.teleop", "teleop", "scripted"),
        ("services.robot", "robot", "sim"),
        ("services.camera", "camera", "sim"),
    ],
)
def test_a_sim_only_driver_is_refused_in_a_real_session_at_start_up(module, section, driver, tmp_path):
    # deploy/real.yaml says world: real; the scripted expert would wait for a task state no real
    # robot publishes and leave every tick stale, a sim camera would record a rendered scene.
    config = real_session(tmp_path, section, {"type": driver})
    proc = subprocess.run(
        [sys.executable, "-m", module, "--config", str(config)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert f"driver '{driver}' only works in sim (world: real)" in proc.stderr and "Traceback" not in proc.stderr
    if driver == "scripted":
        assert "task state" in proc.stderr


def test_a_driver_that_cannot_be_imported_is_one_line_before_any_connection(tmp_path):
    config = real_session(tmp_path, "teleop", {"type": "mylab.teleop:MyDevice"})
    proc = subprocess.run(
        [sys.executable, "-m", "services.teleop", "--config", str(config)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == "error: module 'mylab.teleop' cannot be imported: No module named 'mylab'"


def test_robot_states_name_the_episode_the_recorder_records(zenoh_endpoint, make_bus, tmp_path):
    """(on hardware the states named no episode at all: a policy teleop could not tell an episode
    from an operator resetting the scene between two, and drove the arm through both)"""
    from services.pb.episode_pb2 import (
        EPISODE_COMMAND_DISCARD,
        EPISODE_COMMAND_START,
        EPISODE_COMMAND_STOP,
        EpisodeReply,
        EpisodeRequest,
    )
    from services.recorder.config import RecorderConfig
    from services.recorder.service import Recorder

    proc = None
    rec_bus, bus = make_bus(), make_bus()
    try:
        with Recorder(RecorderConfig(bus=rec_bus.cfg, out_dir=tmp_path), rec_bus):
            named: list[str] = []
            bus.subscribe(topics.ROBOT_STATE, lambda msg, _rx: named.append(msg.episode_id))

            def control(command: int, **fields) -> EpisodeReply:
                req = EpisodeRequest(command=command, **fields).SerializeToString()
                return EpisodeReply.FromString(bus.query(topics.EPISODE_CONTROL, req, timeout=15))

            bus.wait_alive({"recorder"}, timeout=30)
            # an episode under way when the robot service starts (a restart): it names it within a second
            assert control(EPISODE_COMMAND_START, episode_id="ep-1", task="lift", control_hz=20).ok
            proc = start("services.robot", zenoh_endpoint, "driver.type=sim", "control_hz=20")
            wait_for(lambda: named and named[-1] == "ep-1", what="states naming the episode under way")
            assert control(EPISODE_COMMAND_STOP, success=True).ok
            wait_for(lambda: named[-1] == "", what="states naming none once it closed")
            assert control(EPISODE_COMMAND_START, episode_id="ep-2", task="lift", control_hz=20).ok
            wait_for(lambda: named[-1] == "ep-2", what="states naming the next episode")
            assert control(EPISODE_COMMAND_DISCARD).ok
            wait_for(lambda: named[-1] == "", what="states naming none once it was discarded")
    finally:
        if proc is not None:
            stop(proc)
