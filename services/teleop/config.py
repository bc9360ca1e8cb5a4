from __future__ import annotations

from typing import Literal

from pydantic import Field

from services.core.bus import BusConfig
from services.core.config import Frozen


class TeleopConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    source: Literal["scripted"] = "scripted"  # command source; devices for a person come later
    task_state_wait_s: float = Field(0.05, ge=0)  # how long to wait for a tick's task state after its robot state
    log_level: str = "INFO"  # logging level of the process
