from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from services.camera.base import CameraDriver
from services.core.bus import BusConfig
from services.core.config import Frozen, LogLevel
from services.core.registry import DriverConfig, Registry, World, check_world
from services.core.rig import Rig, placeholder_rig


class SimCameraConfig(DriverConfig):
    """The rig's cameras rendered by MuJoCo from a static scene (placement and calibration checks)."""

    sim_only = True

    type: Literal["sim"] = "sim"
    task: str = "lift"  # the scene to render
    seed: int = 0  # scene seed


class CaptureConfig(DriverConfig):
    """Settings every free-running camera group shares (services/camera/capture.py)."""

    wait_s: float = Field(0.1, ge=0)  # grab() waits at most this for a camera's next frame, then leaves it out
    reconnect_min_s: float = Field(0.2, gt=0)  # first retry after a camera stops delivering; doubles per failure
    reconnect_max_s: float = Field(5.0, gt=0)  # longest wait between retries


SourceKind = Literal["device", "stream", "file"]


def source_kind(source: int | str) -> SourceKind:
    """A V4L2 device (an index or a /dev path), a network stream (a URL) or a video file."""
    if isinstance(source, int) or source.isdigit() or source.startswith("/dev/"):
        return "device"
    return "stream" if "://" in source else "file"


class OpenCVSource(Frozen):
    """One camera read through OpenCV. Only a device can be asked for a size, rate and pixel
    format; whatever the source delivers is resized to the service's width and height. A USB
    camera is best named by its ``/dev/v4l/by-id/...`` path, which stays the same when it is
    plugged in again (its index may not)."""

    source: int | str  # V4L2 index (0) or device (/dev/video2), a stream URL (rtsp://...) or a video file
    width: int | None = Field(None, ge=1)  # capture width asked of a device (px); None: its default
    height: int | None = Field(None, ge=1)  # capture height asked of a device (px); None: its default
    fps: float | None = Field(None, gt=0)  # capture rate asked of a device, or a file's playback rate (None: its own)
    fourcc: str | None = Field(None, min_length=4, max_length=4)  # pixel format asked of a device: MJPG, YUYV...
    latency_s: float = Field(0.0, ge=0)  # capture-to-arrival delay taken off arrival times (V4L2: besides the measured)
    at_end: Literal["loop", "end"] = "end"  # a video file at its end: play it again, or stop (the camera is then gone)

    @model_validator(mode="after")
    def _settings_fit_the_source(self) -> OpenCVSource:
        kind = source_kind(self.source)
        asked = [k for k in ("width", "height", "fourcc") if getattr(self, k) is not None]
        if kind != "device" and asked:
            raise ValueError(
                f"{', '.join(asked)}: only a V4L2 device can be asked for a size or pixel format, "
                f"not a {kind} ({self.source}); frames are resized to the service's width and height"
            )
        if kind == "stream" and self.fps is not None:
            raise ValueError(f"fps: a stream ({self.source}) sends at its own rate")
        return self


class OpenCVCameraConfig(CaptureConfig):
    """Cameras read through OpenCV, one capture thread each: USB (V4L2), RTSP/HTTP streams, video files."""

    type: Literal["opencv"] = "opencv"
    cameras: dict[str, OpenCVSource] = Field(min_length=1)  # rig camera name -> its source and settings
    open_timeout_s: float = Field(5.0, gt=0)  # a stream that does not answer within this fails to open
    read_timeout_s: float = Field(2.0, gt=0)  # a stream silent for this long counts as dropped


class RealSenseSource(Frozen):
    """One Intel RealSense colour stream; the mode must be one the device offers."""

    serial: str | None = None  # the device's serial number (`rs-enumerate-devices`); None: the only one connected
    width: int = Field(640, ge=1)  # colour stream width (px)
    height: int = Field(480, ge=1)  # colour stream height (px)
    fps: int = Field(30, ge=1)  # colour stream rate

    @field_validator("serial", mode="before")
    @classmethod
    def _serial_as_text(cls, v: object) -> object:
        return str(v) if isinstance(v, int) else v  # YAML reads an unquoted serial as a number


class RealSenseCameraConfig(CaptureConfig):
    """Intel RealSense cameras through pyrealsense2 (`pip install pyrealsense2`), stamped by the
    device's hardware clock mapped to host time (librealsense's global time domain)."""

    type: Literal["realsense"] = "realsense"
    cameras: dict[str, RealSenseSource] = Field(min_length=1)  # rig camera name -> its device and mode
    timeout_s: float = Field(1.0, gt=0)  # a device that sends no frame for this long counts as dropped

    @model_validator(mode="after")
    def _one_device_each(self) -> RealSenseCameraConfig:
        serials = [c.serial for c in self.cameras.values()]
        if len(serials) > 1 and None in serials:
            raise ValueError("cameras: with several RealSense cameras, give each its serial")
        if len(set(serials)) != len(serials):
            raise ValueError("cameras: two cameras name the same serial")
        return self


CAMERA_DRIVERS: Registry[CameraDriver] = Registry("camera", CameraDriver)
CAMERA_DRIVERS.register("sim", "sim.backends:SimCamera", SimCameraConfig)
CAMERA_DRIVERS.register("opencv", "services.camera.opencv:OpenCVCamera", OpenCVCameraConfig)
CAMERA_DRIVERS.register("realsense", "services.camera.realsense:RealSenseCamera", RealSenseCameraConfig)


class CameraConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    world: World = "sim"  # sim or real (shared top-level key): sim-only drivers are refused in a real session
    driver: CAMERA_DRIVERS.config_type() = SimCameraConfig()  # {type: sim|opencv|realsense, ...} or your class
    rig: str = "five15"  # rig preset or YAML: names, poses and intrinsics of the cameras
    width: int = Field(84, ge=16)  # frame width (px)
    height: int = Field(84, ge=16)  # frame height (px)
    fps: float = Field(20.0, gt=0)  # frames per second per camera
    jpeg_quality: int = Field(90, ge=10, le=100)  # JPEG quality of published frames
    calibration_period_s: float = Field(1.0, gt=0)  # republish calibration and poses this often
    stats_period_s: float = Field(10.0, gt=0)  # log each camera's fps, drops and gaps this often
    log_level: LogLevel = "INFO"  # logging level of the process

    @model_validator(mode="after")
    def _world(self) -> CameraConfig:
        check_world(self.driver, self.world, "camera")
        return self


def stand_in_rig(cfg: CameraConfig) -> Rig | None:
    """A rig of the driver's camera names with placeholder poses, for opening cameras whose rig
    file is not written yet (``viewscale check``, ``calibrate capture``); None for a driver that
    names no cameras of its own (the sim's: its cameras are the rig's)."""
    names = list(getattr(cfg.driver, "cameras", None) or [])
    return placeholder_rig(names) if names else None
