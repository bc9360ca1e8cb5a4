"""The Universal Robots driver (``services/robot/ur.py``) through the real safety layer, control
loop, robot service, recorder and a Zenoh loopback router.

ur-rtde talks to a UR controller and has no simulator we can run here, so the controller is an
in-test fake of the external SDK's two Python modules, ``rtde_control`` and ``rtde_receive``
(installed in ``sys.modules``; ur-rtde itself is not needed). It follows ur-rtde's documented
behaviour where the driver depends on it: ``servoL`` targets become the TCP pose (the fake arm
reaches each target in its period), ``servoL`` returns False in a protective stop, the receive
interface keeps its last sample and says ``isConnected() == False`` once the link drops, and a
control call on a dropped link raises (the real one would block reconnecting first). Nothing of
this project is faked. The Robotiq gripper is tested against a tiny TCP server speaking the
URCap's ASCII protocol.
"""

from __future__ import annotations

import logging
import socket
import sys
import threading
import time
import types
from contextlib import ExitStack

import numpy as np
import pytest
from polling import wait_for

from services.core import topics
from services.core.config import ConfigError
from services.core.geometry import matrix_to_rotvec, rot_z, rotvec_to_matrix
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import EefAction, EefCommand
from services.pb.episode_pb2 import EPISODE_COMMAND_START, EPISODE_COMMAND_STOP, EpisodeReply, EpisodeRequest
from services.recorder.config import RecorderConfig
from services.recorder.reader import read_episode
from services.recorder.service import Recorder
from services.robot.config import (
    ROBOT_DRIVERS,
    RobotConfig,
    RobotiqGripperConfig,
    URRobotConfig,
)
from services.robot.gripper import RobotiqGripper
from services.robot.safety import Safety, SafetyConfig
from services.robot.service import RobotService, make_driver

TOOL_DOWN = [0.0, np.pi, 0.0]  # rotation vector of a gripper pointing down (x kept, y and z flipped)


# -- the fake controller and the fake ur-rtde modules ------------------------------------------------


class FakeArm:
    """One UR controller as the fake ur-rtde interfaces of its host see it."""

    def __init__(self, pose):
        self.lock = threading.Lock()
        self.pose = [float(v) for v in pose]
        self.q = [0.0, -1.57, 1.57, -1.57, -1.57, 0.0]
        self.link = True  # the network between us and the controller
        self.protective = False
        self.program_running = True  # ur-rtde's control script
        self.held = False  # held back (pushing on the table): servoL moves the target, not the arm
        self.calls: list[tuple[str, tuple]] = []  # (interface.method, args), in order
        self.violations: list[str] = []  # calls the driver must never make
        self.interfaces: list[_Interface] = []

    def record(self, name: str, *args) -> None:
        with self.lock:
            self.calls.append((name, args))

    def names(self) -> list[str]:
        with self.lock:
            return [name for name, _ in self.calls]

    def count(self, name: str) -> int:
        return self.names().count(name)

    def servo_targets(self) -> list[list[float]]:
        with self.lock:
            return [list(args[0]) for name, args in self.calls if name == "control.servoL"]

    def protective_stop(self) -> None:
        with self.lock:
            self.protective = True
            self.program_running = False  # a protective stop ends the running program

    def clear_protective_stop(self) -> None:
        with self.lock:
            self.protective = False

    def drop(self) -> None:
        """The link goes down: both interfaces stay disconnected until they reconnect."""
        with self.lock:
            self.link = False
            for iface in self.interfaces:
                iface._open = False


ARMS: dict[str, FakeArm] = {}


class _Interface:
    kind = ""

    def __init__(self, hostname: str, frequency: float = -1.0, *rest):
        if hostname not in ARMS or not ARMS[hostname].link:
            raise RuntimeError(f"Could not connect to {hostname}: connection refused")
        self.arm = ARMS[hostname]
        self.frequency = frequency
        self._open = True
        self.arm.interfaces.append(self)
        self.arm.record(f"{self.kind}.__init__", hostname, frequency)

    def isConnected(self) -> bool:
        return self._open and self.arm.link

    def reconnect(self) -> bool:
        self.arm.record(f"{self.kind}.reconnect")
        if not self.arm.link:
            raise RuntimeError("connection refused")
        self._open = True
        return True

    def disconnect(self) -> None:
        self.arm.record(f"{self.kind}.disconnect")
        self._open = False


