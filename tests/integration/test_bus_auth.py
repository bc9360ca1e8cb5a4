"""The authenticated, authorised bus on real Zenoh: a router process with deploy/zenoh/router-acl.json5
and fresh credentials, client sessions per service user, a real recorder.

What zenoh does, and what these tests pin down: the router refuses a session whose user and password
are not in its users file (the client's open times out; a peer opens but stays alone), and drops,
silently, every message a user's rules do not allow. A dropped put is observed as a put that never
reaches a subscriber while a put sent after it, by the same session over the same link, does.
"""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from polling import wait_for

from services.calibration.charuco import CalibrationError
from services.core import topics
from services.core.bus import Bus, BusConfig, Received, free_tcp_port
from services.core.tensors import compressed_image
from services.pb.episode_pb2 import (
    EPISODE_COMMAND_START,
    EPISODE_COMMAND_STATUS,
    EPISODE_COMMAND_STOP,
    EpisodeReply,
    EpisodeRequest,
)
from services.pb.sensors_pb2 import RobotState, TaskState
from services.recorder.config import RecorderConfig
from services.recorder.service import Recorder
from services.router.credentials import USERS_FILE, password_path, write_credentials

REPO = Path(__file__).resolve().parents[2]
ACL = REPO / "deploy" / "zenoh" / "router-acl.json5"
REFUSE_S = 1.0  # how long a refused client keeps retrying before its open fails


class SecureRouter:
    """``python -m services.router --users ... --acl deploy/zenoh/router-acl.json5`` on a free port."""

    def __init__(self, secrets: Path, log: Path):
        self.secrets = secrets
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        cmd = [sys.executable, "-m", "services.router", "--listen", self.endpoint]
        cmd += ["--users", str(secrets / USERS_FILE), "--acl", str(ACL)]
        self.log = log
        self._log_file = open(log, "w")
        self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=self._log_file, text=True)
        lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x) for x in self.proc.stdout], daemon=True).start()
        try:
            line = lines.get(timeout=30)
        except queue.Empty:
            self.close()
            raise AssertionError(f"router not ready in 30s; log:\n{log.read_text()}") from None
        assert line.startswith("ready router"), f"{line!r}; log:\n{log.read_text()}"

    def config(self, user: str | None = None, **fields) -> BusConfig:
        creds = {"user": user, "password_file": password_path(self.secrets, user)} if user else {}
        return BusConfig(**({"mode": "client", "connect": [self.endpoint]} | creds | fields))

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._log_file.close()


@pytest.fixture(scope="module")
def secure(tmp_path_factory):
    root = tmp_path_factory.mktemp("auth")
    write_credentials(root / "secrets")
    hub = SecureRouter(root / "secrets", root / "router.log")
    yield hub
    hub.close()


@pytest.fixture
def open_bus(secure):
    opened: list[Bus] = []

    def _open(user: str | None = None, **fields) -> Bus:
        bus = Bus(secure.config(user, **fields))
        opened.append(bus)
        return bus

    yield _open
    for bus in reversed(opened):
        bus.close()


class Heard:
    """Every sample a subscriber receives, by key."""

    def __init__(self, bus: Bus, key: str):
        self.samples: list[Received] = []
        bus.subscribe_raw(key, self.samples.append)

    def keys(self) -> list[str]:
        return [s.key for s in self.samples]


def status_request() -> bytes:
    return EpisodeRequest(command=EPISODE_COMMAND_STATUS).SerializeToString()


def robot_state(tick: int) -> RobotState:
    state = RobotState(tick=tick, eef_pos=[0.4, 0.0, 0.2], eef_quat_wxyz=[1, 0, 0, 0])
    state.header.stamp_ns, state.header.seq = time.time_ns(), tick
    return state


def test_a_client_without_valid_credentials_is_refused(secure, open_bus, tmp_path):
    with pytest.raises(ConnectionError, match="may require a user and password"):
        open_bus(connect_timeout_s=REFUSE_S)
    for user, password in [("camera", "not-the-password"), ("stranger", "whatever")]:
        path = tmp_path / f"{user}.password"
        path.write_text(password + "\n")
        cfg = BusConfig(
            mode="client", connect=[secure.endpoint], user=user, password_file=path, connect_timeout_s=REFUSE_S
        )
        with pytest.raises(ConnectionError, match=rf"refused user '{user}': wrong password in {path}"):
            Bus(cfg)
    assert open_bus("camera").session.info.routers_zid(), "the right password opens a session"


def test_a_peer_without_credentials_cannot_publish_into_the_session_or_query_the_recorder(secure, open_bus, tmp_path):
    recorder_bus = open_bus("recorder")
    with Recorder(RecorderConfig(bus=recorder_bus.cfg, out_dir=tmp_path / "episodes"), recorder_bus):
        session = open_bus("session")
        heard = Heard(session, topics.TASK_STATE.key)  # the session follows the sim's task state
        session.wait_alive(["recorder"], timeout=10)

        # A peer does not give up when the router refuses it: it opens, alone.
        intruder = open_bus(mode="peer", connect_timeout_s=REFUSE_S)
        assert not intruder.session.info.routers_zid() and not intruder.session.info.peers_zid()
        intruder.publisher(topics.TASK_STATE).put(TaskState(tick=666))
        with pytest.raises(TimeoutError):
            intruder.query(topics.EPISODE_CONTROL, status_request(), timeout=1.0)
        assert "recorder" not in intruder.alive(timeout=0.5)

        # Positive controls: the sim's task state reaches the session, the recorder answers it.
        open_bus("sim").publisher(topics.TASK_STATE).put(TaskState(tick=1))
        wait_for(lambda: heard.samples, what="the sim's task state")
        assert [TaskState.FromString(s.payload).tick for s in heard.samples] == [1]
        reply = EpisodeReply.FromString(session.query(topics.EPISODE_CONTROL, status_request(), timeout=10))
        assert reply.ok and not reply.recording


