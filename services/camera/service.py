"""The camera service: grabs a camera group at a fixed rate and publishes frames and calibration.

In a sim collection session the sim service publishes the frames (it renders them in lockstep
with physics); this service runs a camera group on its own -- a real rig, or, with the sim
driver, a static rendered scene for checking a rig's placement and calibration.
"""

from __future__ import annotations

import logging
import threading
import time

from services.camera.base import CameraDriver
from services.camera.config import CAMERA_DRIVERS, CameraConfig
from services.camera.publisher import CameraPublisher
from services.core.bus import Bus
from services.core.clock import Rate, now_ns
from services.core.rig import load_rig
from services.core.runtime import serve

log = logging.getLogger(__name__)


def make_driver(cfg: CameraConfig) -> CameraDriver:
    return CAMERA_DRIVERS.build(cfg.driver, rig=load_rig(cfg.rig), width=cfg.width, height=cfg.height)


class CameraService:
    def __init__(self, cfg: CameraConfig, bus: Bus, driver: CameraDriver):
        self.cfg = cfg
        self.bus = bus
        self.driver = driver
        self.publisher = CameraPublisher(bus, driver, cfg.jpeg_quality)

    def __enter__(self) -> CameraService:
        self.bus.announce("camera")
        return self

    def __exit__(self, *exc) -> None:
        self.driver.close()

    def run(self, stop: threading.Event) -> None:
        rate = Rate(self.cfg.fps)
        last_calib = 0.0
        while not stop.is_set():
            if time.monotonic() - last_calib >= self.cfg.calibration_period_s:
                self.publisher.publish_calibration(now_ns())
                last_calib = time.monotonic()
            self.publisher.publish_frames(self.driver.grab(now_ns()))
            rate.sleep()
        log.info("camera stopped after %d frame sets (%d overruns)", self.publisher.frames_published, rate.overruns)


def main(cfg: CameraConfig) -> int:
    driver = make_driver(cfg)  # a driver that cannot be built fails before the bus is opened
    return serve("camera", cfg.bus, lambda bus: CameraService(cfg, bus, driver), f"{cfg.driver.type}/{cfg.rig}")
