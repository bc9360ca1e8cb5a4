"""The camera backend interface: a group of calibrated cameras grabbed together."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from services.core.rig import Camera


@dataclass(frozen=True)
class Frame:
    rgb: np.ndarray  # (H, W, 3) uint8
    stamp_ns: int  # capture time, Unix ns


class CameraBackend(ABC):
    """Cameras that one service publishes. Grabbing all of them in one call lets a backend
    synchronise them (one render pass in sim, a hardware trigger on a real rig)."""

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
        """One frame per camera, captured as close to ``stamp_ns`` as the backend can."""

    def close(self) -> None:
        """Release devices (default: nothing to release)."""
