"""The RealSense driver against a fake of ``pyrealsense2``.

pyrealsense2 is Intel's external SDK (librealsense) and has no simulator, so these tests inject
an in-test fake of that module through ``sys.modules``: only the SDK calls the driver makes
(device query, pipeline, colour stream, global time, frame timestamps), over fake devices that
produce colour-coded frames at 60 fps. The driver itself, its capture threads and its
reconnection are the real code.
"""

from __future__ import annotations

import sys
import time
import types
from enum import Enum

import numpy as np
import pytest
from camera_media import grab_until

from services.camera.config import CAMERA_DRIVERS, CameraConfig, RealSenseCameraConfig
from services.core.config import ConfigError
from services.core.rig import load_rig

RIG = load_rig("three15")
CAPTURE_TO_ARRIVAL_NS = 40_000_000  # the fake devices capture each frame 40 ms before the host gets it


class camera_info(Enum):  # noqa: N801  (the SDK's names)
    serial_number = 1


class stream(Enum):  # noqa: N801
    color = 1


class format(Enum):  # noqa: N801, A001
    rgb8 = 1


class option(Enum):  # noqa: N801
    global_time_enabled = 1


class timestamp_domain(Enum):  # noqa: N801
    hardware_clock = 0
    system_time = 1
    global_time = 2


class frame_metadata_value(Enum):  # noqa: N801
    actual_exposure = 1


class FakeDevice:
    """A connected camera: its serial, the colour it sees, and whether it is plugged in."""

    def __init__(self, serial: str, colour: tuple[int, int, int]):
        self.serial = serial
        self.colour = colour
        self.plugged = True
        self.global_time = False
        self.stamps_ms: list[float] = []  # every timestamp it handed out

    def get_info(self, info: camera_info) -> str:
        assert info is camera_info.serial_number
        return self.serial

    def first_color_sensor(self) -> FakeDevice:
        return self

    def supports(self, opt: option) -> bool:
        return opt is option.global_time_enabled

    def set_option(self, opt: option, value: float) -> None:
        self.global_time = bool(value)


class FakeFrame:
    def __init__(self, data: np.ndarray, stamp_ms: float, domain: timestamp_domain):
        self.data, self.stamp_ms, self.domain = data, stamp_ms, domain

    def __bool__(self) -> bool:
        return True

    def get_color_frame(self) -> FakeFrame:
        return self

    def get_data(self) -> np.ndarray:
        return self.data

    def get_timestamp(self) -> float:
        return self.stamp_ms

    def get_frame_timestamp_domain(self) -> timestamp_domain:
        return self.domain

    def supports_frame_metadata(self, what: frame_metadata_value) -> bool:
        return what is frame_metadata_value.actual_exposure

    def get_frame_metadata(self, what: frame_metadata_value) -> int:
        return 8500


def fake_sdk(devices: list[FakeDevice]) -> types.ModuleType:
    rs = types.ModuleType("pyrealsense2")
    for enum in (camera_info, stream, format, option, timestamp_domain, frame_metadata_value):
        setattr(rs, enum.__name__, enum)

    class context:  # noqa: N801
        def query_devices(self) -> list[FakeDevice]:
            return [d for d in devices if d.plugged]

    class config:  # noqa: N801
        def __init__(self):
            self.serial = None
            self.streams = []

        def enable_device(self, serial: str) -> None:
            self.serial = serial

        def enable_stream(self, *args) -> None:
            self.streams.append(args)

    class pipeline:  # noqa: N801
        def __init__(self):
            self.device: FakeDevice | None = None
            self.mode = None
            self.next = 0.0

        def start(self, cfg: config):
            found = [d for d in devices if d.plugged and d.serial == cfg.serial]
            if not found:
                raise RuntimeError(f"No device connected with serial {cfg.serial}")
            ((kind, width, height, fmt, fps),) = cfg.streams
            assert (kind, fmt) == (stream.color, format.rgb8)
            self.device, self.mode, self.next = found[0], (width, height, fps), time.monotonic()
            return types.SimpleNamespace(get_device=lambda: self.device)

        def wait_for_frames(self, timeout_ms: int) -> FakeFrame:
            dev = self.device
            deadline = time.monotonic() + timeout_ms / 1e3
            while not dev.plugged or time.monotonic() < self.next:  # the next frame, or the timeout
                if time.monotonic() >= deadline:
                    raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
                time.sleep(0.002)
            width, height, fps = self.mode
            self.next += 1.0 / fps
            data = np.empty((height, width, 3), np.uint8)
            data[:] = dev.colour
            if dev.global_time:
                stamp_ms = (time.time_ns() - CAPTURE_TO_ARRIVAL_NS) / 1e6
                dev.stamps_ms.append(stamp_ms)
                return FakeFrame(data, stamp_ms, timestamp_domain.global_time)
            return FakeFrame(data, 123456.0, timestamp_domain.hardware_clock)

        def stop(self) -> None:
            self.device = None

    rs.context, rs.config, rs.pipeline = context, config, pipeline
    return rs


