"""The teleop devices through their real input paths.

Keyboard: a real pseudo-terminal (``os.openpty``); the driver opens the slave side by its path and
the test types key bytes into the master side, as a terminal emulator would.

SpaceMouse: HID report bytes in the device's own format go through pyspacemouse's real decoding
(``SpaceMouseDevice.read``) and our mapping. The HID handle under it is ``FakeHid``, an in-test
stand-in for ``easyhid.Device``: hidapi is an external SDK with no simulator, and the fake only
hands out the queued report bytes, as a non-blocking ``hid_read`` would. Some reports are a
SpaceMouse Compact capture posted in CloudCompare/CloudCompare#2339.

Episode keys: a real recorder on a real Zenoh loopback router, driven by the keys.
Time: an injectable clock where the test checks a deadman or a long press, so nothing waits for
wall time; every wait for the driver's thread polls with a deadline.
"""

from __future__ import annotations

import collections
import os
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from polling import wait_for

from services.core import topics
from services.core.bus import Bus, BusConfig
from services.core.config import ConfigError
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import EefCommand
from services.pb.sensors_pb2 import RobotState
from services.recorder.config import RecorderConfig
from services.recorder.control import episode_control, episode_request
from services.recorder.service import Recorder
from services.teleop.config import TELEOP_DRIVERS, KeyboardTeleopConfig, SpaceMouseTeleopConfig, TeleopConfig
from services.teleop.service import TeleopService

ROOT = Path(__file__).resolve().parents[2]
MAX_DP, MAX_DROT = 0.02, 0.1  # the defaults: the scripted expert's free-space step and rotation cap


class Clock:
    """Monotonic seconds that move only when the test says so."""

    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def robot_state(gripper: float = 0.0, tick: int = 0, episode: str = "") -> RobotState:
    return RobotState(
        header=Header(stamp_ns=time.time_ns(), seq=tick + 1),
        tick=tick,
        eef_pos=[0.45, 0.0, 0.25],
        eef_quat_wxyz=[0, 1, 0, 0],
        joint_pos=[0.0] * 6,
        joint_vel=[0.0] * 6,
        gripper=gripper,
        episode_id=episode,
    )


@pytest.fixture
def pty():
    """(master fd, slave fd, slave path) of a fresh pseudo-terminal."""
    master, slave = os.openpty()
    yield master, slave, os.ttyname(slave)
    os.close(master)
    os.close(slave)


class Typist:
    """Types into the master side and waits until the driver has read that many keys."""

    def __init__(self, master: int, driver):
        self.master = master
        self.driver = driver
        self.sent = 0

    def type(self, data: bytes, keys: int) -> None:
        os.write(self.master, data)
        self.sent += keys
        wait_for(lambda: self.driver.keys_read >= self.sent, 5, f"the driver to read {data!r}")


