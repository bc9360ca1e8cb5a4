"""The camera driver interface: a group of calibrated cameras grabbed together.

A camera driver is chosen by the camera service's ``driver`` config (``services.camera.config``,
through ``services.core.registry``): the sim's rendered cameras (``type: sim``) or a lab's own
class (``type: package.module:Class``). To add one, subclass ``CameraDriver``, give it a nested
``Config`` (a frozen pydantic model) if it takes settings, and implement the four members below;
``from_config`` builds it from that config and the camera service's rig and frame size.
Hardware drivers also report ``stats()`` (the service logs them, ``viewscale check`` shows them,
and a camera that stops delivering is withdrawn from the bus so the recorder flags the episode).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.core.rig import Camera, Rig


@dataclass(frozen=True)
class Frame:
    rgb: np.ndarray  # (H, W, 3) uint8
    stamp_ns: int  # capture time, Unix ns


@dataclass(frozen=True)
class CameraStats:
    """What one camera has delivered so far. A camera that stops delivering (unplugged, stream
    dropped, file ended) is ``connected=False`` until frames come again; that time is a gap."""

    connected: bool  # delivering frames now
    frames: int = 0  # frames captured since start
    fps: float = 0.0  # achieved capture rate over the last few seconds
    drops: int = 0  # frames replaced by a newer one before grab() took them
    reconnects: int = 0  # times the source was opened again after it stopped delivering
    gaps: int = 0  # times the camera stopped delivering
    last_gap_s: float = 0.0  # length of the latest gap (so far, while it lasts)
    latency_s: float | None = None  # mean capture-to-arrival time taken off the stamps; None: unknown
    exposure: float | None = None  # exposure as the device reports it (its own units); None: unknown
    resolution: tuple[int, int] | None = None  # (width, height) the source delivers, before resizing

    def summary(self) -> str:
        """One log line's worth: ``20.0 fps, 412 frames, 3 drops, 1 gap (last 2.10 s), ...``."""
        parts = [
            "connected" if self.connected else "DISCONNECTED",
            f"{self.fps:.1f} fps",
            f"{self.frames} frames",
            f"{self.drops} drops",
            f"{self.reconnects} reconnects",
            f"{self.gaps} gaps" + (f" (last {self.last_gap_s:.2f} s)" if self.gaps else ""),
        ]
        if self.latency_s is not None:
            parts.append(f"latency {self.latency_s * 1e3:.1f} ms")
        if self.exposure is not None:
            parts.append(f"exposure {self.exposure:g}")
        if self.resolution is not None:
            parts.append(f"source {self.resolution[0]}x{self.resolution[1]}")
        return ", ".join(parts)


class CameraDriver(ABC):
    """Cameras that one service publishes. Grabbing all of them in one call lets a driver
    synchronise them (one render pass in sim, a hardware trigger on a real rig)."""

    @classmethod
    def from_config(cls, cfg: Any, *, rig: Rig, width: int, height: int) -> CameraDriver:
        """Build from the driver's typed config and the service's rig and frame size."""
        return cls(cfg, rig=rig, width=width, height=height)  # type: ignore[call-arg]

    @property
    @abstractmethod
    def cameras(self) -> dict[str, Camera]:
        """Name -> calibrated camera (pose in the world frame and intrinsics)."""

    @property
    @abstractmethod
    def size(self) -> tuple[int, int]:
        """(width, height) of every frame."""

    @abstractmethod
    def grab(self, stamp_ns: int) -> dict[str, Frame]:
        """One frame per camera, captured as close to ``stamp_ns`` as the driver can."""

    def stats(self) -> dict[str, CameraStats]:
        """Name -> what that camera delivered so far (default: nothing known, as in sim, where
        every camera renders every frame)."""
        return {}

    def close(self) -> None:
        """Release devices (default: nothing to release)."""
