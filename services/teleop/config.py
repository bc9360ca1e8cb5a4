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


class PolicyTeleopConfig(DriverConfig):
    """A policy served by ``viewscale serve`` (works in sim and on hardware)."""

    type: Literal["policy"] = "policy"
    server: str = "127.0.0.1:50051"  # the policy server's host:port
    views: list[str] | None = None  # cameras to compose (default: the server's default views)
    gamma: dict[str, float] | None = None  # composition weights (default: the server's, 1/V)
    blocking: bool = False  # wait for each chunk (lockstep sessions); real time: never block
    token: str | None = None  # bearer token of the server (VIEWSCALE_DRIVER__TOKEN)
    timeout_s: float = Field(30.0, gt=0)  # GetAction deadline
    connect_timeout_s: float = Field(60.0, gt=0)  # how long to wait for the server at start-up
    seed: int | None = None  # noise seed base; default: from the episode id (reproducible episodes)
    stats_file: str | None = None  # append each episode's runner statistics here (JSON lines)


TELEOP_DRIVERS: Registry[TeleopDriver] = Registry("teleop", TeleopDriver)
TELEOP_DRIVERS.register("scripted", "sim.backends:ScriptedTeleop", ScriptedTeleopConfig)
TELEOP_DRIVERS.register("policy", "services.teleop.policy:PolicyTeleop", PolicyTeleopConfig)


class TeleopConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    world: World = "sim"  # sim or real (shared top-level key): sim-only drivers are refused in a real session
    driver: TELEOP_DRIVERS.config_type() = ScriptedTeleopConfig()  # {type: scripted} or {type: package.module:Class}
    task_state_wait_s: float = Field(0.05, ge=0)  # how long to wait for a tick's task state after its robot state
    frame_wait_s: float = Field(0.05, ge=0)  # how long to wait for the cameras' frames of a tick (policy drivers)
    log_level: str = "INFO"  # logging level of the process

    @model_validator(mode="after")
    def _world(self) -> TeleopConfig:
        check_world(self.driver, self.world, "teleop")
        return self
