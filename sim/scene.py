"""The MuJoCo scene: table, a 6-DOF arm with a parallel gripper, one task's objects, and one
camera per rig camera; plus an offscreen renderer that draws every camera of one state.

World frame = robot base frame: z up, the table top at z = 0, the arm's base at the origin
facing +x. The arm is an anthropomorphic 6R chain (base yaw, shoulder pitch, elbow pitch,
forearm roll, wrist pitch, tool roll) built from primitives, with two fingers on slide joints.

The EEF frame is the site ``eef`` between the finger pads: z along the approach direction
(wrist -> fingertips), y along the line the fingers close on. With the gripper pointing
straight down at yaw 0 its rotation is ``R_DOWN`` (x = world +x, y = world -y, z = world -z).

Each MuJoCo camera is built from the rig camera (``pos``, ``xyaxes``, ``fovy``), so the images
agree with ``Camera.project`` exactly: the calibration is exact by construction.
"""

from __future__ import annotations

import os
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from services.core.rig import Rig
from sim.tasks import Task

TIMESTEP = 0.002  # physics step (s)
ARM_JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6")
FINGER_JOINTS = ("finger_left", "finger_right")
FINGER_OPEN = 0.045  # finger inner-face distance from the centre line when fully open (m)
EEF_SITE = "eef"
R_DOWN = np.diag([1.0, -1.0, -1.0])  # EEF rotation pointing down at yaw 0

# Link lengths (m): shoulder height, upper arm, forearm (elbow -> wrist pitch axis).
SHOULDER_Z = 0.30
UPPER_ARM = 0.42
FOREARM = 0.40

_ROBOT = f"""
    <body name="base" pos="0 0 0">
      <geom class="visual" type="cylinder" size="0.09 0.05" pos="0 0 0.05" material="dark"/>
      <body name="link1" pos="0 0 0.1" gravcomp="1">
        <joint name="j1" axis="0 0 1" range="-2.9 2.9"/>
        <geom class="visual" type="cylinder" size="0.065 0.09" pos="0 0 0.09" material="arm"/>
        <body name="link2" pos="0 0 {SHOULDER_Z - 0.1}" gravcomp="1">
          <joint name="j2" axis="0 1 0" range="-1.9 1.9"/>
          <geom class="visual" type="cylinder" size="0.07 0.065" quat="0.7071068 0.7071068 0 0" material="dark"/>
          <geom class="visual" type="capsule" fromto="0 0 0 0 0 {UPPER_ARM}" size="0.05" material="arm"/>
          <body name="link3" pos="0 0 {UPPER_ARM}" gravcomp="1">
            <joint name="j3" axis="0 1 0" range="-0.2 2.9"/>
            <geom class="visual" type="cylinder" size="0.06 0.06" quat="0.7071068 0.7071068 0 0" material="dark"/>
            <body name="link4" pos="0 0 0" gravcomp="1">
              <joint name="j4" axis="0 0 1" range="-3.1 3.1"/>
              <geom class="visual" type="capsule" fromto="0 0 0.02 0 0 {FOREARM - 0.03}" size="0.042" material="arm"/>
              <body name="link5" pos="0 0 {FOREARM}" gravcomp="1">
                <joint name="j5" axis="0 1 0" range="-2.6 2.6"/>
                <geom class="visual" type="cylinder" size="0.045 0.045" quat="0.7071068 0.7071068 0 0" material="dark"/>
                <body name="link6" pos="0 0 0.06" gravcomp="1">
                  <joint name="j6" axis="0 0 1" range="-4.7 4.7"/>
                  <geom class="visual" type="cylinder" size="0.04 0.02" pos="0 0 0.0" material="arm"/>
                  <body name="hand" pos="0 0 0.04" gravcomp="1">
                    <geom class="gripper" type="box" size="0.025 0.065 0.015" pos="0 0 0.015" material="gripper"/>
                    <site name="{EEF_SITE}" pos="0 0 0.10" quat="0 0 0 1" size="0.005" rgba="1 1 1 0" group="4"/>
                    <body name="finger_left" pos="0 0 0.03" gravcomp="1">
                      <joint name="finger_left" type="slide" axis="0 1 0" range="0 {FINGER_OPEN}"/>
                      <geom class="finger" type="box" size="0.012 0.008 0.04" pos="0 0.008 0.04"/>
                    </body>
                    <body name="finger_right" pos="0 0 0.03" gravcomp="1">
                      <joint name="finger_right" type="slide" axis="0 -1 0" range="0 {FINGER_OPEN}"/>
                      <geom class="finger" type="box" size="0.012 0.008 0.04" pos="0 -0.008 0.04"/>
                    </body>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>"""

_ACTUATORS = f"""
    <position name="j1" joint="j1" kp="3000" dampratio="1" forcerange="-300 300"/>
    <position name="j2" joint="j2" kp="3000" dampratio="1" forcerange="-300 300"/>
    <position name="j3" joint="j3" kp="2000" dampratio="1" forcerange="-200 200"/>
    <position name="j4" joint="j4" kp="600" dampratio="1" forcerange="-60 60"/>
    <position name="j5" joint="j5" kp="600" dampratio="1" forcerange="-60 60"/>
    <position name="j6" joint="j6" kp="400" dampratio="1" forcerange="-40 40"/>
    <position name="finger_left" joint="finger_left" kp="800" dampratio="1" forcerange="-25 25"
              ctrlrange="0 {FINGER_OPEN}"/>
    <position name="finger_right" joint="finger_right" kp="800" dampratio="1" forcerange="-25 25"
              ctrlrange="0 {FINGER_OPEN}"/>"""


