from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from services.core.bus import BusConfig
from services.core.config import Frozen, LogLevel
from services.core.registry import DriverConfig, Registry, World, check_world
from services.robot.base import RobotDriver
from services.robot.gripper import Gripper
from services.robot.safety import SafetyConfig


class SimRobotConfig(DriverConfig):
    """The MuJoCo arm (without cameras, to exercise a teleop driver)."""

    sim_only = True

    type: Literal["sim"] = "sim"
    task: str = "lift"  # the scene to load
    seed: int = 0  # scene randomisation seed


class NullGripperConfig(DriverConfig):
    """No gripper, or one driven by something else: the commanded closure is reported back."""

    type: Literal["none"] = "none"


class RobotiqGripperConfig(DriverConfig):
    """A Robotiq 2F-85 / 2F-140 / Hand-E through the Robotiq URCap's ASCII socket on the controller."""

    type: Literal["robotiq"] = "robotiq"
    host: str = ""  # the socket's host; '' = the arm controller's (where the URCap runs)
    port: int = Field(63352, ge=1, le=65535)  # the URCap's gripper socket
    speed: int = Field(255, ge=0, le=255)  # finger speed, the gripper's raw 0..255
    force: int = Field(100, ge=0, le=255)  # grip force, the gripper's raw 0..255
    timeout_s: float = Field(1.0, gt=0)  # connect and per-request timeout
    activate: bool = True  # activate the gripper at start-up if it is not (its fingers move once)
    activation_timeout_s: float = Field(10.0, gt=0)  # how long activation may take


GRIPPERS: Registry[Gripper] = Registry("gripper", Gripper)
GRIPPERS.register("none", "services.robot.gripper:NullGripper", NullGripperConfig)
GRIPPERS.register("robotiq", "services.robot.gripper:RobotiqGripper", RobotiqGripperConfig)

Pose6 = tuple[float, float, float, float, float, float]


class URRobotConfig(DriverConfig):
    """A Universal Robots arm (CB3 or e-Series) through ur-rtde: RTDE state, servoL towards a target pose."""

    type: Literal["ur"] = "ur"
    host: str  # the controller's IP address or hostname (remote control mode on e-Series)
    frequency: float | None = Field(None, gt=0)  # RTDE rate (Hz); None: the controller's (125 CB3, 500 e-Series)
    lookahead_time: float = Field(0.1, ge=0.03, le=0.2)  # servoL smoothing (s): longer is smoother, lags more
    gain: float = Field(300.0, ge=100, le=2000)  # servoL proportional gain: higher tracks tighter, may shake
    stop_deceleration: float = Field(10.0, gt=0)  # servoStop's deceleration (m/s^2)
    tcp_offset: Pose6 | None = None  # TCP in the flange frame [x, y, z, rx, ry, rz] (m, rad); None: the pendant's
    gripper: GRIPPERS.config_type() = NullGripperConfig()  # {type: none}, {type: robotiq, ...} or package.module:Class
    reconnect_interval_s: float = Field(2.0, gt=0)  # after a fault: how often to try to reconnect and resume
    # how far the servo target may run ahead of the measured TCP: an arm held back (pushing on the
    # table or an object) is not sent further, so it does not leap when it comes free
    max_lead_m: float = Field(0.1, gt=0)  # m (tracking lags about speed x lookahead_time: 2.5 cm at 0.25 m/s)
    max_lead_rad: float = Field(0.6, gt=0)  # rad


ROBOT_DRIVERS: Registry[RobotDriver] = Registry("robot", RobotDriver)
ROBOT_DRIVERS.register("sim", "sim.backends:SimRobot", SimRobotConfig)
ROBOT_DRIVERS.register("ur", "services.robot.ur:UR", URRobotConfig)


class RobotConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    world: World = "sim"  # sim or real (shared top-level key): sim-only drivers are refused in a real session
    driver: ROBOT_DRIVERS.config_type() = SimRobotConfig()  # {type: sim, ...} or {type: package.module:Class, ...}
    safety: SafetyConfig = SafetyConfig()  # workspace box, speed caps, command timeout (every driver)
    control_hz: float = Field(20.0, gt=0)  # control ticks per second
    realtime: bool = True  # pace ticks by the wall clock (always true on hardware)
    command_timeout_s: float = Field(0.5, gt=0)  # lockstep only: wait this long for a tick's command
    command_wait_fraction: float = Field(0.8, gt=0, le=1)  # real time: wait at most this part of a period
    log_level: LogLevel = "INFO"  # logging level of the process

    @model_validator(mode="after")
    def _world(self) -> RobotConfig:
        check_world(self.driver, self.world, "robot")
        return self
