"""Universal Robots arms (CB3, e-Series) through ur-rtde: the reference hardware robot driver.

``driver: {type: ur, host: 192.168.1.10, gripper: {type: robotiq}}`` (``URRobotConfig``).

State. ``RTDEReceiveInterface(host, frequency)`` streams the controller's state in ur-rtde's own
thread at the RTDE rate (125 Hz on CB3, up to 500 Hz on e-Series); ``read`` takes the newest
sample: the TCP pose (``getActualTCPPose``), joints (``getActualQ``, ``getActualQd``) and the
gripper's closure.

Poses. UR poses are ``[x, y, z, rx, ry, rz]``: metres and a rotation vector (the unit axis times
the angle, rad) of the TCP in the robot's base frame, as the teach pendant shows it with the
"Base" feature. That frame is this driver's base frame: ``RobotSnapshot`` carries the position and
the rotation as a w-first quaternion (``ur_pose_to_pos_quat``), and camera extrinsics must be
calibrated against the same frame (hand-eye with poses from this driver does that).

Motion. The driver keeps a target TCP pose, taken from the measured pose when servoing starts.
Each tick's ``EefDelta`` moves it (``p += dp``, ``R = Rot(drot) @ R``, ``apply_delta``), and
``servoL(target, speed, acceleration, 1 / control_hz, lookahead_time, gain)`` sends it: the
controller servos there over one control period, smoothed by the lookahead time and gain. The
safety layer bounds the target, not just the measured pose, by the workspace box
(``target_position``), and the driver keeps it within ``max_lead_m`` and ``max_lead_rad`` of the
measured pose: an arm held back (pushing on the table or an object) falls behind its target, and an
unbounded target would have it leap the whole gap when it came free (said once per such stretch in
the log). A hold sends nothing: the controller's servo thread stays on the last target. ``stop``
(commands stopped coming, or a fault began) is ``servoStop``, and the next motion starts from the
measured pose again, so the arm never jumps back to an old target.

Faults. Every ``read`` checks the connection of both interfaces, protective and emergency stops,
the safety mode (normal or reduced) and the robot mode (running); a ``servoL`` the controller
refuses, an SDK call that raises, or a gripper that cannot be reached is a fault too. ``fault``
reports it: the safety layer stops the arm, sends nothing more and the recorder flags the
episode (``services.robot.safety``). While it lasts a recovery thread tries, every
``reconnect_interval_s``, to reconnect what dropped and, once the stop is cleared on the pendant,
re-uploads ur-rtde's control script if the stop ended it; then servoing resumes from the
measured pose. Nothing is ever sent to a dropped control interface (ur-rtde would block
reconnecting inside the call).

Close: ``servoStop``, ``stopScript``, ``disconnect`` of both interfaces, then the gripper.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from services.core.config import ConfigError
from services.core.geometry import matrix_to_quat_wxyz, matrix_to_rotvec, orthonormalize, rotvec_to_matrix
from services.core.robot_types import EefDelta, RobotSnapshot
from services.robot.base import RobotDriver
from services.robot.gripper import Gripper

if TYPE_CHECKING:
    from services.robot.config import URRobotConfig

log = logging.getLogger(__name__)

# servoL's speed and acceleration: ur-rtde documents both as unused by its servoL (the time, the
# lookahead and the gain shape the motion); the values are its examples'.
SERVO_SPEED = 0.5
SERVO_ACCELERATION = 0.5
SAFETY_MODES = {
    1: "NORMAL",
    2: "REDUCED",
    3: "PROTECTIVE_STOP",
    4: "RECOVERY",
    5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
    8: "VIOLATION",
    9: "FAULT",
    10: "VALIDATE_JOINT_ID",
    11: "UNDEFINED_SAFETY_MODE",
    12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}
SAFE_MODES = {1, 2}  # normal, reduced: the arm may move
ROBOT_MODES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
    8: "UPDATING_FIRMWARE",
}
RUNNING = 7


# -- poses: UR [x, y, z, rx, ry, rz] <-> position + rotation ----------------------------------


def ur_pose_to_pos_matrix(pose) -> tuple[np.ndarray, np.ndarray]:
    """UR ``[x, y, z, rx, ry, rz]`` (m, rotation vector) -> position (3,), rotation matrix (3, 3)."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (6,) or not np.all(np.isfinite(pose)):
        raise ValueError(f"a UR pose is 6 finite numbers, got {pose.tolist()}")
    return pose[:3].copy(), rotvec_to_matrix(pose[3:])