@pytest.fixture
def devices(monkeypatch) -> list[FakeDevice]:
    devs = [FakeDevice("111", (255, 0, 0)), FakeDevice("222", (0, 0, 255))]
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake_sdk(devs))
    return devs


def build(cameras: dict, **settings):
    cfg = CameraConfig.model_validate(
        {"world": "real", "width": 32, "height": 24, "driver": {"type": "realsense", "cameras": cameras, **settings}}
    )
    assert isinstance(cfg.driver, RealSenseCameraConfig)
    return CAMERA_DRIVERS.build(cfg.driver, rig=RIG, width=cfg.width, height=cfg.height)


def test_frames_come_from_the_device_of_each_serial_stamped_by_its_hardware_clock(devices):
    driver = build({"F": {"serial": "222", "width": 64, "height": 48, "fps": 60}, "FL": {"serial": "111"}})
    try:
        got = grab_until(driver, lambda g: len(g["F"]) >= 5 and len(g["FL"]) >= 5)
        assert all(f.rgb.shape == (24, 32, 3) for f in got["F"])  # 64x48 resized to the service's size
        assert all((f.rgb[0, 0] == (0, 0, 255)).all() for f in got["F"])  # serial 222's frames
        assert all((f.rgb[0, 0] == (255, 0, 0)).all() for f in got["FL"])  # serial 111's frames
        for name, dev in (("F", devices[1]), ("FL", devices[0])):
            assert dev.global_time  # switched on by the driver
            handed_out = {round(ms * 1e6) for ms in dev.stamps_ms}
            assert all(f.stamp_ns in handed_out for f in got[name])  # the device's stamp, not arrival time
        st = driver.stats()["F"]
        assert st.connected and st.exposure == 8500 and st.resolution == (64, 48)
        assert st.latency_s == pytest.approx(CAPTURE_TO_ARRIVAL_NS / 1e9, abs=0.02)
    finally:
        driver.close()


def test_an_unplugged_device_is_a_gap_and_is_reopened_when_back(devices):
    driver = build({"F": {"serial": "111"}}, timeout_s=0.2, reconnect_min_s=0.05)
    try:
        grab_until(driver, lambda g: len(g["F"]) >= 3)
        devices[0].plugged = False
        grab_until(driver, lambda g: not driver.stats()["F"].connected)
        devices[0].plugged = True
        before = driver.stats()["F"].frames
        grab_until(driver, lambda g: driver.stats()["F"].frames >= before + 3)
        st = driver.stats()["F"]
        assert (st.connected, st.gaps, st.reconnects) == (True, 1, 1) and st.last_gap_s > 0
    finally:
        driver.close()


def test_serial_selection_errors_name_the_camera_and_what_is_connected(devices):
    with pytest.raises(
        ConfigError, match=r"camera F: cannot open RealSense 999: no RealSense with serial 999 \(connected: 111, 222\)"
    ):
        build({"F": {"serial": "999"}})
    with pytest.raises(ConfigError, match=r"give its serial: 2 RealSense devices connected \(111, 222\)"):
        build({"F": {}})
    with pytest.raises(ValueError, match="give each its serial"):
        build({"F": {"serial": "111"}, "FL": {}})
    driver = build({"F": {"serial": 222}})  # as YAML reads an unquoted serial
    try:
        assert all((f.rgb[0, 0] == (0, 0, 255)).all() for f in grab_until(driver, lambda g: len(g["F"]) >= 2)["F"])
    finally:
        driver.close()
    devices[1].plugged = False
    driver = build({"F": {}})  # the only one connected
    try:
        assert all((f.rgb[0, 0] == (255, 0, 0)).all() for f in grab_until(driver, lambda g: len(g["F"]) >= 2)["F"])
    finally:
        driver.close()


def test_without_the_sdk_the_error_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as if not installed
    with pytest.raises(ConfigError, match="pip install pyrealsense2"):
        build({"F": {}})


def test_a_frame_without_global_time_is_stamped_at_arrival(devices, monkeypatch):
    monkeypatch.setattr(FakeDevice, "supports", lambda self, opt: False)  # old firmware
    before = time.time_ns()
    driver = build({"F": {"serial": "111"}})
    try:
        frames = grab_until(driver, lambda g: len(g["F"]) >= 2)["F"]
        assert all(before <= f.stamp_ns <= time.time_ns() for f in frames)  # not the device's 123456 ms
    finally:
        driver.close()
