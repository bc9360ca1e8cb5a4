from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from services.core.bus import BusConfig
from services.core.config import Frozen, LogLevel
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
    # a server that serves TLS (`viewscale serve --set tls.cert=...`): the PEM file of the CA that
    # signed its certificate (a self-signed certificate is its own CA); None: plaintext
    tls_ca: str | None = None
    timeout_s: float = Field(30.0, gt=0)  # GetAction deadline
    connect_timeout_s: float = Field(60.0, gt=0)  # how long to wait for the server at start-up
    seed: int | None = None  # noise seed base; default: from the episode id (reproducible episodes)
    stats_file: str | None = None  # append each episode's runner statistics here (JSON lines)
    # drive the arm between the recorder's episodes too; by default it holds still there (states
    # that name no episode: a hardware session between `viewscale episode stop` and the next start)
    outside_episodes: bool = False
    # a policy whose actions or states are in the camera frame holds still, from the first tick it
    # would drive, at most this long until each view's calibration and pose are heard (camera services
    # publish them once a second) and checked against the server's; none heard by then: it drives, said once
    calibration_wait_s: float = Field(3.0, ge=0)


class DeviceTeleopConfig(DriverConfig):
    """What every hand-held device shares (``services/teleop/device.py``): a full deflection (a held
    key, the puck pushed all the way) commands ``speed`` x the max per-tick step; episode keys
    drive the recorder's control queryable and record these task/rig/rate with the episode."""

    max_dp: float = Field(0.02, gt=0, le=0.1)  # m per tick at full deflection, speed 1 (the expert's free-space step)
    max_drot: float = Field(0.1, gt=0, le=0.5)  # rad per tick at full deflection, speed 1 (the scripted expert's cap)
    speed: float = Field(0.5, gt=0, le=1)  # fraction of max_dp and max_drot commanded at full deflection
    task: str = ""  # task name recorded with episodes started from the device
    rig: str = ""  # rig name recorded with those episodes
    control_hz: float = Field(20.0, gt=0)  # control rate recorded with those episodes
    episode_timeout_s: float = Field(30.0, gt=0)  # how long an episode key waits for the recorder's answer


class KeyboardTeleopConfig(DeviceTeleopConfig):
    """Keys of a plain terminal (no X server): ``services/teleop/keyboard.py`` lists them."""

    type: Literal["keyboard"] = "keyboard"
    tty: str | None = None  # terminal to read keys from (e.g. /dev/pts/3); default: stdin, which must be a terminal
    speed: float = Field(0.25, gt=0, le=1)  # starting fraction of max_dp and max_drot; '-' and '=' change it
    speed_step: float = Field(1.5, gt=1)  # '=' multiplies the speed by this, '-' divides it (within 0.05 and 1)
    deadman_ms: float = Field(600.0, gt=0)  # a key not seen again this long holds still (> the key-repeat delay)
    repeat_ms: float = Field(150.0, gt=0)  # once a key auto-repeats: hold still this long after its last repeat

    @model_validator(mode="after")
    def _windows(self) -> KeyboardTeleopConfig:
        if self.repeat_ms > self.deadman_ms:
            raise ValueError(f"repeat_ms ({self.repeat_ms}) must not exceed deadman_ms ({self.deadman_ms})")
        return self


class SpaceMouseTeleopConfig(DeviceTeleopConfig):
    """A 3Dconnexion SpaceMouse through ``pyspacemouse`` (``pip install -e '.[hardware]'``):
    ``services/teleop/spacemouse.py`` lists its buttons."""

    type: Literal["spacemouse"] = "spacemouse"
    device: str | None = None  # pyspacemouse name (SpaceMouseCompact, ...); default: the first found
    device_index: int = Field(0, ge=0)  # which of several connected devices of that name
    path: str | None = None  # open this HID node (e.g. /dev/hidraw3) instead of searching by name
    speed: float = Field(1.0, gt=0, le=1)  # fraction of max_dp and max_drot at full deflection of the puck
    deadzone: float = Field(0.05, ge=0, lt=1)  # fraction of full deflection read as zero, per axis (rest is never 0)
    yaw_deg: float = 0.0  # puck frame turned about base z; 0: puck right/away/up = base +x/+y/+z
    rotation: bool = True  # False: ignore the puck's tilt and twist (translation and gripper only)
    deadman_ms: float = Field(100.0, gt=0)  # no report for this long: hold still (a displaced puck reports every ~8 ms)
    gripper_button: str = "LEFT"  # click: toggle the gripper; long press while recording: stop the episode as a failure
    episode_button: str = "RIGHT"  # long press: start an episode, or stop the recording one as a success
    long_press_s: float = Field(1.0, gt=0)  # how long a button is held for an episode command (both held: discard)
    poll_ms: float = Field(4.0, gt=0)  # how often the device is read for new reports


TELEOP_DRIVERS: Registry[TeleopDriver] = Registry("teleop", TeleopDriver)
TELEOP_DRIVERS.register("scripted", "sim.backends:ScriptedTeleop", ScriptedTeleopConfig)
TELEOP_DRIVERS.register("policy", "services.teleop.policy:PolicyTeleop", PolicyTeleopConfig)
TELEOP_DRIVERS.register("keyboard", "services.teleop.keyboard:KeyboardTeleop", KeyboardTeleopConfig)
TELEOP_DRIVERS.register("spacemouse", "services.teleop.spacemouse:SpaceMouseTeleop", SpaceMouseTeleopConfig)


class TeleopConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    world: World = "sim"  # sim or real (shared top-level key): sim-only drivers are refused in a real session
    driver: TELEOP_DRIVERS.config_type() = ScriptedTeleopConfig()  # {type: scripted} or {type: package.module:Class}
    task_state_wait_s: float = Field(0.05, ge=0)  # how long to wait for a tick's task state after its robot state
    frame_wait_s: float = Field(0.05, ge=0)  # how long to wait for the cameras' frames of a tick (policy drivers)
    # a camera that sent no frame for this long has stalled or gone: no command (the arm holds still)
    # until it sends again, rather than a policy driving on its last frame (policy drivers)
    max_frame_gap_s: float = Field(1.0, gt=0)
    log_level: LogLevel = "INFO"  # logging level of the process

    @model_validator(mode="after")
    def _world(self) -> TeleopConfig:
        check_world(self.driver, self.world, "teleop")
        return self
