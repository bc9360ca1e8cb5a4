"""The camera service: grabs a camera group at a fixed rate and publishes frames and calibration.

In a sim collection session the sim service publishes the frames (it renders them in lockstep
with physics); this service runs a camera group on its own -- a real rig, or, with the sim
driver, a static rendered scene for checking a rig's placement and calibration.

A real camera can stop delivering (unplugged, a dropped stream). Its frames then simply stop:
nothing is published in their place. And so that a recording says so, each camera holds a
liveliness token ``alive/camera/<name>`` only while it delivers: the recorder flags an episode
in which a token went away (``service camera/FL lost liveliness mid-episode``) and in which it
came back. Every ``stats_period_s`` the service logs each camera's fps, drops and gaps.
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
from services.core.runtime import refuse_rivals, serve

log = logging.getLogger(__name__)


def make_driver(cfg: CameraConfig) -> CameraDriver:
    return CAMERA_DRIVERS.build(cfg.driver, rig=load_rig(cfg.rig), width=cfg.width, height=cfg.height)


class CameraService:
    def __init__(self, cfg: CameraConfig, bus: Bus, driver: CameraDriver):
        self.cfg = cfg
        self.bus = bus
        self.driver = driver
        self.publisher = CameraPublisher(bus, driver, cfg.jpeg_quality)
        self._tokens: dict[str, object] = {}  # camera -> its liveliness token, held while it delivers

    def __enter__(self) -> CameraService:
        # a sim publishes every camera; another camera service publishing one of these is a rival too
        refuse_rivals(self.bus, "camera", {"sim"} | {f"camera/{n}" for n in self.driver.cameras})
        self.bus.announce("camera")
        self._update_presence()
        return self

    def __exit__(self, *exc) -> None:
        self.driver.close()
        for name in list(self._tokens):
            self._withdraw(name)

    def _update_presence(self) -> None:
        """Hold ``alive/camera/<name>`` exactly while that camera delivers (drivers without stats:
        always)."""
        stats = self.driver.stats()
        for name in self.driver.cameras:
            delivering = stats[name].connected if name in stats else True
            if delivering and name not in self._tokens:
                self._tokens[name] = self.bus.presence(f"camera/{name}")
            elif not delivering and name in self._tokens:
                log.warning("camera %s is not delivering: withdrawn from the bus until it is back", name)
                self._withdraw(name)

    def _withdraw(self, name: str) -> None:
        token = self._tokens.pop(name)
        try:
            token.undeclare()  # type: ignore[attr-defined]
        except Exception:  # the session is already closing underneath
            log.debug("liveliness token of camera %s already gone", name)

    def log_stats(self) -> None:
        for name, st in self.driver.stats().items():
            log.log(logging.INFO if st.connected else logging.WARNING, "camera %s: %s", name, st.summary())

    def run(self, stop: threading.Event) -> None:
        rate = Rate(self.cfg.fps)
        last_calib = 0.0
        last_stats = time.monotonic()
        while not stop.is_set():
            if time.monotonic() - last_calib >= self.cfg.calibration_period_s:
                self.publisher.publish_calibration(now_ns())
                last_calib = time.monotonic()
            self.publisher.publish_frames(self.driver.grab(now_ns()))
            self._update_presence()
            if time.monotonic() - last_stats >= self.cfg.stats_period_s:
                self.log_stats()
                last_stats = time.monotonic()
            rate.sleep()
        self.log_stats()
        log.info("camera stopped after %d frame sets (%d overruns)", self.publisher.frames_published, rate.overruns)


def main(cfg: CameraConfig) -> int:
    driver = make_driver(cfg)  # a driver that cannot be built fails before the bus is opened
    return serve("camera", cfg.bus, lambda bus: CameraService(cfg, bus, driver), f"{cfg.driver.type}/{cfg.rig}")
