"""Intel RealSense cameras through ``pyrealsense2`` (librealsense): the colour stream of each.

``driver: {type: realsense, cameras: {F: {serial: "123622270001"}, FL: {serial: "..."}}}``: one
pipeline per device, selected by serial number, read by its own capture thread
(``services/camera/capture.py``: newest frame, drops, reconnection, stats).

Stamps come from the device: librealsense's *global time* domain maps the camera's hardware
clock onto the host's system clock (Unix milliseconds), correcting the drift between the two,
so a frame's stamp is when the sensor captured it, not when USB delivered it. It is switched on
for every colour sensor that offers it; a frame that still reports another domain (old firmware)
is stamped with its arrival time instead, and the log says so once.

``pyrealsense2`` is an optional dependency (``pip install pyrealsense2``), imported only when
this driver is built.
"""

from __future__ import annotations

import logging
import time
from types import ModuleType
from typing import Any

import numpy as np

from services.camera.capture import CaptureCameras, Captured, Stream, StreamError
from services.camera.config import RealSenseCameraConfig, RealSenseSource
from services.core.config import ConfigError
from services.core.rig import Rig

log = logging.getLogger(__name__)


def import_realsense() -> ModuleType:
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise ConfigError(
            f"camera driver realsense needs Intel's SDK for Python: pip install pyrealsense2 ({exc})"
        ) from None
    return rs


class RealSenseStream(Stream):
    """The colour stream of one device, through its own ``rs.pipeline``."""

    def __init__(self, rs: ModuleType, name: str, spec: RealSenseSource, timeout_s: float):
        self.rs = rs
        self.name = name
        self.spec = spec
        self.timeout_ms = int(timeout_s * 1e3)
        self._pipeline: Any = None
        self._warned_domain = False
        self._exposure: float | None = None

    @property
    def label(self) -> str:
        return f"RealSense {self.spec.serial}" if self.spec.serial else "the only RealSense"

    def _serial(self) -> str:
        rs = self.rs
        serials = [dev.get_info(rs.camera_info.serial_number) for dev in rs.context().query_devices()]
        present = ", ".join(serials) or "none"
        if self.spec.serial is None:
            if len(serials) != 1:
                raise StreamError(f"give its serial: {len(serials)} RealSense devices connected ({present})")
            return serials[0]
        if self.spec.serial not in serials:
            raise StreamError(f"no RealSense with serial {self.spec.serial} (connected: {present})")
        return self.spec.serial

    def open(self) -> None:
        rs, spec = self.rs, self.spec
        self.close()
        serial = self._serial()
        config = rs.config()
        config.enable_device(serial)
        config.enable_stream(rs.stream.color, spec.width, spec.height, rs.format.rgb8, spec.fps)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(config)
        except RuntimeError as exc:  # librealsense's errors: a mode the device lacks, a device in use
            raise StreamError(f"{spec.width}x{spec.height} RGB at {spec.fps} fps: {exc}") from None
        sensor = profile.get_device().first_color_sensor()
        if sensor.supports(rs.option.global_time_enabled):
            sensor.set_option(rs.option.global_time_enabled, 1)
        self._pipeline = pipeline

    def read(self) -> Captured | None:
        rs = self.rs
        if self._pipeline is None:
            return None
        try:
            frames = self._pipeline.wait_for_frames(self.timeout_ms)
        except RuntimeError as exc:  # no frame within the timeout, or the device went away
            log.warning("camera %s: %s: %s", self.name, self.label, exc)
            return None
        receive_ns = time.time_ns()
        color = frames.get_color_frame()
        if not color:
            return None
        image = np.array(color.get_data(), dtype=np.uint8, copy=True)  # the SDK reuses its buffer
        if color.get_frame_timestamp_domain() == rs.timestamp_domain.global_time:
            stamp_ns = round(color.get_timestamp() * 1e6)  # ms on the host's Unix clock
        else:
            if not self._warned_domain:
                self._warned_domain = True
                log.warning(
                    "camera %s: %s gives no global-time stamps (%s): stamping frames at arrival",
                    self.name,
                    self.label,
                    color.get_frame_timestamp_domain(),
                )
            stamp_ns = receive_ns
        if color.supports_frame_metadata(rs.frame_metadata_value.actual_exposure):
            self._exposure = float(color.get_frame_metadata(rs.frame_metadata_value.actual_exposure))
        return Captured(image, stamp_ns, receive_ns)

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:  # already stopped by an unplug
                pass
            self._pipeline = None

    @property
    def size(self) -> tuple[int, int] | None:
        return (self.spec.width, self.spec.height)

    def exposure(self) -> float | None:
        """The last frame's actual exposure (microseconds), where the device reports it."""
        return self._exposure


class RealSenseCamera(CaptureCameras):
    """The rig's cameras as RealSense colour streams (see the module docstring). Frames are
    resized to the service's width and height when the stream's mode differs."""

    @classmethod
    def from_config(cls, cfg: RealSenseCameraConfig, *, rig: Rig, width: int, height: int) -> RealSenseCamera:
        rs = import_realsense()
        streams = {name: RealSenseStream(rs, name, spec, cfg.timeout_s) for name, spec in cfg.cameras.items()}
        driver = cls(streams, cfg, rig=rig, width=width, height=height)
        driver.start()
        return driver
