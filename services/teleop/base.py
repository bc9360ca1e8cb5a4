"""The teleop driver interface: anything that turns what the robot reports into EEF delta commands.

A teleop driver is chosen by the teleop service's ``driver`` config (``services.teleop.config``,
through ``services.core.registry``): the sim's scripted expert (``type: scripted``), a trained
policy behind the policy server (``type: policy``), or a lab's own class (``type:
package.module:Class``, with a nested ``Config`` for its settings). A driver that looks at the
cameras names them in ``cameras``; the service then hands it each camera's frame of the tick.
A driver an operator holds (the keyboard, the SpaceMouse: ``services/teleop/device.py``) also
gets the service's bus through ``attach``, for its episode keys.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from services.core.robot_types import EefDelta
from services.pb.sensors_pb2 import RobotState, TaskState

if TYPE_CHECKING:
    from services.core.bus import Bus


@dataclass(frozen=True)
class CameraFrame:
    jpeg: bytes  # as the camera published it
    stamp_ns: int  # capture time


class TeleopDriver(ABC):
    #: True when the driver needs the simulator's privileged TaskState (scripted experts).
    needs_task_state: bool = False
    #: Cameras whose frame of each tick the driver needs (a policy), in addition to the state.
    cameras: tuple[str, ...] = ()

    @classmethod
    def from_config(cls, cfg: Any) -> TeleopDriver:
        """Build from the driver's typed config (None for a class without a Config)."""
        return cls(cfg)  # type: ignore[call-arg]

    @abstractmethod
    def reset(self, task: str, episode_id: str = "") -> None:
        """A new episode begins (``task`` is empty where no task state says it)."""

    @abstractmethod
    def act(self, state: RobotState, task: TaskState | None, frames: dict[str, CameraFrame]) -> EefDelta:
        """The command answering ``state`` (same tick); ``frames``: one per camera in ``cameras``."""

    def attach(self, bus: Bus) -> None:
        """The service's open bus, before the first tick (default: unused). Drivers with episode keys
        send the recorder's control requests on it."""

    def interrupt(self) -> None:
        """The service is stopping: an ``act`` waiting (for a policy's chunk) returns now (default:
        nothing waits)."""

    def close(self) -> None:
        """Release the device (default: nothing to release)."""
