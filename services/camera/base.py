"""The camera driver interface: a group of calibrated cameras grabbed together.

A camera driver is chosen by the camera service's ``driver`` config (``services.camera.config``,
through ``services.core.registry``): the sim's rendered cameras (``type: sim``) or a lab's own
class (``type: package.module:Class``). To add one, subclass ``CameraDriver``, give it a nested
``Config`` (a frozen pydantic model) if it takes settings, and implement the four members below;
``from_config`` builds it from that config and the camera service's rig and frame size.
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

    def close(self) -> None:
        """Release devices (default: nothing to release)."""
