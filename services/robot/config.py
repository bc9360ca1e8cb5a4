from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from services.core.bus import BusConfig
from services.core.config import Frozen
from services.core.registry import DriverConfig, Registry, World, check_world
from services.robot.base import RobotDriver
from services.robot.safety import SafetyConfig


class SimRobotConfig(DriverConfig):
    """The MuJoCo arm (without cameras, to exercise a teleop driver)."""

    sim_only = True

    type: Literal["sim"] = "sim"
    task: str = "lift"  # the scene to load
    seed: int = 0  # scene randomisation seed


ROBOT_DRIVERS: Registry[RobotDriver] = Registry("robot", RobotDriver)
ROBOT_DRIVERS.register("sim", "sim.backends:SimRobot", SimRobotConfig)


class RobotConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    world: World = "sim"  # sim or real (shared top-level key): sim-only drivers are refused in a real session
    driver: ROBOT_DRIVERS.config_type() = SimRobotConfig()  # {type: sim, ...} or {type: package.module:Class, ...}
    safety: SafetyConfig = SafetyConfig()  # workspace box, speed caps, command timeout (every driver)
    control_hz: float = Field(20.0, gt=0)  # control ticks per second
    realtime: bool = True  # pace ticks by the wall clock (always true on hardware)
    command_timeout_s: float = Field(0.5, gt=0)  # lockstep only: wait this long for a tick's command
    command_wait_fraction: float = Field(0.8, gt=0, le=1)  # real time: wait at most this part of a period
    log_level: str = "INFO"  # logging level of the process

    @model_validator(mode="after")
    def _world(self) -> RobotConfig:
        check_world(self.driver, self.world, "robot")
        return self