class FakeReceive(_Interface):
    kind = "receive"

    def __init__(self, hostname, frequency=-1.0, *rest):
        super().__init__(hostname, frequency, *rest)
        self._sample = self._fresh()

    def _fresh(self) -> dict:
        with self.arm.lock:
            return {"pose": list(self.arm.pose), "q": list(self.arm.q), "protective": self.arm.protective}

    def _latest(self) -> dict:
        if self.isConnected():  # a dropped link leaves the last sample in place
            self._sample = self._fresh()
        return self._sample

    def getActualTCPPose(self):
        return self._latest()["pose"]

    def getActualQ(self):
        return self._latest()["q"]

    def getActualQd(self):
        return [0.0] * 6

    def isProtectiveStopped(self) -> bool:
        return self._latest()["protective"]

    def isEmergencyStopped(self) -> bool:
        return False

    def getSafetyMode(self) -> int:
        return 3 if self._latest()["protective"] else 1

    def getRobotMode(self) -> int:
        return 7


class FakeControl(_Interface):
    kind = "control"

    def _call(self, name: str, *args) -> None:
        self.arm.record(f"control.{name}", *args)
        if not self.isConnected():
            self.arm.violations.append(f"{name} on a dropped link")
            raise RuntimeError("RTDEControlInterface: Lost connection to robot...")

    def servoL(self, pose, speed, acceleration, time, lookahead_time, gain) -> bool:
        self._call("servoL", list(pose), speed, acceleration, time, lookahead_time, gain)
        with self.arm.lock:
            if self.arm.protective or not self.arm.program_running:
                return False
            if not self.arm.held:
                self.arm.pose = [float(v) for v in pose]  # the arm reaches the target within `time`
        return True

    def servoStop(self, a=10.0) -> bool:
        self._call("servoStop", a)
        return True

    def stopScript(self) -> None:
        self._call("stopScript")
        with self.arm.lock:
            self.arm.program_running = False

    def isProgramRunning(self) -> bool:
        with self.arm.lock:
            return self.arm.program_running

    def reuploadScript(self) -> bool:
        self._call("reuploadScript")
        with self.arm.lock:
            self.arm.program_running = not self.arm.protective
            return self.arm.program_running

    def setTcp(self, tcp_offset) -> bool:
        self._call("setTcp", list(tcp_offset))
        return True


@pytest.fixture
def fake_ur(monkeypatch):
    """Install the fake ur-rtde modules; returns ``make(host, pose) -> FakeArm``."""
    control = types.ModuleType("rtde_control")
    control.RTDEControlInterface = FakeControl
    receive = types.ModuleType("rtde_receive")
    receive.RTDEReceiveInterface = FakeReceive
    monkeypatch.setitem(sys.modules, "rtde_control", control)
    monkeypatch.setitem(sys.modules, "rtde_receive", receive)

    def make(host: str = "ur-fake", pose=(0.45, 0.0, 0.25, *TOOL_DOWN)) -> FakeArm:
        ARMS[host] = FakeArm(pose)
        return ARMS[host]

    yield make
    ARMS.clear()


# -- a session: robot service (UR behind Safety and ControlLoop), recorder, a teleop -----------------


