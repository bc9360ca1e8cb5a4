"""Free-running cameras: one capture thread per camera keeps its newest frame, ``grab()`` takes them.

Real cameras run on their own clocks, so unlike the sim nobody renders on demand. Each camera's
thread reads frames as they come, stamps each at capture (the stream decides how: a device's
hardware clock, or arrival time minus a latency), converts it to RGB at the service's size, and
keeps only the newest: a frame replaced before ``grab()`` took it is counted as a drop.

``grab()`` returns every camera's newest frame that it has not returned before, waiting at most
``wait_s`` for connected cameras that have none yet. A slow or disconnected camera therefore
delays a frame set by at most ``wait_s`` and is then left out: its last frame is never handed
out twice, and no placeholder is made up, so downstream a missing camera is missing frames.

A stream that stops delivering (unplugged, network drop, a file at its end) is closed and
opened again with exponential backoff; the time without frames is a gap, counted in ``stats()``.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from services.camera.base import CameraDriver, CameraStats, Frame
from services.camera.config import CaptureConfig
from services.core.config import ConfigError
from services.core.rig import Camera, Rig

log = logging.getLogger(__name__)

_FPS_WINDOW_S = 2.0  # achieved fps is measured over this much recent history
_LATENCY_EMA = 0.05  # weight of a new frame in the mean latency


class StreamError(Exception):
    """A source that cannot be opened; the message says why, in words."""


@dataclass(frozen=True)
class Captured:
    image: np.ndarray  # (H, W, 3) uint8, the source's size; RGB, or BGR where the stream says so
    stamp_ns: int  # capture time, Unix ns
    receive_ns: int  # when this process got it, Unix ns


class Stream(ABC):
    """One camera's connection. After start-up only its capture thread touches it."""

    bgr: bool = False  # frames come in OpenCV's BGR order
    period_s: float | None = None  # pace reads at this period (a file played like a camera); None: as they come

    @property
    @abstractmethod
    def label(self) -> str:
        """The source, as messages name it (a device, URL, file or serial number)."""

    @abstractmethod
    def open(self) -> None:
        """Connect; raise ``StreamError`` saying why not."""

    @abstractmethod
    def read(self) -> Captured | None:
        """The next frame, or None when the stream dropped or ended (then it is closed and reopened)."""

    def close(self) -> None:
        """Release the connection; it may be opened again."""

    @property
    def finished(self) -> bool:
        """True when the source ended for good (a file not looped): no reopening."""
        return False

    @property
    def size(self) -> tuple[int, int] | None:
        """(width, height) the source delivers, once known."""
        return None

    def exposure(self) -> float | None:
        """The device's exposure setting, where it reports one."""
        return None


def convert(image: np.ndarray, size: tuple[int, int], bgr: bool) -> np.ndarray:
    """(H, W, 3) source frame -> (height, width, 3) uint8 RGB at ``size`` (width, height)."""
    if (image.shape[1], image.shape[0]) != size:
        shrink = image.shape[1] > size[0] or image.shape[0] > size[1]
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    if bgr:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(image, dtype=np.uint8)


