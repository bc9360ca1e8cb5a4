"""Publishing a camera group: JPEG frames, calibration and pose on the rig's topics."""

from __future__ import annotations

from services.camera.base import CameraDriver, Frame
from services.core import topics
from services.core.bus import Bus
from services.core.tensors import compressed_image


class CameraPublisher:
    def __init__(self, bus: Bus, driver: CameraDriver, jpeg_quality: int = 90):
        self.driver = driver
        self.jpeg_quality = jpeg_quality
        self._image = {n: bus.publisher(topics.camera_image(n)) for n in driver.cameras}
        self._calib = {n: bus.publisher(topics.camera_calibration(n)) for n in driver.cameras}
        self._pose = {n: bus.publisher(topics.camera_pose(n)) for n in driver.cameras}
        self.frames_published = 0

    def publish_frames(self, frames: dict[str, Frame]) -> None:
        """Publish what the driver grabbed; a camera without a new frame is simply not in ``frames``."""
        if not frames:
            return
        for name, frame in frames.items():
            self._image[name].put(compressed_image(frame.rgb, frame.stamp_ns, name, self.jpeg_quality))
        self.frames_published += 1

    def publish_calibration(self, stamp_ns: int) -> None:
        width, height = self.driver.size
        for name, cam in self.driver.cameras.items():
            self._calib[name].put(cam.calibration_msg(width, height, stamp_ns))
            self._pose[name].put(cam.pose_msg(stamp_ns))
