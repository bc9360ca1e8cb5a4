"""The camera service: grabs a camera group at a fixed rate and publishes frames and calibration.

In a sim collection session the sim service publishes the frames (it renders them in lockstep
with physics); this service runs a camera group on its own -- a real rig, or, with the sim
backend, a static rendered scene for checking a rig's placement and calibration.
"""

from __future__ import annotations

import logging
import threading
import time

from services.camera.backends.base import CameraBackend
from services.camera.config import CameraConfig
from services.camera.publisher import CameraPublisher
from services.core.bus import Bus
from services.core.clock import Rate, now_ns
from services.core.runtime import serve

log = logging.getLogger(__name__)


def make_backend(cfg: CameraConfig) -> CameraBackend:
    if cfg.backend == "sim":
        from services.camera.backends.sim import SimCameraBackend
        from services.core.rig import load_rig
        from sim.world import SimWorld

        world = SimWorld(cfg.task, load_rig(cfg.rig), cfg.width, cfg.height)
        world.reset(cfg.seed)
        return SimCameraBackend(world, cfg.width, cfg.height)
    raise ValueError(f"unknown camera backend {cfg.backend!r}")


class CameraService:
    def __init__(self, cfg: CameraConfig, bus: Bus, backend: CameraBackend):
        self.cfg = cfg
        self.bus = bus
        self.backend = backend
        self.publisher = CameraPublisher(bus, backend, cfg.jpeg_quality)

    def __enter__(self) -> "CameraService":
        self.bus.announce("camera")
        return self

    def __exit__(self, *exc) -> None:
        self.backend.close()

    def run(self, stop: threading.Event) -> None:
        rate = Rate(self.cfg.fps)
        last_calib = 0.0
        while not stop.is_set():
            if time.monotonic() - last_calib >= self.cfg.calibration_period_s:
                self.publisher.publish_calibration(now_ns())
                last_calib = time.monotonic()
            self.publisher.publish_frames(self.backend.grab(now_ns()))
            rate.sleep()
        log.info("camera stopped after %d frame sets (%d overruns)", self.publisher.frames_published, rate.overruns)


def main(cfg: CameraConfig) -> int:
    return serve("camera", cfg.bus, lambda bus: CameraService(cfg, bus, make_backend(cfg)), f"{cfg.backend}/{cfg.rig}")