class Teleop:
    """Answers every robot state with ``self.action`` (None: answers nothing) and keeps what ran."""

    def __init__(self, bus):
        self.action: tuple[list[float], list[float], float] | None = None
        self.applied = []
        self.states = []
        self.cv = threading.Condition()
        self.pub = bus.publisher(topics.COMMAND)
        bus.subscribe(topics.ROBOT_STATE, self._on_state)
        bus.subscribe(topics.APPLIED_ACTION, self._on_applied)

    def _on_state(self, msg, _rx) -> None:
        action = self.action
        if action is not None:
            dp, drot, grip = action
            self.pub.put(
                EefCommand(
                    header=Header(stamp_ns=time.time_ns(), seq=msg.tick),
                    tick=msg.tick,
                    action=EefAction(dp=dp, drot=drot, gripper=grip),
                )
            )
        with self.cv:
            self.states.append(msg)
            self.cv.notify_all()

    def _on_applied(self, msg, _rx) -> None:
        with self.cv:
            self.applied.append(msg)
            self.cv.notify_all()

    def wait(self, pred, timeout: float = 10.0, what: str = "applied actions"):
        with self.cv:
            assert self.cv.wait_for(lambda: pred(self.applied), timeout=timeout), f"timed out waiting for {what}"
            return list(self.applied)


class Session:
    def __init__(self, stack: ExitStack, make_bus, bus_config, tmp_path, host: str, **safety):
        self.stack = stack
        self.cfg = RobotConfig(
            bus=bus_config,
            world="real",
            driver=URRobotConfig(host=host, reconnect_interval_s=0.1),
            safety=SafetyConfig(**safety),
            control_hz=20.0,
        )
        self.service = RobotService(self.cfg, make_bus(), make_driver(self.cfg))
        self.driver = self.service.robot.driver
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        rec_cfg = RecorderConfig(bus=bus_config, out_dir=tmp_path / "episodes", min_rate_fraction=0.0)
        self.recorder = stack.enter_context(Recorder(rec_cfg, make_bus()))
        self.bus = make_bus()
        self.teleop = Teleop(self.bus)

    def _run(self) -> None:
        with self.service:
            self.service.run(self.stop)

    def __enter__(self) -> Session:
        self.thread.start()
        self.bus.wait_alive({"recorder", "robot"}, timeout=10)
        return self

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=10)
        assert not self.thread.is_alive()

    def __exit__(self, *exc) -> None:
        self.close()

    def control(self, command: int, **fields) -> EpisodeReply:
        req = EpisodeRequest(command=command, **fields)
        return EpisodeReply.FromString(self.bus.query(topics.EPISODE_CONTROL, req.SerializeToString(), timeout=15))

    def start_episode(self, episode_id: str) -> None:
        reply = self.control(EPISODE_COMMAND_START, episode_id=episode_id, task="lift", rig="five15", control_hz=20.0)
        assert reply.ok, reply.error

    def stop_episode(self, episode_id: str):
        reply = self.control(EPISODE_COMMAND_STOP, episode_id=episode_id, success=False)
        assert reply.ok, reply.error
        return reply.meta


@pytest.fixture
def session(fake_ur, make_bus, bus_config, tmp_path):
    sessions: list[Session] = []
    with ExitStack() as stack:

        def make(host: str = "ur-fake", **safety) -> Session:
            s = Session(stack, make_bus, bus_config, tmp_path, host, **safety)
            sessions.append(s)
            return s.__enter__()

        yield make
        for s in sessions:
            s.close()


# -- through the robot service ---------------------------------------------------------------------


def test_commands_arrive_clipped_to_the_workspace_box(fake_ur, session):
    arm = fake_ur(pose=(0.74, 0.0, 0.25, *TOOL_DOWN))  # 6 cm below the box's x limit (0.8)
    s = session()
    s.teleop.action = ([0.02, 0.0, 0.0], [0.0, 0.0, 0.05], 0.0)  # 2 cm and 0.05 rad about z per tick
    applied = s.teleop.wait(lambda a: sum(not x.stale for x in a) >= 8, what="8 executed commands")
    ran = [a for a in applied if not a.stale]
    assert any("workspace" in a.limits for a in ran) and not any(a.fault for a in applied)
    targets = np.array(arm.servo_targets())
    assert len(targets) >= 8
    assert targets[:, 0].max() == pytest.approx(0.8, abs=1e-12)  # stopped at the wall, never past it
    assert np.all(targets[:, 0] <= 0.8 + 1e-12)
    assert np.allclose(targets[:, 1:3], [0.0, 0.25], atol=1e-12)  # the other axes untouched
    # Each target's rotation is the last one turned 0.05 rad about base z (composing on the left).
    R = [rotvec_to_matrix(t[3:]) for t in targets]
    for prev, nxt in zip(R, R[1:]):
        assert np.allclose(nxt, rot_z(0.05) @ prev, atol=1e-9)
    x = [a.action.dp[0] for a in ran]
    assert sum(x) == pytest.approx(0.8 - 0.74, abs=1e-9)  # what ran adds up to the distance to the wall
    # every servoL carries the configured servo parameters, one control period each
    name, args = next(c for c in arm.calls if c[0] == "control.servoL")
    assert args[3:] == (pytest.approx(1 / 20), 0.1, 300.0)


