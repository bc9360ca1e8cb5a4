"""Cameras read through OpenCV: USB cameras (V4L2), network streams (RTSP, HTTP) and video files.

``driver: {type: opencv, cameras: {F: {source: 0, fourcc: MJPG, width: 1280, height: 720},
FL: {source: "rtsp://10.0.0.5/stream1"}}}``: one capture thread per camera
(``services/camera/capture.py``), each frame stamped at capture, reconnection after an unplug
or a dropped stream, stats for the service's log and ``viewscale check``.

Stamps. OpenCV gives no capture time for streams and files, so those are stamped with their
arrival time minus the configured ``latency_s``. A V4L2 device does better: the kernel stamps
each buffer with CLOCK_MONOTONIC when it is captured (UVC: when its first packet arrives), and
OpenCV reports it as ``CAP_PROP_POS_MSEC``; its age at arrival is the driver-to-process delay,
measured per frame (``v4l2_stamp``); ``latency_s`` then only needs to hold what happens before
the kernel sees the frame (exposure and readout).

Reads never hang the service: ``grab()`` only waits ``wait_s`` for a capture thread; streams are
opened with ``open_timeout_s`` and a silent stream fails its read after ``read_timeout_s``
(FFmpeg's interrupt callback); a V4L2 read returns an error at once when the device is unplugged.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import cv2

from services.camera.capture import CaptureCameras, Captured, Stream, StreamError
from services.camera.config import OpenCVCameraConfig, OpenCVSource, source_kind
from services.core.rig import Rig

log = logging.getLogger(__name__)

_MAX_BUFFER_AGE_S = 1.0  # a V4L2 buffer stamp older than this is not a monotonic capture time


def v4l2_stamp(receive_ns: int, monotonic_s: float, buffer_ms: float, latency_s: float) -> int:
    """Capture time (Unix ns) of a V4L2 frame that arrived at ``receive_ns`` (Unix) and
    ``monotonic_s`` (CLOCK_MONOTONIC), whose buffer the kernel stamped ``buffer_ms`` (CLOCK_MONOTONIC,
    ms). A buffer stamp that is not a plausible recent monotonic time (a driver stamping with
    another clock, or none) is ignored: only ``latency_s`` is taken off then."""
    age = monotonic_s - buffer_ms / 1e3
    if not 0.0 <= age < _MAX_BUFFER_AGE_S:
        age = 0.0
    return receive_ns - round((age + latency_s) * 1e9)


def fourcc_text(code: float) -> str:
    """OpenCV's FOURCC property (a number) -> its four characters ('' if none)."""
    n = int(code)
    text = "".join(chr((n >> (8 * i)) & 0xFF) for i in range(4))
    return text if n > 0 and text.isprintable() else ""


def safe_label(source: int | str) -> str:
    """The source as logs show it: V4L2 index as a device, a URL without its password."""
    if isinstance(source, int) or source.isdigit():
        return f"/dev/video{int(source)}"
    if "://" in source:
        parts = urlsplit(source)
        if parts.password:
            host = parts.hostname or ""
            netloc = f"{parts.username}:***@{host}" + (f":{parts.port}" if parts.port else "")
            return urlunsplit(parts._replace(netloc=netloc))
    return source


