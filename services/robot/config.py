from __future__ import annotations

from typing import Any

from pydantic import Field

from services.core.bus import BusConfig
from services.core.config import Frozen


class RobotConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    driver: str = "sim"  # "sim" (a MuJoCo arm without cameras) or "package.module:ClassName"
    driver_args: dict[str, Any] = Field(default_factory=dict)  # keyword arguments for the driver class
    task: str = "lift"  # sim driver only: the scene to load
    seed: int = 0  # sim driver only: scene randomisation seed
    control_hz: float = Field(20.0, gt=0)  # control ticks per second
    realtime: bool = True  # pace ticks by the wall clock (always true on hardware)
    command_timeout_s: float = Field(0.5, gt=0)  # lockstep only: wait this long for a tick's command
    command_wait_fraction: float = Field(0.8, gt=0, le=1)  # real time: wait at most this part of a period
    log_level: str = "INFO"  # logging level of the process
