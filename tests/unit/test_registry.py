"""Drivers chosen by name or import path, with typed settings (services/core/registry.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Literal

import pytest
from pydantic import ValidationError

from services.core.config import ConfigError, Frozen, load_config
from services.core.registry import DriverConfig, Registry

ROOT = Path(__file__).resolve().parents[2]


class Arm:
    """A stand-in interface: built with its typed config and the context the service passes."""

    @classmethod
    def from_config(cls, cfg, **context):
        return cls(cfg, **context)

    def __init__(self, cfg, **context):
        self.cfg, self.context = cfg, context


class FakeArmConfig(DriverConfig):
    type: Literal["fake"] = "fake"
    speed: float = 1.0


class LabArm(Arm):
    class Config(Frozen):
        host: str
        port: int = 30004


class BareArm(Arm):
    pass


class NotAnArm:
    pass


ARMS: Registry[Arm] = Registry("arm", Arm)
ARMS.register("fake", f"{__name__}:Arm", FakeArmConfig)


class ServiceConfig(Frozen):
    driver: ARMS.config_type() = FakeArmConfig()


def test_a_registered_name_gets_its_typed_config_and_the_context():
    cfg = ServiceConfig.model_validate({"driver": {"type": "fake", "speed": 2.5}})
    assert isinstance(cfg.driver, FakeArmConfig) and cfg.driver.speed == 2.5
    arm = ARMS.build(cfg.driver, control_hz=20.0)
    assert type(arm) is Arm and arm.cfg is cfg.driver and arm.context == {"control_hz": 20.0}
    assert ServiceConfig().driver == FakeArmConfig()
    with pytest.raises(ValidationError, match="speed"):
        ServiceConfig.model_validate({"driver": {"type": "fake", "speed": "fast"}})
    with pytest.raises(ValidationError, match="Extra inputs"):
        ServiceConfig.model_validate({"driver": {"type": "fake", "sped": 1}})


def test_a_labs_own_class_is_validated_against_its_config():
    cfg = ServiceConfig.model_validate({"driver": {"type": f"{__name__}:LabArm", "host": "10.0.0.2"}})
    arm = ARMS.build(cfg.driver)
    assert isinstance(arm, LabArm) and arm.cfg == LabArm.Config(host="10.0.0.2", port=30004)
    bad = ServiceConfig.model_validate({"driver": {"type": f"{__name__}:LabArm", "hots": "10.0.0.2"}})
    with pytest.raises(ConfigError, match=f"invalid settings for arm driver {__name__}:LabArm"):
        ARMS.build(bad.driver)
    bare = ServiceConfig.model_validate({"driver": {"type": f"{__name__}:BareArm", "host": "x"}})
    with pytest.raises(ConfigError, match="declares no Config"):
        ARMS.build(bare.driver)
    assert ARMS.build(ServiceConfig.model_validate({"driver": {"type": f"{__name__}:BareArm"}}).driver).cfg is None


def test_unknown_names_and_wrong_classes_are_clear_errors():
    with pytest.raises(ValidationError, match="unknown arm driver 'nope': choose one of fake"):
        ServiceConfig.model_validate({"driver": {"type": "nope"}})
    with pytest.raises(ConfigError, match="not a Arm"):
        ARMS.build(ServiceConfig.model_validate({"driver": {"type": f"{__name__}:NotAnArm"}}).driver)
    with pytest.raises(ConfigError, match="has no class 'Missing'"):
        ARMS.build(ServiceConfig.model_validate({"driver": {"type": f"{__name__}:Missing"}}).driver)
    with pytest.raises(ValueError, match="registered twice"):
        ARMS.register("fake", f"{__name__}:Arm", FakeArmConfig)


def test_the_type_can_be_switched_from_the_command_line(tmp_path):
    yaml = tmp_path / "svc.yaml"
    yaml.write_text("svc:\n  driver: {type: fake, speed: 3}\n")
    cfg = load_config(ServiceConfig, yaml, ["driver.speed=4"], environ={}, section="svc")
    assert cfg.driver == FakeArmConfig(speed=4.0)


def test_the_teleop_process_never_loads_mujoco():
    # The scripted expert reads the sim's task state over the bus; MuJoCo is for the simulating drivers.
    code = (
        "import sys; from services.teleop.config import TeleopConfig; from services.teleop.service import "
        "make_driver; d = make_driver(TeleopConfig()); d.reset('lift'); "
        "print(type(d).__name__, 'mujoco' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ScriptedTeleop", "False"]
