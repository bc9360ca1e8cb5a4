"""Media for the camera tests: numbered video files and a real RTSP server on loopback.

Every frame carries its number as black/white bars (``rtsp_server.frame_bytes``; read back with
``code_of``), so a test can check order, repeats and what a gap skipped, after JPEG and resizing.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from rtsp_server import code_of, frame_bytes

__all__ = ["RtspServer", "code_of", "frame_rgb", "require_rtsp_server", "write_video"]

HERE = Path(__file__).resolve().parent
SYSTEM_PYTHON = "/usr/bin/python3"  # the interpreter Debian's PyGObject and GStreamer bindings belong to


def frame_rgb(n: int, width: int = 160, height: int = 120) -> np.ndarray:
    return np.frombuffer(frame_bytes(n, width, height), np.uint8).reshape(height, width, 3)


def write_video(path: Path, numbers: range, fps: float = 20.0, size: tuple[int, int] = (160, 120)) -> Path:
    """An MJPG AVI whose frames carry ``numbers``, as any camera recording would be read."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert writer.isOpened(), f"OpenCV cannot write {path}"
    for n in numbers:
        writer.write(cv2.cvtColor(frame_rgb(n, *size), cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def require_rtsp_server() -> None:
    """The RTSP tests need gst-rtsp-server for the system Python, which
    ``deploy/install-system-deps.sh`` installs (``make test`` runs it). Skipped only where it cannot
    be installed (no system Python or no apt); anywhere else its absence is a failure."""
    probe = "import gi; gi.require_version('GstRtspServer', '1.0'); from gi.repository import GstRtspServer"
    if Path(SYSTEM_PYTHON).exists():
        done = subprocess.run([SYSTEM_PYTHON, "-c", probe], capture_output=True, text=True)
        if done.returncode == 0:
            return
        why = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "import failed"
    else:
        why = f"no {SYSTEM_PYTHON}"
    if shutil.which("apt-get") is None:
        pytest.skip(f"no RTSP server to test against ({why}) and no apt-get to install gst-rtsp-server")
    pytest.fail(f"gst-rtsp-server is missing ({why}): run `bash deploy/install-system-deps.sh` (make test does)")


class RtspServer:
    """``rtsp_server.py`` as a process: serves numbered frames at ``rtsp://127.0.0.1:<port>/cam``
    until killed; ``start`` again brings the same URL back (a camera that rebooted)."""

    def __init__(self, fps: int = 20, size: tuple[int, int] = (160, 120)):
        self.fps = fps
        self.size = size
        self.port = 0  # chosen by the OS on the first start, reused after
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"rtsp://127.0.0.1:{self.port}/cam"

    def start(self, first: int = 0) -> str:
        cmd = [SYSTEM_PYTHON, str(HERE / "rtsp_server.py"), "--port", str(self.port), "--fps", str(self.fps)]
        cmd += ["--width", str(self.size[0]), "--height", str(self.size[1]), "--start", str(first)]
        log = tempfile.TemporaryFile("w+")  # a file, not a pipe nobody drains while it serves
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True)
        line = self.proc.stdout.readline()  # the ready line, or EOF if it died
        if not line.startswith("ready "):
            self.proc.wait(timeout=10)
            log.seek(0)
            raise AssertionError(f"RTSP server did not start: {line!r} {log.read()}")
        log.close()
        self.port = int(line.split()[1].rsplit(":", 1)[1].split("/")[0])
        return self.url

    def kill(self) -> None:
        """Gone at once, as a camera losing power: no RTSP TEARDOWN, the TCP connection just closes."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self.proc = None

    def __enter__(self) -> RtspServer:
        return self

    def __exit__(self, *exc) -> None:
        self.kill()


def grab_until(driver, done: Callable[[dict[str, list]], bool], timeout: float = 10.0) -> dict[str, list]:
    """Grab as the camera service does until ``done(frames so far)``; fail at the deadline."""
    got: dict[str, list] = {name: [] for name in driver.cameras}
    deadline = time.monotonic() + timeout
    while not done(got):
        assert time.monotonic() < deadline, f"gave up after {timeout} s: {driver.stats()}"
        for name, frame in driver.grab(time.time_ns()).items():
            got[name].append(frame)
    return got