def test_a_command_timeout_stops_the_arm_and_commands_restart_it(fake_ur, session):
    arm = fake_ur()
    s = session(command_timeout_s=0.3)
    s.teleop.action = ([0.0, 0.01, 0.0], [0.0, 0.0, 0.0], 0.0)
    s.teleop.wait(lambda a: sum(not x.stale for x in a) >= 3, what="commands executed")
    stops = arm.count("control.servoStop")  # (a slow start-up may have stopped it once already)
    s.teleop.action = None  # the operator lets go
    wait_for(lambda: arm.count("control.servoStop") > stops, what="servoStop after the command timeout")
    servos = arm.count("control.servoL")
    n = len(s.teleop.applied)
    s.teleop.wait(lambda a: len(a) >= n + 4, what="held ticks")
    assert arm.count("control.servoL") == servos  # stopped: holding sends nothing
    assert arm.count("control.servoStop") == stops + 1 and s.service.robot.stopped
    stopped_at = list(arm.pose)
    s.teleop.action = ([0.0, 0.01, 0.0], [0.0, 0.0, 0.0], 0.0)
    wait_for(lambda: arm.count("control.servoL") > servos, what="servoing again")
    first = arm.servo_targets()[servos]
    assert first[1] == pytest.approx(stopped_at[1] + 0.01)  # from where the arm stood, not an old target


