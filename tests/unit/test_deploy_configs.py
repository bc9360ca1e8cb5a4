"""The shipped session files are valid as they stand: every service section of deploy/sim.yaml and
deploy/real.yaml loads into its service's config (the drivers are typed by the registry, so a
misspelt key or a driver name that does not exist fails here, not on the lab's first day)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.camera.config import CameraConfig, OpenCVCameraConfig
from services.core.config import load_config
from services.recorder.config import RecorderConfig
from services.robot.config import RobotConfig, URRobotConfig
from services.teleop.config import SpaceMouseTeleopConfig, TeleopConfig

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "section, model",
    [("robot", RobotConfig), ("camera", CameraConfig), ("teleop", TeleopConfig), ("recorder", RecorderConfig)],
)
def test_every_section_of_the_real_session_file_loads(section, model):
    cfg = load_config(model, ROOT / "deploy" / "real.yaml", section=section, environ={})
    assert cfg.bus.mode == "client"
    if hasattr(cfg, "world"):
        assert cfg.world == "real"


def test_the_real_session_file_names_hardware_drivers():
    env: dict[str, str] = {}
    robot = load_config(RobotConfig, ROOT / "deploy" / "real.yaml", section="robot", environ=env)
    camera = load_config(CameraConfig, ROOT / "deploy" / "real.yaml", section="camera", environ=env)
    teleop = load_config(TeleopConfig, ROOT / "deploy" / "real.yaml", section="teleop", environ=env)
    assert isinstance(robot.driver, URRobotConfig) and robot.driver.gripper.type == "robotiq"
    assert isinstance(camera.driver, OpenCVCameraConfig) and set(camera.driver.cameras) == {"F", "FL", "FR"}
    assert isinstance(teleop.driver, SpaceMouseTeleopConfig)
