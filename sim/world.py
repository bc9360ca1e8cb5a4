"""SimWorld: one task's scene stepped at a fixed control rate by EEF delta actions.

Action semantics (the ``EefAction`` message): ``dp`` (3,) metres and ``drot`` (3,) an
axis-angle vector in radians, both in the base (= world) frame, and a gripper target closure in
[0, 1] (0 open, 1 closed). The world keeps an EEF *target* pose and integrates each delta into
it, rotation composing on the left in the base frame (``R_next = Rot(drot) @ R``), and keeps
the target within ``MAX_LEAD`` metres / ``MAX_LEAD_ROT`` radians of the actual EEF pose, so a
blocked arm (pressing on the table, a jammed nut) does not wind the target up and lurch when it
frees. The workspace box and the speed caps are not the world's: the sim arm runs behind the
same safety layer as hardware (``services.robot.safety``), which limits every action first.

Damped-least-squares IK (``sim.ik``) turns the target into joint positions once per tick, and
the joint position actuators follow, their set points ramped linearly over the physics
substeps of one control period (``TIMESTEP`` = 2 ms, 25 substeps at 20 Hz). Everything is
deterministic: the same seed and the same actions give the same trajectory, bit for bit (on one
machine and MuJoCo build; rendering does not perturb it).
"""

from __future__ import annotations

import math
import numbers

import mujoco
import numpy as np

from services.core.geometry import (
    clip_norm,
    matrix_to_quat_wxyz,
    orthonormalize,
    rotation_error,
    rotvec_to_matrix,
)
from services.core.rig import Rig
from services.core.robot_types import ObjectPose, RobotSnapshot
from sim.ik import SiteIk
from sim.scene import (
    ARM_JOINTS,
    EEF_SITE,
    FINGER_JOINTS,
    FINGER_OPEN,
    R_DOWN,
    TIMESTEP,
    MultiCameraRenderer,
    build_model,
)
from sim.tasks import TASKS, make_task

__all__ = ["TASKS", "SimWorld"]

MAX_LEAD = 0.05  # m the target may run ahead of the actual EEF position
MAX_LEAD_ROT = 0.5  # rad the target may run ahead of the actual EEF rotation
HOME_POS = np.array([0.45, 0.0, 0.25])  # EEF at reset, pointing down (R_DOWN)
HOME_SEED = np.array([0.0, 0.0, 1.9, 0.0, 1.2, 0.0])  # elbow-up IK seed for the home pose
SETTLE_STEPS = 50  # physics steps after placing the objects, before the first tick
# Quaternion sign: the hemisphere of the pointing-down rotation (w = 0 there, so "w >= 0" would
# flip sign on noise around home); continuous everywhere the gripper does not point up.
_QUAT_DOWN = np.array([0.0, 1.0, 0.0, 0.0])