def ur_pose_to_pos_quat(pose) -> tuple[np.ndarray, np.ndarray]:
    """UR ``[x, y, z, rx, ry, rz]`` -> position (3,), w-first unit quaternion (4,) (w >= 0)."""
    p, R = ur_pose_to_pos_matrix(pose)
    q = matrix_to_quat_wxyz(R)
    return p, (-q if q[0] < 0 else q)


def pos_matrix_to_ur_pose(p: np.ndarray, R: np.ndarray) -> list[float]:
    """Position (3,) and rotation (3, 3) -> UR ``[x, y, z, rx, ry, rz]`` (rotation angle in [0, pi])."""
    return [float(v) for v in (*np.asarray(p, dtype=np.float64), *matrix_to_rotvec(R))]


def apply_delta(p: np.ndarray, R: np.ndarray, action: EefDelta) -> tuple[np.ndarray, np.ndarray]:
    """The pose ``action`` moves (p, R) to: ``p + dp`` and ``Rot(drot) @ R``, both in the base frame."""
    return np.asarray(p) + action.dp, orthonormalize(rotvec_to_matrix(action.drot) @ R)


class UR(RobotDriver):
    """A UR arm through ur-rtde's ``RTDEControlInterface`` and ``RTDEReceiveInterface``."""

    def __init__(self, cfg: URRobotConfig, control_hz: float, control: Any, receive: Any, gripper: Gripper):
        self.cfg = cfg
        self.period = 1.0 / control_hz  # servoL's time: each target is reached over one control tick
        self._c = control
        self._r = receive
        self.gripper = gripper
        self._target: tuple[np.ndarray, np.ndarray] | None = None  # (p, R) being servoed to
        self._gripper_sent: float | None = None  # the last closure sent to the gripper
        self._lead_capped = False  # the target is being held within the lead of the measured pose
        self._last: RobotSnapshot | None = None  # the last good reading (returned while disconnected)
        self._measured: tuple[np.ndarray, np.ndarray] | None = None  # (p, R) of that reading
        self._fault = ""  # latched: why the arm cannot move ('' when it can)
        self._gripper_error = ""  # the gripper could not be reached
        self._recovered = threading.Event()  # the recovery thread resumed what the fault stopped
        self._recovery: threading.Thread | None = None
        self._last_attempt = 0.0
        self._attempts = 0  # recovery attempts for the current fault (the first failure is logged loud)
        self._closed = False
        if cfg.tcp_offset is not None:
            control.setTcp(list(cfg.tcp_offset))
        self._check()
        self.read()

    @classmethod
    def from_config(cls, cfg: URRobotConfig, *, control_hz: float) -> UR:
        try:
            import rtde_control
            import rtde_receive
        except ImportError as exc:
            raise ConfigError(
                f"robot driver 'ur' needs ur-rtde ({exc}): pip install ur-rtde (or pip install 'viewscale[hardware]')"
            ) from exc
        from services.robot.config import GRIPPERS

        frequency = cfg.frequency if cfg.frequency is not None else -1.0  # -1: ur-rtde's default for the model
        receive = control = None
        try:
            receive = rtde_receive.RTDEReceiveInterface(cfg.host, frequency)
            control = rtde_control.RTDEControlInterface(cfg.host, frequency)
            gripper = GRIPPERS.build(cfg.gripper, arm_host=cfg.host)
        except Exception as exc:
            for iface in (control, receive):
                if iface is not None:
                    _quietly(iface.disconnect)
            if isinstance(exc, (RuntimeError, OSError)) and not isinstance(exc, ConnectionError):
                raise ConnectionError(
                    f"cannot connect to the UR controller at {cfg.host}: {exc} "
                    "(is it on and reachable, and on e-Series in remote control mode?)"
                ) from exc
            raise  # a gripper that cannot be reached or built says so itself
        try:
            return cls(cfg, control_hz, control, receive, gripper)
        except Exception:
            for release in (control.disconnect, receive.disconnect, gripper.close):
                _quietly(release)
            raise

    # -- state ----------------------------------------------------------------------------
    def read(self) -> RobotSnapshot:
        self._check()
        if not self._connected():
            if self._last is None:
                raise ConnectionError(f"no state from the UR controller at {self.cfg.host}")
            return self._last
        try:
            pose = self._r.getActualTCPPose()
            p, R = ur_pose_to_pos_matrix(pose)
            q = ur_pose_to_pos_quat(pose)[1]
            joints = np.asarray(self._r.getActualQ(), dtype=np.float64)
            speeds = np.asarray(self._r.getActualQd(), dtype=np.float64)
        except (RuntimeError, ValueError) as exc:
            self._set_fault(f"reading the state of the UR controller at {self.cfg.host} failed: {exc}")
            if self._last is None:
                raise ConnectionError(self._fault) from exc
            return self._last
        closure = self._last.gripper if self._last is not None else 0.0
        if not self._gripper_error:
            try:
                closure = self.gripper.position()
            except OSError as exc:
                self._gripper_failed(exc)
        self._measured = (p, R)
        self._last = RobotSnapshot(p, q, joints, speeds, closure)
        return self._last

    def target_position(self) -> np.ndarray | None:
        # No target while not servoing: the safety layer then bounds the measured position.
        return None if self._target is None else self._target[0].copy()

    def fault(self) -> str:
        self._check()
        return self._fault

    # -- commands -------------------------------------------------------------------------
    def apply(self, action: EefDelta) -> None:
        if self._fault or self._closed:
            return  # the safety layer sends nothing while there is a fault; never move through one
        if np.any(action.dp) or np.any(action.drot):
            self._servo(action)
        if self._gripper_sent is None or abs(action.gripper - self._gripper_sent) > 1e-3:
            try:
                self.gripper.move(action.gripper)
                self._gripper_sent = action.gripper
            except OSError as exc:
                self._gripper_failed(exc)

    def _servo(self, action: EefDelta) -> None:
        if self._target is None:
            if self._measured is None:
                return
            self._target = self._measured
        self._target = self._within_lead(*apply_delta(*self._target, action))
        pose = pos_matrix_to_ur_pose(*self._target)
        try:
            ok = self._c.servoL(
                pose, SERVO_SPEED, SERVO_ACCELERATION, self.period, self.cfg.lookahead_time, self.cfg.gain
            )
        except RuntimeError as exc:
            self._set_fault(f"servoL to the UR controller at {self.cfg.host} failed: {exc}")
            return
        if not ok:
            self._check()  # a protective stop says why; otherwise the script is gone
            if not self._fault:
                self._set_fault("the UR controller refused servoL (its control script is not running)")

    def _within_lead(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(p, R) pulled back to within ``max_lead_m`` and ``max_lead_rad`` of the measured pose."""
        mp, mR = self._measured
        gap, turn = p - mp, matrix_to_rotvec(R @ mR.T)  # (the rotation from the measured to the target)
        dist, angle = float(np.linalg.norm(gap)), float(np.linalg.norm(turn))
        lead_m, lead_rad = self.cfg.max_lead_m, self.cfg.max_lead_rad
        if dist <= lead_m and angle <= lead_rad:
            self._lead_capped = False
            return p, R
        if not self._lead_capped:
            self._lead_capped = True
            log.warning(
                "the arm is %.0f mm and %.1f degrees behind its servo target (held back?): the target is "
                "kept within max_lead_m %g m and max_lead_rad %g rad of it",
                dist * 1e3, np.degrees(angle), lead_m, lead_rad,
            )  # fmt: skip
        if dist > lead_m:
            p = mp + gap * (lead_m / dist)
        if angle > lead_rad:
            R = orthonormalize(rotvec_to_matrix(turn * (lead_rad / angle)) @ mR)
        return p, R

    def stop(self) -> None:
        self._target = None  # the next motion starts from wherever the arm comes to rest
        if self._controllable():
            try:
                self._c.servoStop(self.cfg.stop_deceleration)
            except RuntimeError as exc:
                log.warning("servoStop on the UR controller at %s failed: %s", self.cfg.host, exc)

    # -- faults ---------------------------------------------------------------------------
    def _connected(self) -> bool:
        try:
            return bool(self._r.isConnected() and self._c.isConnected())
        except RuntimeError:
            return False

    def _controllable(self) -> bool:
        """Connected: a call on the control interface returns instead of reconnecting inside it."""
        try:
            return bool(self._c.isConnected())
        except RuntimeError:
            return False

    def _condition(self) -> str:
        """What stops the arm right now, from the controller's state ('' when nothing does)."""
        host = self.cfg.host
        if not self._connected():
            return f"connection to the UR controller at {host} lost"
        try:
            if self._r.isEmergencyStopped():
                return "emergency stop: release it and restart the arm on the teach pendant"
            if self._r.isProtectiveStopped():
                return "protective stop: clear it on the teach pendant (servoing resumes from where the arm stands)"
            safety = int(self._r.getSafetyMode())
            if safety not in SAFE_MODES:
                return f"safety mode {SAFETY_MODES.get(safety, 'UNKNOWN')} ({safety})"
            mode = int(self._r.getRobotMode())
            if mode != RUNNING:
                return f"robot mode {ROBOT_MODES.get(mode, 'UNKNOWN')} ({mode}): the arm is not running"
        except RuntimeError as exc:
            return f"reading the state of the UR controller at {host} failed: {exc}"
        if self._gripper_error:
            return self._gripper_error
        return ""

    def _set_fault(self, text: str) -> None:
        if text != self._fault:
            log.warning("UR %s: %s", self.cfg.host, text)
            self._fault = text
            self._recovered.clear()
            self._attempts = 0

    def _gripper_failed(self, exc: OSError) -> None:
        self._gripper_error = f"gripper unreachable: {exc}"
        self._set_fault(self._gripper_error)

    def _check(self) -> None:
        """Latch what stops the arm; clear it once the condition is gone and recovery resumed it."""
        if self._closed:
            return
        condition = self._condition()
        if condition:
            self._set_fault(condition)
        if not self._fault:
            return
        if not condition and self._recovered.is_set():
            log.warning("UR %s: %s is over; servoing resumes from the measured pose", self.cfg.host, self._fault)
            self._fault = ""
            self._target = None
            self._gripper_sent = None
            self._recovered.clear()
            return
        alive = self._recovery is not None and self._recovery.is_alive()
        if not alive and time.monotonic() - self._last_attempt >= self.cfg.reconnect_interval_s:
            self._last_attempt = time.monotonic()
            self._recovery = threading.Thread(target=self._recover, name="ur-recovery", daemon=True)
            self._recovery.start()

    def _recover(self) -> None:
        """One recovery attempt (a thread of its own: reconnecting blocks for seconds)."""
        try:
            if not self._r.isConnected():
                self._r.reconnect()
            if not self._c.isConnected():
                self._c.reconnect()
            if self._gripper_error:
                self.gripper.reconnect()
                self._gripper_error = ""
            if self._condition():
                return  # still stopped (on the pendant): try again later
            if not self._c.isProgramRunning():
                # A protective stop ends ur-rtde's control script; uploading it again is its way back.
                if not self._c.reuploadScript():
                    raise RuntimeError("reuploadScript failed")
            self._recovered.set()
        except (RuntimeError, OSError) as exc:
            self._attempts += 1
            level = logging.WARNING if self._attempts == 1 else logging.DEBUG
            log.log(level, "UR %s: recovery attempt %d failed: %s", self.cfg.host, self._attempts, exc)

    # -- release --------------------------------------------------------------------------
    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._recovery is not None:
            self._recovery.join(timeout=5.0)
        if self._controllable():
            _quietly(self._c.servoStop, self.cfg.stop_deceleration)
            _quietly(self._c.stopScript)
        _quietly(self._c.disconnect)
        _quietly(self._r.disconnect)
        _quietly(self.gripper.close)
        log.info("disconnected from the UR controller at %s", self.cfg.host)


def _quietly(fn, *args) -> None:
    """Call ``fn`` while releasing the hardware: a failure is logged, the release goes on."""
    try:
        fn(*args)
    except (RuntimeError, OSError) as exc:
        log.warning("%s failed while closing: %s", getattr(fn, "__name__", fn), exc)