class _CameraThread:
    """One camera: its stream, its capture thread, its newest frame and its counters.
    Everything but the stream is guarded by the driver's condition ``cond``."""

    def __init__(
        self,
        name: str,
        stream: Stream,
        size: tuple[int, int],
        cond: threading.Condition,
        stop: threading.Event,
        backoff: tuple[float, float],
    ):
        self.name = name
        self.stream = stream
        self.size = size
        self.cond = cond
        self.stop = stop
        self.backoff = backoff
        self.latest: Captured | None = None
        self.seq = 0  # frames captured
        self.taken = 0  # seq of the last frame grab() returned
        self.connected = True  # opened at start-up
        self.drops = 0
        self.reconnects = 0
        self.gaps = 0
        self.last_frame_ns = 0  # arrival of the newest frame (Unix ns)
        self.down_since_ns = 0  # when the current gap began (0: none)
        self.last_gap_s = 0.0
        self.latency_s: float | None = None
        self.exposure: float | None = None
        self.resolution: tuple[int, int] | None = stream.size
        self._arrivals: deque[float] = deque()  # monotonic arrival times within the fps window
        self.thread = threading.Thread(target=self._run, name=f"camera-{name}", daemon=True)

    # -- capture thread ---------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._loop()
        except Exception:  # a driver bug must show, and leave the camera counted as gone
            log.exception("camera %s: capture thread failed", self.name)
            self._went_down()
        finally:
            self.stream.close()

    def _loop(self) -> None:
        due = time.monotonic()
        asked_at = -1.0
        exposure, resolution = self.exposure, self.resolution
        while not self.stop.is_set():
            if not self.connected and not self._reopen():
                return
            period = self.stream.period_s
            if period is not None:  # a file: hand out frames at its rate, as a camera would
                if self.stop.wait(max(0.0, due - time.monotonic())):
                    return
                due = max(due + period, time.monotonic())
            captured = self.stream.read()
            if captured is None:
                self.stream.close()
                if self.stream.finished:
                    log.warning("camera %s: %s ended; no more frames from it", self.name, self.stream.label)
                    self._went_down()
                    return
                log.warning("camera %s: %s stopped delivering; reconnecting", self.name, self.stream.label)
                self._went_down()
                continue
            if time.monotonic() - asked_at >= 1.0:  # asked here: a capture object is not thread-safe
                asked_at = time.monotonic()
                exposure, resolution = self.stream.exposure(), self.stream.size
            rgb = convert(captured.image, self.size, self.stream.bgr)
            self._store(captured, rgb, exposure, resolution)

    def _reopen(self) -> bool:
        """Open the stream again, waiting longer after each failure; False once stopped."""
        delay = self.backoff[0]
        failures = 0
        while not self.stop.wait(delay):
            try:
                self.stream.open()
            except StreamError as exc:
                failures += 1
                if failures == 1 or failures % 10 == 0:
                    label = self.stream.label
                    log.warning("camera %s: cannot reopen %s (%d tries): %s", self.name, label, failures, exc)
                delay = min(2 * delay, self.backoff[1])
                continue
            with self.cond:
                self.connected = True
                self.reconnects += 1
            log.info("camera %s: reopened %s", self.name, self.stream.label)
            return True
        return False

    def _went_down(self) -> None:
        with self.cond:
            if self.connected:
                self.connected = False
                self.gaps += 1
                self.down_since_ns = self.last_frame_ns or time.time_ns()
            self.cond.notify_all()  # grab() stops waiting for this camera

    def _store(self, captured: Captured, rgb: np.ndarray, exposure: float | None, size) -> None:
        now = time.monotonic()
        with self.cond:
            if self.seq > self.taken:
                self.drops += 1
            if self.down_since_ns:
                self.last_gap_s = (captured.receive_ns - self.down_since_ns) / 1e9
                self.down_since_ns = 0
                log.warning("camera %s: frames again after a %.2f s gap", self.name, self.last_gap_s)
            self.latest = Captured(rgb, captured.stamp_ns, captured.receive_ns)
            self.seq += 1
            self.last_frame_ns = captured.receive_ns
            latency = (captured.receive_ns - captured.stamp_ns) / 1e9
            self.latency_s = (
                latency if self.latency_s is None else self.latency_s + _LATENCY_EMA * (latency - self.latency_s)
            )
            self.exposure, self.resolution = exposure, size
            self._arrivals.append(now)
            while self._arrivals and self._arrivals[0] < now - _FPS_WINDOW_S:
                self._arrivals.popleft()
            self.cond.notify_all()

    # -- any thread, holding cond -----------------------------------------------------------
    def stats(self) -> CameraStats:
        now = time.monotonic()
        recent = [t for t in self._arrivals if t >= now - _FPS_WINDOW_S]
        fps = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) >= 2 and recent[-1] > recent[0] else 0.0
        gap = self.last_gap_s
        if not self.connected and self.down_since_ns:
            gap = (time.time_ns() - self.down_since_ns) / 1e9
        return CameraStats(
            connected=self.connected,
            frames=self.seq,
            fps=fps if self.connected else 0.0,
            drops=self.drops,
            reconnects=self.reconnects,
            gaps=self.gaps,
            last_gap_s=gap,
            latency_s=self.latency_s,
            exposure=self.exposure,
            resolution=self.resolution,
        )