def _vector(name: str, value, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be {n} finite numbers, got {value!r}")
    return arr


def _scalar(name: str, value) -> float:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.array([np.nan])
    if arr.size != 1 or not np.isfinite(arr).all():
        raise ValueError(f"{name} must be one finite number, got {value!r}")
    return float(arr.reshape(()))


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ValueError(f"seed must be a non-negative int below 2**64, got {type(seed).__name__} {seed!r}")
    seed = int(seed)
    if not 0 <= seed < 2**64:
        raise ValueError(f"seed must be a non-negative int below 2**64, got {seed}")
    return seed


class SimWorld:
    """One task in the shared scene, seen by a rig's cameras (framed for the task: ``Rig.for_task``).
    A context manager."""

    def __init__(self, task: str, rig: Rig, width: int = 84, height: int = 84, control_hz: float = 20.0):
        self._task = make_task(task)
        if not isinstance(rig, Rig):
            raise ValueError(f"rig must be a services.core.rig.Rig, got {type(rig).__name__}")
        for name, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        if not (isinstance(control_hz, numbers.Real) and math.isfinite(control_hz) and 0 < control_hz <= 1 / TIMESTEP):
            raise ValueError(f"control_hz must be in (0, {1 / TIMESTEP:g}], got {control_hz!r}")
        self.task: str = task
        self.rig: Rig = rig.for_task(task)  # the task's framing of the rig (same angles)
        self.control_hz: float = float(control_hz)
        self.seed: int | None = None
        self.tick: int = 0  # control periods since the last reset
        self.width, self.height = int(width), int(height)
        self.substeps = max(1, round(1.0 / (self.control_hz * TIMESTEP)))

        self.model = build_model(self._task, self.rig, self.width, self.height)
        self.data = mujoco.MjData(self.model)
        m = self.model
        jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in ARM_JOINTS]
        fid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in FINGER_JOINTS]
        self._arm_qadr = np.array([m.jnt_qposadr[j] for j in jid])
        self._arm_dadr = np.array([m.jnt_dofadr[j] for j in jid])
        self._finger_qadr = np.array([m.jnt_qposadr[j] for j in fid])
        self._arm_act = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, j) for j in ARM_JOINTS])
        self._finger_act = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, j) for j in FINGER_JOINTS])
        self._site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, EEF_SITE)
        self._bodies = {name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) for name in self._task.objects}
        self._free_qadr = {}
        for name in self._task.place(None):
            body = self._bodies[name]
            self._free_qadr[name] = m.jnt_qposadr[m.body_jntadr[body]]
        self._ik = SiteIk(m, EEF_SITE, ARM_JOINTS)
        home = self._ik.solve(HOME_SEED, HOME_POS, R_DOWN)
        if home.pos_err > 1e-3 or home.rot_err > 1e-2:
            raise RuntimeError(f"home pose unreachable (IK error {home.pos_err:.4f} m, {home.rot_err:.4f} rad)")
        self._q_home = home.q
        self._renderer: MultiCameraRenderer | None = None
        self._reset_state(None)

    # -- episode ----------------------------------------------------------------------------

    def reset(self, seed: int) -> None:
        """Arm at home, gripper open, objects placed from ``seed`` (same seed, same scene)."""
        seed = _check_seed(seed)
        self._reset_state(np.random.default_rng(seed))
        self.seed = seed

    def _reset_state(self, rng: np.random.Generator | None) -> None:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[self._arm_qadr] = self._q_home
        d.qpos[self._finger_qadr] = FINGER_OPEN
        for name, (pos, quat) in self._task.place(rng).items():
            adr = self._free_qadr[name]
            d.qpos[adr : adr + 3] = pos
            d.qpos[adr + 3 : adr + 7] = quat
        self._q_cmd = self._q_home.copy()
        self._finger_cmd = FINGER_OPEN
        d.ctrl[self._arm_act] = self._q_cmd
        d.ctrl[self._finger_act] = self._finger_cmd
        for _ in range(SETTLE_STEPS):
            mujoco.mj_step(m, d)
        d.time = 0.0
        mujoco.mj_forward(m, d)
        self._target_pos = d.site_xpos[self._site].copy()
        self._target_R = d.site_xmat[self._site].reshape(3, 3).copy()
        self.tick = 0

    # -- control ----------------------------------------------------------------------------

    def step(self, dp, drot, gripper) -> None:
        """Integrate one EEF delta into the target and simulate one control period.

        ``dp`` and ``drot`` are 3 finite numbers each, ``gripper`` one (clipped to [0, 1]);
        anything else is a ValueError. Only the lead limit is applied here (module docstring).
        """
        dp = _vector("dp", dp, 3)
        drot = _vector("drot", drot, 3)
        g = min(max(_scalar("gripper", gripper), 0.0), 1.0)

        d = self.data
        eef_pos = d.site_xpos[self._site].copy()
        eef_R = d.site_xmat[self._site].reshape(3, 3).copy()
        self._target_pos = eef_pos + clip_norm(self._target_pos + dp - eef_pos, MAX_LEAD)
        R = rotvec_to_matrix(drot) @ self._target_R
        lead = rotation_error(R, eef_R)
        if np.linalg.norm(lead) > MAX_LEAD_ROT:
            R = rotvec_to_matrix(clip_norm(lead, MAX_LEAD_ROT)) @ eef_R
        self._target_R = orthonormalize(R)  # no drift from orthonormality over thousands of compositions

        q_prev, f_prev = self._q_cmd, self._finger_cmd
        self._q_cmd = self._ik.solve(q_prev, self._target_pos, self._target_R).q
        self._finger_cmd = FINGER_OPEN * (1.0 - g)
        n = self.substeps
        for k in range(1, n + 1):
            a = k / n
            d.ctrl[self._arm_act] = q_prev + a * (self._q_cmd - q_prev)
            d.ctrl[self._finger_act] = f_prev + a * (self._finger_cmd - f_prev)
            mujoco.mj_step(self.model, d)
        mujoco.mj_forward(self.model, d)  # derived quantities (site poses) of the new state
        self.tick += 1

    # -- state ------------------------------------------------------------------------------

    def robot(self) -> RobotSnapshot:
        d = self.data
        quat = matrix_to_quat_wxyz(d.site_xmat[self._site].reshape(3, 3))
        if quat @ _QUAT_DOWN < 0:
            quat = -quat
        fingers = float(np.mean(d.qpos[self._finger_qadr]))
        return RobotSnapshot(
            eef_pos=d.site_xpos[self._site].copy(),
            eef_quat_wxyz=quat,
            joint_pos=d.qpos[self._arm_qadr].copy(),
            joint_vel=d.qvel[self._arm_dadr].copy(),
            gripper=min(max(1.0 - fingers / FINGER_OPEN, 0.0), 1.0),
        )

    def target(self) -> tuple[np.ndarray, np.ndarray]:
        """The EEF target pose (pos (3,), R (3, 3)) the arm is following."""
        return self._target_pos.copy(), self._target_R.copy()

    def objects(self) -> dict[str, ObjectPose]:
        d = self.data
        return {name: ObjectPose(pos=d.xpos[b].copy(), quat_wxyz=d.xquat[b].copy()) for name, b in self._bodies.items()}

    def success(self) -> bool:
        return self._task.success(self.objects())

    @property
    def horizon(self) -> int:
        """Tick budget of one episode of this task at 20 Hz."""
        return self._task.horizon

    # -- images -----------------------------------------------------------------------------

    def render(self) -> dict[str, np.ndarray]:
        """Camera name -> (H, W, 3) uint8 RGB of the current state, in rig order."""
        if self._renderer is None:
            self._renderer = MultiCameraRenderer(self.model, self.rig.names, self.width, self.height)
        mujoco.mj_forward(self.model, self.data)
        return self._renderer.render(self.data)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> SimWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