def test_a_protective_stop_is_reported_stops_the_arm_and_flags_the_episode(fake_ur, session, caplog):
    caplog.set_level(logging.WARNING)
    arm = fake_ur()
    s = session()
    s.start_episode("ur-pstop")
    s.teleop.action = ([0.005, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0)
    s.teleop.wait(lambda a: sum(not x.stale for x in a) >= 3, what="commands executed")
    stops = arm.count("control.servoStop")
    arm.protective_stop()
    applied = s.teleop.wait(lambda a: sum(bool(x.fault) for x in a) >= 5, what="faulted ticks")
    fault = next(a.fault for a in applied if a.fault)
    assert fault.startswith("protective stop")
    servos = arm.count("control.servoL")
    assert arm.count("control.servoStop") == stops + 1  # stopped once, when it began
    faulted = [a for a in applied if a.fault]
    assert all(np.allclose(a.action.dp, 0) and not a.limits for a in faulted)  # what ran: a hold
    assert any("robot fault: protective stop" in r.message and r.levelname == "ERROR" for r in caplog.records)

    arm.clear_protective_stop()  # cleared on the pendant: the script is uploaded again, servoing resumes
    wait_for(lambda: arm.count("control.servoL") > servos, what="servoing after the stop was cleared")
    assert "control.reuploadScript" in arm.names()
    resumed = s.teleop.wait(lambda a: _executed_after_fault(a) >= 3, what="3 executed commands after the fault cleared")
    assert _executed_after_fault(resumed) >= 3
    meta = s.stop_episode("ur-pstop")
    ep = read_episode(meta.path)  # kept: every tick before, during and after the stop
    recorded = ep.messages("/robot/applied")
    n_fault = sum(bool(r.msg.fault) for r in recorded)
    assert n_fault >= 5 and _executed_after_fault([r.msg for r in recorded]) >= 1
    # A robot service ticks on between episodes: START and STOP may cut a tick between its two messages.
    assert abs(len(ep.messages("/robot/state")) - len(recorded)) <= 1
    flag = next(f for f in meta.flags if f.startswith("robot fault:"))
    assert flag == f"robot fault: {n_fault} ticks the arm was stopped: {fault} ({n_fault} ticks)"
    assert ep.flags == list(meta.flags)


def _executed_after_fault(applied) -> int:
    """Commands that ran after the last faulted tick (0 if there was no fault)."""
    last = max((i for i, a in enumerate(applied) if a.fault), default=None)
    return 0 if last is None else sum(not a.stale and not a.fault for a in applied[last + 1 :])


def test_a_dropped_connection_mid_episode_stops_the_arm_and_keeps_the_episode_flagged(fake_ur, session, caplog):
    caplog.set_level(logging.WARNING)
    arm = fake_ur()
    s = session()
    s.start_episode("ur-drop")
    s.teleop.action = ([0.005, 0.0, 0.0], [0.0, 0.0, 0.0], 1.0)
    before = s.teleop.wait(lambda a: sum(not x.stale for x in a) >= 3, what="commands executed")
    arm.drop()
    s.teleop.wait(lambda a: sum(bool(x.fault) for x in a) >= 5, what="faulted ticks")
    meta = s.stop_episode("ur-drop")
    s.close()  # the service closes the driver on the dropped link

    assert arm.violations == []  # nothing sent to a dropped control interface (ur-rtde would block)
    assert any(
        r.levelname == "ERROR" and "robot fault: connection to the UR controller at ur-fake lost" in r.message
        for r in caplog.records
    )
    flag = next(f for f in meta.flags if f.startswith("robot fault:"))
    assert "connection to the UR controller at ur-fake lost" in flag
    ep = read_episode(meta.path)
    states = ep.messages("/robot/state")
    assert len(states) >= len(before) and abs(len(states) - len(ep.messages("/robot/applied"))) <= 1
    # While disconnected the state is the last one read (the arm took at most one more step after it).
    faulted = {r.msg.tick for r in ep.messages("/robot/applied") if r.msg.fault}
    held = {tuple(st.msg.eef_pos) for st in states if st.msg.tick in faulted}
    assert len(faulted) >= 3 and len(held) == 1
    assert np.allclose(next(iter(held)), arm.pose[:3], atol=0.005 + 1e-9)
    names = arm.names()
    assert "control.disconnect" in names and "receive.disconnect" in names
    assert names.count("receive.reconnect") >= 1  # it kept trying, without blocking the loop


# -- the driver on its own -------------------------------------------------------------------------


def test_close_stops_servoing_ends_the_script_and_disconnects(fake_ur):
    arm = fake_ur()
    cfg = URRobotConfig(host="ur-fake", tcp_offset=(0.0, 0.0, 0.15, 0.0, 0.0, 0.0), frequency=125.0)
    driver = ROBOT_DRIVERS.build(cfg, control_hz=20.0)
    assert ("control.setTcp", ([0.0, 0.0, 0.15, 0.0, 0.0, 0.0],)) in arm.calls
    assert ("receive.__init__", ("ur-fake", 125.0)) in arm.calls
    snap = driver.read()
    assert np.allclose(snap.eef_pos, [0.45, 0.0, 0.25]) and np.allclose(snap.eef_quat_wxyz, [0, 0, 1, 0])
    assert len(snap.joint_pos) == 6 and driver.fault() == ""
    del arm.calls[:]
    driver.close()
    assert arm.names() == ["control.servoStop", "control.stopScript", "control.disconnect", "receive.disconnect"]
    driver.close()  # twice is harmless
    assert len(arm.calls) == 4


def test_the_safety_layer_bounds_the_driver_target_not_just_the_measured_pose(fake_ur):
    # The arm lags its target on hardware; the box must hold for where it is going.
    arm = fake_ur(pose=(0.7, 0.0, 0.25, *TOOL_DOWN))
    driver = ROBOT_DRIVERS.build(URRobotConfig(host="ur-fake"), control_hz=20.0)
    with Safety(driver, SafetyConfig(), 20.0) as safe:
        safe.read()
        arm.pose[0] = 0.7  # pin the measured pose: the fake arm "lags" at 0.7 from here on
        step = np.array([0.025, 0.0, 0.0])
        for _ in range(6):
            safe.read()
            ran = safe.apply(_delta(step))
        assert driver.target_position()[0] == pytest.approx(0.8)
        assert ran.limits == ("workspace",) and ran.action.dp[0] == pytest.approx(0.0)


def test_an_arm_held_back_is_not_sent_ever_further_ahead_so_it_does_not_leap_when_it_comes_free(fake_ur, caplog):
    arm = fake_ur()
    driver = ROBOT_DRIVERS.build(URRobotConfig(host="ur-fake"), control_hz=20.0)
    start = matrix_to_rotvec(rotvec_to_matrix(TOOL_DOWN))
    with Safety(driver, SafetyConfig(), 20.0) as safe:
        safe.read()
        arm.held = True  # pushing on something: the commands go on, the arm stays at x = 0.45
        with caplog.at_level(logging.WARNING, logger="services.robot.ur"):
            for _ in range(10):
                safe.read()
                safe.apply(_delta([0.025, 0.0, 0.0], drot=[0.0, 0.0, 0.12]))
        target = arm.servo_targets()[-1]
        assert target[0] == pytest.approx(0.45 + 0.1)  # max_lead_m, not the 0.25 m commanded
        turned = rotvec_to_matrix(target[3:]) @ rotvec_to_matrix(start).T
        assert np.linalg.norm(matrix_to_rotvec(turned)) == pytest.approx(0.6)  # max_lead_rad, not 1.2
        assert len([r for r in caplog.records if "behind its servo target" in r.getMessage()]) == 1
        arm.held = False  # free: it goes to the bounded target (the fake at once), then on as commanded
        for x in (0.55, 0.575):
            safe.read()
            safe.apply(_delta([0.025, 0.0, 0.0]))
            assert arm.pose[0] == pytest.approx(x)


def test_after_a_dropped_link_comes_back_the_driver_reconnects_and_servos_from_the_measured_pose(fake_ur):
    arm = fake_ur()
    driver = ROBOT_DRIVERS.build(URRobotConfig(host="ur-fake", reconnect_interval_s=0.05), control_hz=20.0)
    with Safety(driver, SafetyConfig(), 20.0) as safe:
        safe.read()
        safe.apply(_delta([0.01, 0.0, 0.0]))
        arm.drop()
        safe.read()
        assert safe.apply(_delta([0.01, 0.0, 0.0])).fault == "connection to the UR controller at ur-fake lost"
        arm.pose[1] = 0.05  # moved by hand meanwhile
        arm.link = True
        wait_for(lambda: driver.fault() == "", what="the fault to clear after reconnecting")
        assert {"receive.reconnect", "control.reconnect"} <= set(arm.names())
        safe.read()
        ran = safe.apply(_delta([0.01, 0.0, 0.0]))
        assert ran.fault == "" and arm.servo_targets()[-1][:3] == pytest.approx([0.47, 0.05, 0.25])
        assert arm.violations == []


def test_missing_ur_rtde_is_one_config_error_naming_the_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "rtde_control", None)  # what an absent package looks like to import
    with pytest.raises(ConfigError, match="pip install ur-rtde"):
        ROBOT_DRIVERS.build(URRobotConfig(host="10.0.0.2"), control_hz=20.0)