class OpenCVStream(Stream):
    """One ``cv2.VideoCapture``: V4L2 for devices, FFmpeg (with timeouts) for streams and files."""

    bgr = True

    def __init__(self, name: str, spec: OpenCVSource, cfg: OpenCVCameraConfig):
        self.name = name
        self.spec = spec
        self.kind = source_kind(spec.source)
        self.open_timeout_ms = int(cfg.open_timeout_s * 1e3)
        self.read_timeout_ms = int(cfg.read_timeout_s * 1e3)
        self._label = safe_label(spec.source)
        self._cap: cv2.VideoCapture | None = None
        self._size: tuple[int, int] | None = None
        self._ended = False
        self._settings_logged = False
        self.period_s = None

    @property
    def label(self) -> str:
        return self._label

    def open(self) -> None:
        self.close()
        source = self.spec.source
        if self.kind == "device":
            target = f"/dev/video{int(source)}" if isinstance(source, int) or source.isdigit() else source
            if not Path(target).exists():
                raise StreamError(f"no such device {target}")
            cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
        else:
            if self.kind == "file" and not Path(source).is_file():
                raise StreamError("no such file")
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, self.open_timeout_ms]
            params += [cv2.CAP_PROP_READ_TIMEOUT_MSEC, self.read_timeout_ms]
            cap = cv2.VideoCapture(str(source), cv2.CAP_FFMPEG, params)
        if not cap.isOpened():
            cap.release()
            why = {
                "device": "not a V4L2 capture device, or busy",
                "stream": f"no stream there within {self.open_timeout_ms / 1e3:g} s (refused, wrong path or no answer)",
                "file": "not a video FFmpeg can read",
            }[self.kind]
            raise StreamError(why)
        if self.kind == "device":
            self._configure(cap)
        if self.kind == "file":
            fps = self.spec.fps or cap.get(cv2.CAP_PROP_FPS)
            if not fps or fps <= 0:
                cap.release()
                raise StreamError("the file gives no frame rate: set fps for it")
            self.period_s = 1.0 / fps
        self._size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        self._ended = False
        self._cap = cap

    def _configure(self, cap: cv2.VideoCapture) -> None:
        """Ask the device for the configured format, size and rate (format first: the sizes and
        rates a device offers depend on it), and say what it gave where that differs."""
        spec = self.spec
        if spec.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*spec.fourcc))
        if spec.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, spec.width)
        if spec.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, spec.height)
        if spec.fps:
            cap.set(cv2.CAP_PROP_FPS, spec.fps)
        got = {
            "fourcc": fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
            "width": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            "height": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            "fps": cap.get(cv2.CAP_PROP_FPS),
        }
        differs = {
            k: (getattr(spec, k), v)
            for k, v in got.items()
            if getattr(spec, k) is not None and (abs(v - spec.fps) > 0.5 if k == "fps" else v != getattr(spec, k))
        }
        if differs and not self._settings_logged:
            log.warning(
                "camera %s: %s gave %s",
                self.name,
                self._label,
                ", ".join(f"{k} {g} (asked {a})" for k, (a, g) in differs.items()),
            )
        self._settings_logged = True

    def read(self) -> Captured | None:
        captured = self._read()
        if captured is None and self.kind == "file":
            if self.spec.at_end == "end":
                self._ended = True
                return None
            try:  # loop: play it again from the start; failing that, it is a drop like any other
                self.open()
            except StreamError:
                return None
            captured = self._read()
        return captured

    def _read(self) -> Captured | None:
        cap = self._cap
        if cap is None:
            return None
        ok, image = cap.read()
        receive_ns, monotonic_s = time.time_ns(), time.monotonic()
        if not ok or image is None:
            return None
        latency = self.spec.latency_s
        if self.kind == "device":
            stamp = v4l2_stamp(receive_ns, monotonic_s, cap.get(cv2.CAP_PROP_POS_MSEC), latency)
        else:
            stamp = receive_ns - round(latency * 1e9)
        return Captured(image, stamp, receive_ns)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    @property
    def finished(self) -> bool:
        return self._ended

    @property
    def size(self) -> tuple[int, int] | None:
        return self._size

    def exposure(self) -> float | None:
        if self.kind != "device" or self._cap is None:
            return None
        value = self._cap.get(cv2.CAP_PROP_EXPOSURE)
        return None if value == -1.0 else float(value)  # -1: the device has no exposure control


class OpenCVCamera(CaptureCameras):
    """The rig's cameras read through OpenCV (see the module docstring): each camera name of the
    config is a rig camera, whose calibration is published with its frames. Frames are resized
    to the service's width and height when the source delivers another size."""

    @classmethod
    def from_config(cls, cfg: OpenCVCameraConfig, *, rig: Rig, width: int, height: int) -> OpenCVCamera:
        # OpenCV's own warnings (`[ WARN:0@0.2] global cap.cpp:212 open VIDEOIO(FFMPEG): ...` on a
        # source it cannot open) went to stderr beside ours, which say the same in plain words
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        streams = {name: OpenCVStream(name, spec, cfg) for name, spec in cfg.cameras.items()}
        driver = cls(streams, cfg, rig=rig, width=width, height=height)
        driver.start()
        return driver
