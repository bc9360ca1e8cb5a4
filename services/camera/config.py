from __future__ import annotations

from typing import Literal

from pydantic import Field

from services.core.bus import BusConfig
from services.core.config import Frozen


class CameraConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    backend: Literal["sim"] = "sim"  # camera hardware; USB/RTSP capture comes behind the same interface
    rig: str = "five15"  # rig preset or YAML: names, poses and intrinsics of the cameras
    task: str = "lift"  # sim backend only: the scene to render
    seed: int = 0  # sim backend only: scene seed
    width: int = Field(84, ge=16)  # frame width (px)
    height: int = Field(84, ge=16)  # frame height (px)
    fps: float = Field(20.0, gt=0)  # frames per second per camera
    jpeg_quality: int = Field(90, ge=10, le=100)  # JPEG quality of published frames
    calibration_period_s: float = Field(1.0, gt=0)  # republish calibration and poses this often
    log_level: str = "INFO"  # logging level of the process