def test_an_unreachable_controller_is_a_connection_error(fake_ur):
    with pytest.raises(ConnectionError, match="cannot connect to the UR controller at nowhere"):
        ROBOT_DRIVERS.build(URRobotConfig(host="nowhere"), control_hz=20.0)


def test_the_config_is_typed_and_strict():
    cfg = RobotConfig.model_validate(
        {"world": "real", "driver": {"type": "ur", "host": "10.0.0.2", "gripper": {"type": "robotiq", "force": 50}}}
    )
    assert isinstance(cfg.driver, URRobotConfig) and isinstance(cfg.driver.gripper, RobotiqGripperConfig)
    assert cfg.driver.gripper.port == 63352 and cfg.driver.lookahead_time == 0.1
    with pytest.raises(ValueError, match="lookahead_time"):
        RobotConfig.model_validate({"driver": {"type": "ur", "host": "h", "lookahead_time": 0.5}})
    with pytest.raises(ValueError, match="extra"):
        RobotConfig.model_validate({"driver": {"type": "ur", "host": "h", "ip": "h"}})
    with pytest.raises(ValueError, match="host"):
        RobotConfig.model_validate({"driver": {"type": "ur"}})


# -- the Robotiq gripper over its URCap socket -----------------------------------------------------


class RobotiqServer:
    """A Robotiq URCap socket on loopback: ``SET VAR n ...`` -> ``ack``, ``GET VAR`` -> ``VAR n``."""

    def __init__(self, sta: int = 0):
        self.vars = {"ACT": 0, "STA": sta, "GTO": 0, "POS": 0, "SPE": 0, "FOR": 0, "PRE": 0}
        self.lines: list[str] = []
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            threading.Thread(target=self._client, args=(conn,), daemon=True).start()

    def _client(self, conn: socket.socket) -> None:
        buf = b""
        with conn:
            while True:
                try:
                    data = conn.recv(1024)
                except OSError:
                    return
                if not data:
                    return
                buf += data
                while b"\n" in buf:
                    line, _, buf = buf.partition(b"\n")
                    conn.sendall(self._answer(line.decode().strip()).encode() + b"\n")

    def _answer(self, line: str) -> str:
        self.lines.append(line)
        words = line.split()
        if words[0] == "GET":
            return f"{words[1]} {self.vars[words[1]]}"
        for var, value in zip(words[1::2], words[2::2]):
            self.vars[var] = int(value)
        if self.vars["ACT"] == 1:
            self.vars["STA"] = 3
        if self.vars["GTO"] == 1:
            self.vars["PRE"] = self.vars["POS"]
        return "ack"

    def close(self) -> None:
        self.sock.close()
        for conn in self.conns:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass


@pytest.fixture
def robotiq():
    server = RobotiqServer()
    yield server
    server.close()


def test_robotiq_activates_moves_and_reads_over_its_socket(robotiq):
    cfg = RobotiqGripperConfig(port=robotiq.port, speed=200, force=60)
    gripper = RobotiqGripper.from_config(cfg, arm_host="127.0.0.1")
    try:
        assert robotiq.lines[:3] == ["GET STA", "SET ACT 1", "GET STA"]
        assert robotiq.lines[3] == "SET GTO 1 SPE 200 FOR 60"
        gripper.move(0.5)
        assert robotiq.lines[-1] == "SET POS 128 SPE 200 FOR 60 GTO 1"
        assert gripper.position() == pytest.approx(128 / 255) and robotiq.lines[-1] == "GET POS"
        # the position it holds is not sent again (before: a SET, a round trip, every such tick)
        sent = len(robotiq.lines)
        gripper.move(0.5)
        gripper.move(0.501)  # (127.8: POS 128)
        assert len(robotiq.lines) == sent
        gripper.move(7.0)  # clamped to closed
        assert robotiq.vars["POS"] == 255 and len(robotiq.lines) == sent + 1
        # a new connection sends it again
        gripper.reconnect()
        gripper.move(1.0)
        assert robotiq.lines[-1] == "SET POS 255 SPE 200 FOR 60 GTO 1"
    finally:
        gripper.close()


def test_a_gripper_that_goes_away_is_a_fault_that_stops_the_arm(fake_ur, robotiq):
    arm = fake_ur(host="127.0.0.1")
    cfg = URRobotConfig(host="127.0.0.1", gripper={"type": "robotiq", "port": robotiq.port}, reconnect_interval_s=60)
    driver = ROBOT_DRIVERS.build(cfg, control_hz=20.0)
    with Safety(driver, SafetyConfig(), 20.0) as safe:
        safe.read()
        safe.apply(_delta(np.array([0.01, 0.0, 0.0]), gripper=1.0))
        assert robotiq.vars["POS"] == 255 and safe.read().gripper == pytest.approx(1.0)
        robotiq.close()  # unplugged
        safe.read()
        ran = safe.apply(_delta(np.array([0.01, 0.0, 0.0]), gripper=0.0))
        assert ran.fault.startswith("gripper unreachable") and safe.faults == 1
        assert arm.count("control.servoStop") == 1 and arm.count("control.servoL") == 1