def _camera_xml(rig: Rig) -> str:
    lines = []
    for cam in rig.cameras.values():
        pos = " ".join(f"{v:.17g}" for v in cam.position)
        xyaxes = " ".join(f"{v:.17g}" for v in cam.mujoco_xyaxes)
        lines.append(
            f'    <camera name={quoteattr(cam.name)} pos="{pos}" xyaxes="{xyaxes}" fovy="{cam.fovy_deg:.17g}"/>'
        )
    return "\n".join(lines)


def scene_xml(task: Task, rig: Rig, width: int = 84, height: int = 84) -> str:
    """The full MJCF of one task's scene with the rig's cameras."""
    return f"""<mujoco model="viewscale_{task.name}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP}" integrator="implicitfast" cone="elliptic" impratio="10"/>
  <visual>
    <global offwidth="{max(width, 640)}" offheight="{max(height, 480)}"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.82 0.85 0.9" rgb2="0.45 0.5 0.58"
             width="32" height="32"/>
    <material name="table" rgba="0.72 0.6 0.45 1" reflectance="0"/>
    <material name="arm" rgba="0.86 0.87 0.9 1" reflectance="0"/>
    <material name="dark" rgba="0.22 0.23 0.26 1" reflectance="0"/>
    <material name="gripper" rgba="0.12 0.12 0.14 1" reflectance="0"/>
    <material name="finger" rgba="0.35 0.35 0.38 1" reflectance="0"/>
{task.assets_xml()}
  </asset>
  <default>
    <joint armature="0.05" damping="0.5"/>
    <geom friction="1 0.01 0.0001" condim="4" solref="0.01 1"/>
    <default class="visual">
      <geom contype="0" conaffinity="0" group="1"/>
    </default>
    <default class="gripper">
      <geom contype="1" conaffinity="1" group="1"/>
    </default>
    <default class="finger">
      <geom contype="1" conaffinity="1" group="1" friction="1.5 0.02 0.0001" material="finger"/>
    </default>
  </default>
  <worldbody>
    <light name="key" directional="true" castshadow="false" pos="0.5 -0.5 2" dir="-0.2 0.3 -1"
           diffuse="0.45 0.45 0.45" specular="0 0 0"/>
    <geom name="table" type="box" size="0.75 0.8 0.03" pos="0.35 0 -0.03" material="table"/>
{_ROBOT}
{task.worldbody_xml()}
{_camera_xml(rig)}
  </worldbody>
  <contact>
    <exclude body1="finger_left" body2="finger_right"/>
  </contact>
  <actuator>{_ACTUATORS}
  </actuator>
</mujoco>
"""


def build_model(task: Task, rig: Rig, width: int = 84, height: int = 84) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(scene_xml(task, rig, width, height))


class RenderError(RuntimeError):
    """No OpenGL context to render the cameras with (the message says which backend, and what to do)."""


class MultiCameraRenderer:
    """Draws every camera of one simulation state into (H, W, 3) uint8 RGB arrays.

    The scene's geometry is gathered once per state (``mjv_updateScene``); each camera then
    only moves the viewpoint and the headlight (``mjv_updateCamera``, ``mjv_makeLights``)
    before ``mjr_render``, which is what makes a five-camera set cheap; the images are the same
    as a full scene update per camera would give. Shadows and reflections are off: they dominate the cost at policy
    resolutions and the policy gains nothing from them.
    """

    def __init__(self, model: mujoco.MjModel, camera_names: list[str], width: int, height: int):
        self._model = model
        self._width, self._height = width, height
        self._cams: dict[str, mujoco.MjvCamera] = {}
        for name in camera_names:
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            if cam.fixedcamid < 0:
                raise ValueError(f"camera {name!r} is not in the model")
            self._cams[name] = cam
        # The GL context is current only inside each call (``as_current``), so whichever thread
        # renders next can take it.
        try:
            self._gl = mujoco.GLContext(width, height)
            with self._gl.as_current():  # (GLFW with no display gets this far, and fails here)
                self._ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
                mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._ctx)
        except Exception as exc:  # GLFW on a machine without a display, no EGL or OSMesa library
            if getattr(self, "_gl", None) is not None:
                self._gl.free()
            raise RenderError(
                f"cannot render with MUJOCO_GL={os.environ.get('MUJOCO_GL', '(unset)')}: {exc}; headless, "
                "render with MUJOCO_GL=egl (libEGL: apt install libegl1) or MUJOCO_GL=osmesa "
                "(apt install libosmesa6), set before mujoco is imported"
            ) from exc
        self._scene = mujoco.MjvScene(model, maxgeom=1000)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._buf = np.empty((height, width, 3), dtype=np.uint8)

    def render(self, data: mujoco.MjData) -> dict[str, np.ndarray]:
        """Camera name -> (H, W, 3) uint8 RGB of ``data`` as it is (call mj_forward first)."""
        out: dict[str, np.ndarray] = {}
        first = True
        with self._gl.as_current():
            for name, cam in self._cams.items():
                if first:
                    mujoco.mjv_updateScene(
                        self._model, data, self._option, self._perturb, cam, mujoco.mjtCatBit.mjCAT_ALL, self._scene
                    )
                    first = False
                else:
                    mujoco.mjv_updateCamera(self._model, data, cam, self._scene)
                    mujoco.mjv_makeLights(self._model, data, self._scene)  # the headlight moves with the camera
                mujoco.mjr_render(self._rect, self._scene, self._ctx)
                mujoco.mjr_readPixels(self._buf, None, self._rect, self._ctx)
                out[name] = np.flipud(self._buf).copy()  # OpenGL rows run bottom-up
        return out

    def close(self) -> None:
        if self._ctx is not None:
            with self._gl.as_current():
                self._ctx.free()
            self._ctx = None
            self._gl.free()