def test_keyboard_on_a_real_terminal(pty):
    master, slave, path = pty
    before = termios.tcgetattr(slave)
    assert before[3] & termios.ICANON and before[3] & termios.ECHO
    clock = Clock()
    cfg = KeyboardTeleopConfig(tty=path, speed=0.5, deadman_ms=600, repeat_ms=150)
    driver = TELEOP_DRIVERS.build(cfg, clock=clock)  # the registry's path, as the service builds it
    try:
        assert not driver.needs_task_state
        during = termios.tcgetattr(slave)
        assert not during[3] & termios.ICANON and not during[3] & termios.ECHO  # cbreak, no echo
        assert during[3] & termios.ISIG  # Ctrl-C still interrupts
        keys = Typist(master, driver)

        def act(gripper: float = 0.0):
            return driver.act(robot_state(gripper), None, {})

        idle = act()
        assert not idle.dp.any() and not idle.drot.any() and idle.gripper == 0.0

        keys.type(b"w", 1)  # one press: moves until the deadman window ends
        np.testing.assert_allclose(act().dp, [0.5 * MAX_DP, 0, 0])
        clock.t += 0.55
        np.testing.assert_allclose(act().dp, [0.5 * MAX_DP, 0, 0])
        clock.t += 0.1  # 650 ms without the key: hold still
        held = act()
        assert not held.dp.any() and not held.drot.any()

        # auto-repeat: once the key repeats, releasing it stops the arm after repeat_ms
        for _ in range(3):
            clock.t += 0.04
            keys.type(b"w", 1)
        clock.t += 0.14
        assert act().dp[0] > 0
        clock.t += 0.02
        assert not act().dp.any()

        # an arrow key (an escape sequence, split across two writes) with a rotation key: both held
        keys.type(b"\x1b[", 0)
        keys.type(b"Cj", 2)
        cmd = act()
        np.testing.assert_allclose(cmd.dp, [0, -0.5 * MAX_DP, 0])
        np.testing.assert_allclose(cmd.drot, [0, 0, 0.5 * MAX_DROT])

        keys.type(b"=", 1)  # faster: 0.5 x 1.5
        np.testing.assert_allclose(act().dp, [0, -0.75 * MAX_DP, 0])
        keys.type(b"=" * 3, 3)  # capped at full speed
        np.testing.assert_allclose(act().dp, [0, -MAX_DP, 0])
        assert np.linalg.norm(act().drot) == pytest.approx(MAX_DROT)

        # the gripper starts where the robot reports it and toggles with space
        assert act(gripper=0.0).gripper == 0.0
        keys.type(b" ", 1)
        assert act(gripper=0.0).gripper == 1.0
        assert act(gripper=0.3).gripper == 1.0  # the target stays while the fingers close
        keys.type(b" ", 1)
        assert act(gripper=1.0).gripper == 0.0
        driver.reset("", "next")  # a new episode: from the robot's gripper again, no key carried over
        cmd = act(gripper=0.9)
        assert cmd.gripper == 1.0 and not cmd.dp.any() and not cmd.drot.any()
    finally:
        driver.close()
    assert termios.tcgetattr(slave) == before  # the terminal is given back as it was
    driver.close()  # twice is harmless


