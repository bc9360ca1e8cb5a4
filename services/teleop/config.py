from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from services.core.bus import BusConfig
from services.core.config import Frozen
from services.core.registry import DriverConfig, Registry, World, check_world
from services.teleop.base import TeleopDriver


class ScriptedTeleopConfig(DriverConfig):
    """The scripted experts read the sim's privileged task state, which a real robot does not
    publish: every tick would be held still as stale."""

    sim_only = True
    type: Literal["scripted"] = "scripted"


TELEOP_DRIVERS: Registry[TeleopDriver] = Registry("teleop", TeleopDriver)
TELEOP_DRIVERS.register("scripted", "sim.backends:ScriptedTeleop", ScriptedTeleopConfig)


class TeleopConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    world: World = "sim"  # sim or real (shared top-level key): sim-only drivers are refused in a real session
    driver: TELEOP_DRIVERS.config_type() = ScriptedTeleopConfig()  # {type: scripted} or {type: package.module:Class}
    task_state_wait_s: float = Field(0.05, ge=0)  # how long to wait for a tick's task state after its robot state
    log_level: str = "INFO"  # logging level of the process

    @model_validator(mode="after")
    def _world(self) -> TeleopConfig:
        check_world(self.driver, self.world, "teleop")
        return self
