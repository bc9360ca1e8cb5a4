"""The robot service: a RobotDriver behind the control loop, ticking from start-up.

On hardware this is the process that owns the arm. With ``driver: {type: sim}`` it runs a MuJoCo arm
without cameras (useful to exercise a teleop source); full sim collection sessions use the sim
service instead, which runs the same loop with cameras and episode control.
"""

from __future__ import annotations

import logging
import threading

from services.core.bus import Bus
from services.core.runtime import refuse_rivals, serve
from services.robot.base import RobotDriver
from services.robot.config import ROBOT_DRIVERS, RobotConfig
from services.robot.loop import ControlLoop
from services.robot.safety import Safety

log = logging.getLogger(__name__)


def make_driver(cfg: RobotConfig) -> RobotDriver:
    return ROBOT_DRIVERS.build(cfg.driver, control_hz=cfg.control_hz)


class RobotService:
    def __init__(self, cfg: RobotConfig, bus: Bus, driver: RobotDriver):
        self.cfg = cfg
        self.bus = bus
        self.robot = Safety(driver, cfg.safety, cfg.control_hz)
        self.loop = ControlLoop(
            bus, self.robot, cfg.control_hz, cfg.realtime, cfg.command_timeout_s, cfg.command_wait_fraction
        )

    def __enter__(self) -> RobotService:
        refuse_rivals(self.bus, "robot", {"robot", "sim"})  # (before: both published robot/state)
        self.bus.announce("robot")
        return self

    def __exit__(self, *exc) -> None:
        self.robot.close()

    def run(self, stop: threading.Event) -> None:
        self.loop.run(stop)


def main(cfg: RobotConfig) -> int:
    driver = make_driver(cfg)  # a driver that cannot be built fails before the bus is opened
    return serve("robot", cfg.bus, lambda bus: RobotService(cfg, bus, driver), cfg.driver.type)
