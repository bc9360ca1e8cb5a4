from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from services.camera.base import CameraDriver
from services.core.bus import BusConfig
from services.core.config import Frozen
from services.core.registry import DriverConfig, Registry, World, check_world


class SimCameraConfig(DriverConfig):
    """The rig's cameras rendered by MuJoCo from a static scene (placement and calibration checks)."""

    sim_only = True

    type: Literal["sim"] = "sim"
    task: str = "lift"  # the scene to render
    seed: int = 0  # scene seed


CAMERA_DRIVERS: Registry[CameraDriver] = Registry("camera", CameraDriver)
CAMERA_DRIVERS.register("sim", "sim.backends:SimCamera", SimCameraConfig)


class CameraConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    world: World = "sim"  # sim or real (shared top-level key): sim-only drivers are refused in a real session
    driver: CAMERA_DRIVERS.config_type() = SimCameraConfig()  # {type: sim} or {type: package.module:Class, ...}
    rig: str = "five15"  # rig preset or YAML: names, poses and intrinsics of the cameras
    width: int = Field(84, ge=16)  # frame width (px)
    height: int = Field(84, ge=16)  # frame height (px)
    fps: float = Field(20.0, gt=0)  # frames per second per camera
    jpeg_quality: int = Field(90, ge=10, le=100)  # JPEG quality of published frames
    calibration_period_s: float = Field(1.0, gt=0)  # republish calibration and poses this often
    log_level: str = "INFO"  # logging level of the process

    @model_validator(mode="after")
    def _world(self) -> CameraConfig:
        check_world(self.driver, self.world, "camera")
        return self