def test_an_authenticated_camera_publishes_camera_keys_but_not_the_robots(open_bus):
    listener = open_bus("recorder")  # the one user that hears every key
    heard = Heard(listener, "**")
    camera = open_bus("camera")
    fake_state = camera.publisher(topics.ROBOT_STATE)
    image = camera.publisher(topics.camera_image("F"))
    frame = np.zeros((8, 8, 3), dtype=np.uint8)
    camera.announce("camera")
    camera.announce("robot")  # posing as the robot service

    for tick in range(3):
        # Same session, same link, same priority: zenoh delivers in order, so once the frame sent
        # after the state has arrived, a state the router forwarded would have arrived before it.
        fake_state.put(robot_state(tick))
        image.put(compressed_image(frame, time.time_ns(), "F"))
        wait_for(lambda n=tick + 1: heard.keys().count("camera/F/image") == n, what=f"frame {tick}")
    assert heard.keys() == ["camera/F/image"] * 3

    # The same key from its rightful publisher does arrive.
    open_bus("sim").publisher(topics.ROBOT_STATE).put(robot_state(7))
    wait_for(lambda: "robot/state" in heard.keys(), what="the sim's robot state")
    assert RobotState.FromString(heard.samples[-1].payload).tick == 7

    # Liveliness is a key too: the camera's own token is seen, the one it forged is not.
    observer = open_bus("session")
    wait_for(lambda: "camera" in observer.alive(timeout=0.5), what="the camera's token")
    assert "robot" not in observer.alive(timeout=0.5)


def test_the_recorder_answers_the_session_and_nobody_else(open_bus, tmp_path):
    recorder_bus = open_bus("recorder")
    with Recorder(RecorderConfig(bus=recorder_bus.cfg, out_dir=tmp_path / "episodes"), recorder_bus):
        session = open_bus("session")
        session.wait_alive(["recorder"], timeout=10)
        reply = EpisodeReply.FromString(session.query(topics.EPISODE_CONTROL, status_request(), timeout=10))
        assert reply.ok and not reply.recording
        # Authenticated, but not allowed to query: the query is dropped at the router.
        camera = open_bus("camera")
        with pytest.raises(TimeoutError):
            camera.query(topics.EPISODE_CONTROL, status_request(), timeout=1.0)
        # The operator's CLI may (viewscale episode).
        operator = open_bus("operator")
        assert EpisodeReply.FromString(operator.query(topics.EPISODE_CONTROL, status_request(), timeout=10)).ok
        # So may the teleop: the episode keys of the SpaceMouse and the keyboard, the operator's hand
        # (before: dropped, and the keys logged 'no answer from the recorder')
        teleop = open_bus("teleop")
        assert EpisodeReply.FromString(teleop.query(topics.EPISODE_CONTROL, status_request(), timeout=10)).ok
        # The robot service hears the episodes start and close (its states name the one recorded)
        heard = Heard(open_bus("robot"), "recorder/episode")
        time.sleep(0.5)  # (the subscription reaches the router)
        for command in (EPISODE_COMMAND_START, EPISODE_COMMAND_STOP):
            req = EpisodeRequest(command=command, episode_id="auth-1", task="lift", control_hz=20)
            assert EpisodeReply.FromString(
                session.query(topics.EPISODE_CONTROL, req.SerializeToString(), timeout=10)
            ).ok
        wait_for(lambda: len(heard.samples) == 2, what="the start and the close on recorder/episode")


def test_the_operator_hears_the_arms_state_for_a_hand_eye_capture(open_bus):
    """``viewscale calibrate capture --kind hand_eye``, run as the operator, reads robot/state
    (before: the router dropped it, and capture said that no robot service was running)."""
    from services.calibration.capture import ArmPoses

    poses = ArmPoses(open_bus("operator"))
    robot = open_bus("robot")
    state = robot.publisher(topics.ROBOT_STATE)
    t0 = time.time_ns()
    for tick in range(50):  # until the operator's subscription has reached the router
        state.put(robot_state(tick))
        try:
            assert poses.after(t0, timeout_s=0.2).eef_pos[0] == pytest.approx(0.4)
            break
        except CalibrationError:
            continue
    else:
        pytest.fail("the operator never heard robot/state")


def test_the_teleop_hears_the_cameras_calibration_and_pose(open_bus):
    """The policy teleop compares each camera's published calibration and pose with the policy
    server's before it drives (before: the router let the teleop user hear only camera images, and
    on an authenticated bus the check saw nothing, so it never held a moved camera's policy)."""
    from services.core.rig import load_rig

    teleop = open_bus("teleop")
    heard = {"calibration": Heard(teleop, "camera/F/calibration"), "pose": Heard(teleop, "camera/F/pose")}
    camera = open_bus("camera")
    cam = load_rig("three15").cameras["F"]
    calibration, pose = camera.publisher(topics.camera_calibration("F")), camera.publisher(topics.camera_pose("F"))
    deadline = time.monotonic() + 10
    while not all(h.keys() for h in heard.values()):  # until the teleop's subscriptions reached the router
        assert time.monotonic() < deadline, {k: h.keys() for k, h in heard.items()}
        calibration.put(cam.calibration_msg(32, 32, time.time_ns()))
        pose.put(cam.pose_msg(time.time_ns()))
        time.sleep(0.1)