def test_the_teleop_process_reads_a_terminal_and_gives_it_back_on_sigterm(zenoh_endpoint, pty):
    master, slave, path = pty
    before = termios.tcgetattr(slave)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.teleop",
            "--set",
            "bus.mode=client",
            "--set",
            f"bus.connect=[{zenoh_endpoint}]",
        ]
        + ["--set", "world=real", "--set", "driver.type=keyboard", "--set", f"driver.tty={path}"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().startswith("ready teleop keyboard"), proc.stderr.read()
        assert not termios.tcgetattr(slave)[3] & termios.ICANON
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    assert proc.returncode == 0, proc.stderr.read()
    assert termios.tcgetattr(slave) == before


def test_keyboard_needs_a_terminal(tmp_path):
    plain = tmp_path / "not-a-tty"
    plain.write_text("")
    with pytest.raises(ConfigError, match="is not a terminal"):
        TELEOP_DRIVERS.build(KeyboardTeleopConfig(tty=str(plain)))
    with pytest.raises(ConfigError, match="cannot open the terminal"):
        TELEOP_DRIVERS.build(KeyboardTeleopConfig(tty=str(tmp_path / "missing")))


# A terminal of its own, as a shell's: the helper leads a new session with a fresh pty as its
# controlling terminal, its group in the foreground, and runs the command there or as a background
# job (a process group of its own, as `cmd &` in an interactive shell makes it).
JOB = """
import fcntl, os, subprocess, sys, termios, time
master, slave = os.openpty()
fcntl.ioctl(slave, termios.TIOCSCTTY, 0)
background = sys.argv[1] == "background"
job = subprocess.Popen(sys.argv[2:], stdin=slave, process_group=0 if background else None)
deadline = time.monotonic() + 30
while job.poll() is None and time.monotonic() < deadline:
    with open(f"/proc/{job.pid}/stat") as f:
        if f.read().rsplit(") ", 1)[1].split()[0] == "T":
            job.kill()
            sys.exit("stopped by its terminal")
    time.sleep(0.05)
sys.exit(job.wait() if job.returncode is not None else "still running")
"""

OPEN_KEYBOARD = (
    "from services.teleop.config import KeyboardTeleopConfig\n"
    "from services.teleop.keyboard import KeyboardTeleop\n"
    "KeyboardTeleop(KeyboardTeleopConfig()).close()\n"
    "print('opened')"
)


def test_keyboard_started_in_the_background_of_its_terminal_says_so():
    """README's `... &` loop with the keyboard teleop: before, the terminal stopped the process
    (SIGTTOU, setting its mode) and nothing was said; in the foreground it opens as before."""
    teleop = [sys.executable, "-m", "services.teleop", "--set", "driver.type=keyboard"]
    job = subprocess.run(
        [sys.executable, "-c", JOB, "background", *teleop],
        capture_output=True,
        text=True,
        timeout=60,
        start_new_session=True,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert job.returncode == 2, job.stderr
    assert job.stderr.strip().splitlines()[-1] == (
        "error: keyboard teleop: it runs in the background of its terminal (started with &?), where the keys "
        "do not reach it: run it in the foreground, or set driver.tty=/dev/pts/N of another terminal"
    )
    fore = subprocess.run(
        [sys.executable, "-c", JOB, "foreground", sys.executable, "-c", OPEN_KEYBOARD],
        capture_output=True,
        text=True,
        timeout=60,
        start_new_session=True,
    )
    assert fore.returncode == 0 and fore.stdout.strip() == "opened", fore.stderr


# -- SpaceMouse ---------------------------------------------------------------------------------


class FakeHid:
    """In-test stand-in for ``easyhid.Device`` (the hidapi handle pyspacemouse reads): hands out the
    queued report bytes one per ``read``, empty when none is waiting (a non-blocking hid_read)."""

    product_string = "SpaceMouse Compact"
    manufacturer_string = "3Dconnexion"
    release_number = 0x0437
    serial_number = ""

    def __init__(self):
        self.reports: collections.deque[bytes] = collections.deque()
        self.closed = False

    def open(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def read(self, size: int = 64, timeout=None) -> bytes:
        return self.reports.popleft()[:size] if self.reports else b""


def translation(x: int, y: int, z: int) -> bytes:
    """Report 1 of the SpaceMouse Compact: raw HID axes (+x right, +y toward you, +z down), int16 LE."""
    return struct.pack("<Bhhh", 1, x, y, z)


def rotation(rx: int, ry: int, rz: int) -> bytes:
    return struct.pack("<Bhhh", 2, rx, ry, rz)


def buttons(left: bool, right: bool) -> bytes:
    return bytes([3, int(left) | int(right) << 1])


# SpaceMouse Compact, pressed down and tilted (CloudCompare/CloudCompare#2339)
CAPTURED = [bytes.fromhex(h) for h in ("02200000001700", "0112000000f800", "02200000001900", "01120000001201")]


@pytest.fixture
def spacemouse():
    pyspacemouse = pytest.importorskip("pyspacemouse", reason="pip install -e '.[test]' installs pyspacemouse")
    made = []

    def make(**overrides):
        spec = pyspacemouse.apply_axis_convention(
            pyspacemouse.get_device_specs()["SpaceMouseCompact"], pyspacemouse.AxisConvention.HID_Z_UP
        )
        hid = FakeHid()
        device = pyspacemouse.SpaceMouseDevice(info=spec, device=hid)
        device.open()
        clock = Clock()
        driver = TELEOP_DRIVERS.build(SpaceMouseTeleopConfig(**overrides), device=device, clock=clock)
        made.append(driver)

        def feed(*reports: bytes) -> None:
            want = driver.reports + len(reports)
            hid.reports.extend(reports)
            wait_for(lambda: driver.reports >= want, 5, "the driver to decode the reports")

        return driver, feed, clock, hid

    yield make
    for driver in made:
        driver.close()


def act(driver, gripper: float = 0.0):
    return driver.act(robot_state(gripper), None, {})


def test_spacemouse_reports_become_capped_eef_deltas(spacemouse):
    driver, feed, clock, hid = spacemouse(deadzone=0.05, deadman_ms=100)
    assert not driver.needs_task_state
    assert not act(driver).dp.any()  # no report yet: still

    feed(*CAPTURED)  # pressed down: the last translation report has raw z = 0x0112 (down) and x = 0x12
    z = (274 / 350 - 0.05) / 0.95  # pyspacemouse's scale (350), then our deadzone
    x = (18 / 350 - 0.05) / 0.95
    cmd = act(driver)
    np.testing.assert_allclose(cmd.dp, [x * MAX_DP, 0, -z * MAX_DP], atol=1e-9)
    np.testing.assert_allclose(cmd.drot, [(32 / 350 - 0.05) / 0.95 * MAX_DROT, 0, -(25 / 350 - 0.05) / 0.95 * MAX_DROT])

    feed(translation(350, 0, 0), rotation(0, 0, 0))  # full right
    np.testing.assert_allclose(act(driver).dp, [MAX_DP, 0, 0])
    feed(translation(400, -400, -400))  # every axis beyond full scale: capped to max_dp per tick
    cmd = act(driver)
    assert np.linalg.norm(cmd.dp) == pytest.approx(MAX_DP)
    assert cmd.dp[1] > 0 and cmd.dp[2] > 0  # away from you is +y, lifting is +z (Z up)
    feed(translation(10, -15, 5))  # inside the deadzone
    assert not act(driver).dp.any()

    feed(translation(0, 0, -350), rotation(0, 0, -350))  # lift and twist counter-clockwise
    cmd = act(driver)
    np.testing.assert_allclose(cmd.dp, [0, 0, MAX_DP])
    np.testing.assert_allclose(cmd.drot, [0, 0, MAX_DROT])
    clock.t += 0.099
    assert act(driver).dp[2] > 0
    clock.t += 0.002  # no report for 101 ms: the deadman holds still
    held = act(driver)
    assert not held.dp.any() and not held.drot.any()

    # LEFT click: gripper toggle (from where the robot reports it)
    assert act(driver, gripper=0.0).gripper == 0.0
    feed(buttons(True, False))
    clock.t += 0.2
    feed(buttons(False, False))
    assert act(driver, gripper=0.0).gripper == 1.0
    feed(buttons(True, False), buttons(False, False))  # pressed and released between two polls
    assert act(driver, gripper=1.0).gripper == 0.0
    assert driver.episodes.replies == []  # no episode gesture so far

    driver.close()
    assert hid.closed


def test_spacemouse_frame_turn_and_translation_only(spacemouse):
    driver, feed, _, _ = spacemouse(yaw_deg=90, rotation=False, speed=0.5)
    feed(translation(350, 0, 0), rotation(350, 0, 0))  # puck right, tilted
    cmd = act(driver)
    np.testing.assert_allclose(cmd.dp, [0, 0.5 * MAX_DP, 0], atol=1e-12)  # turned 90 degrees: base +y
    assert not cmd.drot.any()


def test_spacemouse_config_errors(spacemouse, monkeypatch):
    pyspacemouse = pytest.importorskip("pyspacemouse")
    spec = pyspacemouse.get_device_specs()["SpaceMouseCompact"]
    device = pyspacemouse.SpaceMouseDevice(info=spec, device=FakeHid())
    with pytest.raises(ConfigError, match="has buttons LEFT, RIGHT"):
        TELEOP_DRIVERS.build(SpaceMouseTeleopConfig(episode_button="MENU"), device=device)
    with pytest.raises(ConfigError, match="cannot open a SpaceMouse"):  # none plugged in (or no hidapi) here
        TELEOP_DRIVERS.build(SpaceMouseTeleopConfig(device="SpaceMouseCompact"))
    monkeypatch.setitem(sys.modules, "pyspacemouse", None)  # a machine without the library
    with pytest.raises(ConfigError, match=r"pip install pyspacemouse"):
        TELEOP_DRIVERS.build(SpaceMouseTeleopConfig())


# -- episode keys drive a real recorder ---------------------------------------------------------


def test_episode_keys_drive_the_recorder(zenoh_endpoint, pty, spacemouse, tmp_path, caplog):
    master, _slave, path = pty
    bus_cfg = BusConfig(mode="client", connect=[zenoh_endpoint])
    out = tmp_path / "episodes"
    with ExitStack() as stack:
        rec_bus, teleop_bus, robot = (stack.enter_context(Bus(bus_cfg)) for _ in range(3))
        stack.enter_context(Recorder(RecorderConfig(bus=bus_cfg, out_dir=out), rec_bus))
        cfg = TeleopConfig(bus=bus_cfg, world="real", driver=KeyboardTeleopConfig(tty=path, task="pour", rig="five15"))
        keyboard = TELEOP_DRIVERS.build(cfg.driver)
        service = stack.enter_context(TeleopService(cfg, teleop_bus, keyboard))  # closes the driver
        stop = threading.Event()
        runner = threading.Thread(target=service.run, args=(stop,), daemon=True)
        runner.start()
        stack.callback(runner.join, 10)
        stack.callback(stop.set)
        robot.wait_alive({"recorder", "teleop"}, timeout=30)
        keys = Typist(master, keyboard)

        def status():
            return episode_control(robot, episode_request("status"), 10)

        def replies(driver, n: int):
            return wait_for(lambda: len(driver.episodes.replies) >= n and driver.episodes.replies, 20, "the recorder")

        keys.type(b"b", 1)  # begin
        action, reply = replies(keyboard, 1)[0]
        assert action == "start" and reply.ok, reply.error
        episode = reply.meta.episode_id
        assert episode.startswith("pour-five15-") and status().recording
        # no robot service announced on this bus: the operator's log warns (before: at INFO, among the rest)
        warned = [r for r in caplog.records if r.levelname == "WARNING" and "episode key start" in r.getMessage()]
        assert warned and "warning: no robot service or sim on this bus" in warned[0].getMessage()

        # while recording, a key moves the arm through the service: robot state in, command out
        commands: list[EefCommand] = []
        answered = threading.Event()

        def on_command(msg: EefCommand, _rx) -> None:
            commands.append(msg)
            answered.set()

        robot.subscribe(topics.COMMAND, on_command)
        states = robot.publisher(topics.ROBOT_STATE)
        deadline = time.monotonic() + 10
        for tick in range(1000):  # a robot ticking until the key shows in a command
            keys.type(b"w", 1)
            answered.clear()
            states.put(robot_state(tick=tick))
            answered.wait(0.2)
            if any(c.action.dp[0] > 0 for c in commands) or time.monotonic() > deadline:
                break
        assert any(c.action.dp[0] > 0 for c in commands), f"no command moved +x in {len(commands)}"
        assert all(c.source == "keyboard" for c in commands)

        keys.type(b"y", 1)  # stop, success
        action, reply = replies(keyboard, 2)[1]
        assert action == "stop_success" and reply.ok, reply.error
        assert reply.meta.success and reply.meta.episode_id == episode
        assert (out / f"{episode}.mcap").exists() and not status().recording

        # the SpaceMouse: long press RIGHT starts, long press of both buttons discards
        mouse, feed, clock, _ = spacemouse(task="wipe", rig="five15", long_press_s=1.0)
        mouse.attach(teleop_bus)
        feed(buttons(False, True))
        clock.t += 1.0
        action, reply = replies(mouse, 1)[0]
        assert action == "start" and reply.ok, reply.error
        second = reply.meta.episode_id
        assert second.startswith("wipe-five15-") and status().recording
        feed(buttons(False, False), buttons(True, True))
        clock.t += 1.0
        action, reply = replies(mouse, 2)[1]
        assert action == "discard" and reply.ok, reply.error
        assert not status().recording
        assert sorted(p.name for p in out.glob("*.mcap*")) == [f"{episode}.mcap"]  # the discarded one is gone
