"""The robot service: a RobotDriver behind the control loop, ticking from start-up.

On hardware this is the process that owns the arm. Its states name the episode the recorder is
recording (from the recorder's announcements on ``recorder/episode``), and none between episodes.
With ``driver: {type: sim}`` it runs a MuJoCo arm without cameras (useful to exercise a teleop
source); full sim collection sessions use the sim service instead, which runs the same loop with
cameras and episode control.
"""

from __future__ import annotations

import logging
import threading

from services.core import topics
from services.core.bus import Bus
from services.core.runtime import refuse_rivals, serve
from services.pb.episode_pb2 import EpisodeMeta
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
        bus.subscribe(topics.EPISODE, self._on_episode)

    def _on_episode(self, meta: EpisodeMeta, _rx) -> None:
        """The recorder's episodes: the states name the one being recorded, and none between them (a
        policy teleop drives the arm only within an episode; the sim's session names its own)."""
        if meta.end_ns == 0:
            self.loop.episode_id = meta.episode_id
            log.info("episode %s started: the states name it", meta.episode_id)
        elif meta.episode_id == self.loop.episode_id:
            self.loop.episode_id = ""
            log.info("episode %s closed", meta.episode_id)

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
