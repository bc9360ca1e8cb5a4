from __future__ import annotations

from pydantic import Field

from services.core.bus import BusConfig
from services.core.config import Frozen
from services.robot.safety import SafetyConfig

# The sim's control rates: at most one tick per physics step (sim.scene.TIMESTEP, 2 ms); below
# 1 Hz an episode of a few hundred ticks would take hours of wall time.
MIN_CONTROL_HZ, MAX_CONTROL_HZ = 1.0, 500.0


class SimConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    rig: str = "five15"  # camera rig preset name (services/core/rigs) or path to a rig YAML
    task: str = "lift"  # scene loaded at start-up; each RESET may name another
    seed: int = 0  # seed of the start-up scene
    width: int = Field(84, ge=16)  # rendered frame width (px)
    height: int = Field(84, ge=16)  # rendered frame height (px)
    jpeg_quality: int = Field(90, ge=10, le=100)  # JPEG quality of published frames
    control_hz: float = Field(20.0, ge=MIN_CONTROL_HZ, le=MAX_CONTROL_HZ)  # control ticks per second
    safety: SafetyConfig = SafetyConfig()  # workspace box, speed caps, command timeout: as on hardware
    realtime: bool = True  # pace ticks by the wall clock; false: lockstep, as fast as commands come
    command_timeout_s: float = Field(1.0, gt=0)  # lockstep only: wait this long for a tick's command
    command_wait_fraction: float = Field(0.8, gt=0, le=1)  # real time: wait at most this part of a period
    calibration_period_s: float = Field(1.0, gt=0)  # republish calibration and camera poses this often
    log_level: str = "INFO"  # logging level of the process
