"""Simulated cameras: render the rig's cameras from a shared MuJoCo ``SimWorld``."""

from __future__ import annotations

from services.camera.backends.base import CameraBackend, Frame
from services.core.rig import Camera


class SimCameraBackend(CameraBackend):
    def __init__(self, world, width: int, height: int):
        self.world = world  # sim.world.SimWorld; its scene holds one MuJoCo camera per rig camera
        self._size = (width, height)

    @property
    def cameras(self) -> dict[str, Camera]:
        return self.world.rig.cameras

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def grab(self, stamp_ns: int) -> dict[str, Frame]:
        # In sim the capture time is the simulated instant all cameras share.
        return {name: Frame(rgb, stamp_ns) for name, rgb in self.world.render().items()}