def test_no_gripper_is_the_default_and_reports_the_command_back(fake_ur):
    fake_ur()
    driver = ROBOT_DRIVERS.build(URRobotConfig(host="ur-fake"), control_hz=20.0)
    driver.apply(_delta(np.zeros(3), gripper=0.7))
    assert driver.read().gripper == pytest.approx(0.7)
    driver.close()


def _delta(dp, drot=(0.0, 0.0, 0.0), gripper: float = 0.0):
    from services.core.robot_types import EefDelta

    return EefDelta(np.asarray(dp, dtype=np.float64), np.asarray(drot, dtype=np.float64), float(gripper))


def test_rotation_targets_round_trip_through_the_fake(fake_ur):
    # The pose the driver reports after a rotation is the rotation vector the controller was sent.
    arm = fake_ur()
    # (a quarter turn in one step, past the default lead of 0.6 rad: the lead is not what is tested)
    driver = ROBOT_DRIVERS.build(URRobotConfig(host="ur-fake", max_lead_rad=2.0), control_hz=20.0)
    driver.read()
    driver.apply(_delta(np.zeros(3), drot=(0.0, 0.0, np.pi / 2)))
    sent = arm.servo_targets()[-1]
    expected = rot_z(np.pi / 2) @ rotvec_to_matrix(TOOL_DOWN)
    assert np.allclose(rotvec_to_matrix(sent[3:]), expected, atol=1e-12)
    assert np.allclose(matrix_to_rotvec(expected), sent[3:], atol=1e-9) or np.allclose(
        matrix_to_rotvec(expected), -np.asarray(sent[3:]), atol=1e-9
    )
    driver.close()


def test_viewscale_check_reports_a_ready_arm_a_stopped_one_and_one_it_cannot_reach(fake_ur):
    """The robot part of `viewscale check`, on the UR driver: read, never moved, closed after."""
    from services.robot.config import RobotConfig
    from services.session.check import robot_findings

    arm = fake_ur()
    cfg = RobotConfig(world="real", driver=URRobotConfig(host="ur-fake"))
    [ok] = robot_findings(cfg)
    assert ok.ok and "EEF at (0.450, 0.000, 0.250) m" in ok.text and "6 joints" in ok.text, ok.text
    assert arm.count("control.servoL") == 0 and arm.names()[-1] == "receive.disconnect"

    arm.protective_stop()
    [stopped] = robot_findings(cfg)
    assert not stopped.ok and "cannot move" in stopped.text and "protective stop" in stopped.text, stopped.text

    [unreachable] = robot_findings(RobotConfig(world="real", driver=URRobotConfig(host="ur-nowhere")))
    assert not unreachable.ok and "cannot connect" in unreachable.text and "ur-nowhere" in unreachable.text


def test_a_teleop_that_sends_bad_commands_every_tick_is_logged_once_a_while(fake_ur, session, caplog):
    """Commands the robot service rejects (a step over 1 m), one a tick: each is counted and the arm
    holds, and the log says it once, then once every 5 s (before: a line per command, 20 a second)."""
    fake_ur()
    s = session()
    with caplog.at_level("WARNING", logger="services.robot.loop"):
        s.teleop.action = ([1.5, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0)
        n0 = len(s.teleop.applied)
        ran = s.teleop.wait(lambda a: len(a) >= n0 + 30, what="30 ticks")
        assert all(a.stale for a in ran[n0 + 2 :])  # held still: the command was not used
        assert s.service.loop.rejected["invalid"] >= 28
    said = [r.getMessage() for r in caplog.records if "rejected command" in r.getMessage()]
    assert 1 <= len(said) <= 2 and "1.5" in said[0], said