class CaptureCameras(CameraDriver):
    """A group of free-running cameras, each read by its own thread (see the module docstring).

    Subclasses build one ``Stream`` per rig camera; ``start`` opens them all (in parallel, so
    network cameras do not add up their connection times) and fails with one line naming every
    camera that cannot be opened and its source.
    """

    def __init__(self, streams: dict[str, Stream], cfg: CaptureConfig, *, rig: Rig, width: int, height: int):
        unknown = sorted(set(streams) - set(rig.cameras))
        if unknown:
            raise ConfigError(
                f"camera {', '.join(unknown)} not in rig {rig.spec.name} ({', '.join(rig.cameras)}): "
                "the driver's camera names must be the rig's, whose calibration they publish"
            )
        self._cameras = {name: rig.cameras[name] for name in streams}
        self._size = (width, height)
        self.wait_s = cfg.wait_s
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._threads = {
            name: _CameraThread(
                name, stream, self._size, self._cond, self._stop, (cfg.reconnect_min_s, cfg.reconnect_max_s)
            )
            for name, stream in streams.items()
        }
        self._started = False

    def start(self) -> None:
        """Open every stream, then start capturing; ConfigError if any cannot be opened."""
        failed: dict[str, str] = {}
        with ThreadPoolExecutor(max_workers=len(self._threads)) as pool:
            results = {name: pool.submit(_try_open, t.stream) for name, t in self._threads.items()}
            for name, fut in results.items():
                why = fut.result()
                if why is not None:
                    failed[name] = f"camera {name}: cannot open {self._threads[name].stream.label}: {why}"
        if failed:
            for name, t in self._threads.items():
                if name not in failed:
                    t.stream.close()
            raise ConfigError("; ".join(failed.values()))
        for name, t in self._threads.items():
            t.resolution = t.stream.size
            size = f"{t.resolution[0]}x{t.resolution[1]}" if t.resolution else "size unknown"
            log.info("camera %s: opened %s (%s)", name, t.stream.label, size)
            t.thread.start()
        self._started = True

    @property
    def cameras(self) -> dict[str, Camera]:
        return self._cameras

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def grab(self, stamp_ns: int) -> dict[str, Frame]:
        """Each camera's newest frame not returned before, stamped at its capture, resized to the
        service's ``size`` if the source's differs. ``stamp_ns`` is not used: free-running cameras
        are not triggered, so the newest frame is the closest one. Connected cameras without a new
        frame are waited for up to ``wait_s``; whoever still has none (or is disconnected) is left
        out of the result."""
        deadline = time.monotonic() + self.wait_s
        with self._cond:
            while True:
                waiting = [t for t in self._threads.values() if t.connected and t.seq == t.taken]
                left = deadline - time.monotonic()
                if not waiting or left <= 0:
                    break
                self._cond.wait(left)
            frames: dict[str, Frame] = {}
            for name, t in self._threads.items():
                if t.seq > t.taken and t.latest is not None:
                    frames[name] = Frame(t.latest.image, t.latest.stamp_ns)
                    t.taken = t.seq
            return frames

    def stats(self) -> dict[str, CameraStats]:
        with self._cond:
            return {name: t.stats() for name, t in self._threads.items()}

    def close(self) -> None:
        """Stop the capture threads and release every source. A thread stuck in a driver call
        (a read that has not timed out yet) is not waited for beyond a few seconds."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if not self._started:
            for t in self._threads.values():
                t.stream.close()
            return
        deadline = time.monotonic() + 5.0
        for t in self._threads.values():
            t.thread.join(max(0.0, deadline - time.monotonic()))
            if t.thread.is_alive():
                log.warning("camera %s: capture thread still busy in its driver at close", t.name)


def _try_open(stream: Stream) -> str | None:
    try:
        stream.open()
    except StreamError as exc:
        return str(exc)
    return None
