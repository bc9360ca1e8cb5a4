"""Camera rigs: named cameras placed by rotations around the workspace centre.

A rig YAML (presets in ``services/core/rigs/``) gives a base view -- the front camera F, at
``distance`` from ``center``, seen from ``azimuth_deg`` (0 = from +x, facing the robot) and
``elevation_deg`` above the table, image-up as close to world +z as possible -- and each camera
as a rigid rotation of that camera around the centre: ``pitch_deg`` > 0 moves it up about the
base view's image-right axis, then ``yaw_deg`` > 0 moves it to its own left about the base
view's image-up axis. Every camera looks at the centre, and FL is exactly 15 degrees from F.
A camera may instead give an absolute ``azimuth_deg``/``elevation_deg`` (side and top views).

Framing (the defaults, robomimic agentview-like): elevated 55 degrees and looking down on the
objects' start region with a narrow 25-degree field of view, so that at 84x84 the region spans
about 70 % of the image width and every task object is at least 8 px across in every view of
``five15`` (``tests/unit/test_rig.py`` projects them). One framing cannot do that for every task:
with a 4 cm cube at 8 px, 84 px cover 42 cm, while the can task's workspace (can region to bin)
is 58 cm wide. So ``tasks`` moves the centre and distance per task, keeping every angle (and so
every ``R_ext``); ``Rig.for_task`` applies it, and ``SimWorld`` does so for its task.

Conventions (the ones published in foxglove ``CameraCalibration``/``FrameTransform``):
- optical frame as OpenCV: x right, y down, z forward;
- ``R_wc`` (camera-to-world rotation) has the optical axes as columns; the pose published on
  ``camera/<name>/pose`` is (``position``, ``R_wc``) with parent ``world``;
- ``R_ext = R_wc.T`` is the world-to-camera rotation the paper's camera action space uses,
  and ``x_cam = R_ext @ (x_world - position)``;
- ``K`` has square pixels and the principal point at the image centre in OpenCV's
  pixel-centre convention: ``cx = (W - 1) / 2``.
"""

from __future__ import annotations

import math
from functools import cached_property
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from pydantic import Field
from scipy.spatial.transform import Rotation

from services.core.config import ConfigError, Frozen, read_yaml
from services.core.topics import WORLD_FRAME

RIG_DIR = Path(__file__).resolve().parent / "rigs"  # shipped as package data


class CameraSpec(Frozen):
    yaw_deg: float = 0.0  # rotation to the camera's left about the base view's image-up axis through the centre
    pitch_deg: float = 0.0  # rotation upward about the base view's image-right axis through the centre
    azimuth_deg: float | None = None  # absolute placement instead of yaw/pitch: view azimuth (0 = from +x)
    elevation_deg: float | None = None  # absolute placement instead of yaw/pitch: height angle (90 = top-down)
    distance: float | None = None  # metres from the centre; default: the rig's
    fovy_deg: float | None = None  # vertical field of view; default: the rig's


class Framing(Frozen):
    center: tuple[float, float, float] | None = None  # workspace centre for this task; default: the rig's
    distance: float | None = None  # base camera distance for this task; default: the rig's


# The sim tasks' workspaces (sim/tasks.py): lift (the defaults) frames the cube's 16 x 20 cm patch
# and the gripper at home; can frames its can's patch (y < 0) and most of the bin (y = 0.2), the
# can (6 cm) at 8+ px; square its nut's patch and the peg.
TASK_FRAMING: dict[str, Framing] = {
    "can": Framing(center=(0.49, -0.03, 0.1), distance=1.35),
    "square": Framing(center=(0.49, -0.03, 0.1), distance=1.2),
}


class RigSpec(Frozen):
    name: str  # rig name, recorded with every episode
    center: tuple[float, float, float] = (0.49, 0.0, 0.1)  # workspace centre, world frame (m): the lift patch + gripper
    distance: float = 0.83  # base camera distance from the centre (m)
    azimuth_deg: float = 0.0  # base view direction: 0 = camera on +x looking back at the robot
    elevation_deg: float = 55.0  # base view height above the horizontal through the centre
    fovy_deg: float = 25.0  # vertical field of view
    cameras: dict[str, CameraSpec] = Field(min_length=1)  # name -> rotation of the base view
    tasks: dict[str, Framing] = Field(default_factory=lambda: dict(TASK_FRAMING))  # per-task centre/distance


class Camera:
    """One calibrated pinhole camera of a rig (exact in sim: the renderer uses the same numbers)."""

    def __init__(self, name: str, position: np.ndarray, R_wc: np.ndarray, fovy_deg: float):
        self.name = name
        self.position = np.asarray(position, dtype=np.float64)  # (3,) world
        self.R_wc = np.asarray(R_wc, dtype=np.float64)  # (3, 3) camera -> world, OpenCV axes
        self.fovy_deg = float(fovy_deg)

    @property
    def R_ext(self) -> np.ndarray:
        """World-to-camera rotation (the paper's R^ext)."""
        return self.R_wc.T

    @property
    def t_ext(self) -> np.ndarray:
        return -self.R_ext @ self.position

    def K(self, width: int, height: int) -> np.ndarray:
        f = (height / 2.0) / math.tan(math.radians(self.fovy_deg) / 2.0)
        return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world -> (N, 3) optical frame."""
        return (np.asarray(points_world) - self.position) @ self.R_ext.T

    def project(self, points_world: np.ndarray, width: int, height: int) -> np.ndarray:
        """(N, 3) world points -> (N, 2) pixel coordinates (u right, v down)."""
        pc = self.to_camera(np.atleast_2d(points_world))
        uvw = pc @ self.K(width, height).T
        return uvw[:, :2] / uvw[:, 2:3]

    @cached_property
    def mujoco_xyaxes(self) -> tuple[float, ...]:
        """MJCF ``xyaxes``: MuJoCo cameras look down -z with y up, so flip OpenCV's y and z."""
        x_axis = self.R_wc[:, 0]
        y_axis = -self.R_wc[:, 1]
        return tuple(float(v) for v in (*x_axis, *y_axis))

    def calibration_msg(self, width: int, height: int, stamp_ns: int) -> CameraCalibration:
        K = self.K(width, height)
        P = np.hstack([K, np.zeros((3, 1))])
        msg = CameraCalibration(
            frame_id=self.name,
            width=width,
            height=height,
            distortion_model="plumb_bob",
            D=[0.0] * 5,
            K=K.flatten().tolist(),
            R=np.eye(3).flatten().tolist(),
            P=P.flatten().tolist(),
        )
        msg.timestamp.FromNanoseconds(stamp_ns)
        return msg

    def pose_msg(self, stamp_ns: int) -> FrameTransform:
        x, y, z, w = Rotation.from_matrix(self.R_wc).as_quat()
        msg = FrameTransform(parent_frame_id=WORLD_FRAME, child_frame_id=self.name)
        msg.timestamp.FromNanoseconds(stamp_ns)
        msg.translation.x, msg.translation.y, msg.translation.z = (float(v) for v in self.position)
        msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = float(x), float(y), float(z), float(w)
        return msg

    @classmethod
    def from_msgs(cls, calib: CameraCalibration, pose: FrameTransform) -> tuple[Camera, np.ndarray]:
        """Rebuild a camera and its K from published (or recorded) messages."""
        q = pose.rotation
        R_wc = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        t = pose.translation
        K = np.asarray(calib.K, dtype=np.float64).reshape(3, 3)
        fovy = math.degrees(2.0 * math.atan((calib.height / 2.0) / K[1, 1]))
        return cls(pose.child_frame_id or calib.frame_id, np.array([t.x, t.y, t.z]), R_wc, fovy), K


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """R_wc (OpenCV optical axes as columns) for a camera at ``position`` looking at ``target``,
    with image-up as close to world +z as possible (world -x when looking straight down)."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0])
    if abs(z @ up) > 0.999:
        up = np.array([-1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # points down in the image
    return np.stack([x, y, z], axis=1)


def _orbit(center: np.ndarray, distance: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return center + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


class Rig:
    def __init__(self, spec: RigSpec, task: str | None = None):
        self.spec = spec
        self.task = task  # the task whose framing was applied (None: the rig's own centre/distance)
        center = np.asarray(spec.center, dtype=np.float64)
        base_pos = _orbit(center, spec.distance, spec.azimuth_deg, spec.elevation_deg)
        base_R = look_at(base_pos, center)
        up, right = -base_R[:, 1], base_R[:, 0]  # the base view's image-up and image-right axes
        self.cameras: dict[str, Camera] = {}
        for name, cam in spec.cameras.items():
            fovy = cam.fovy_deg if cam.fovy_deg is not None else spec.fovy_deg
            if cam.azimuth_deg is not None or cam.elevation_deg is not None:
                position = _orbit(
                    center,
                    cam.distance or spec.distance,
                    spec.azimuth_deg if cam.azimuth_deg is None else cam.azimuth_deg,
                    spec.elevation_deg if cam.elevation_deg is None else cam.elevation_deg,
                )
                self.cameras[name] = Camera(name, position, look_at(position, center), fovy)
                continue
            # A rigid rotation of the base camera about axes through the centre: the camera
            # keeps looking at the centre and the angle between it and F is exactly the one
            # given. With OpenCV axes, +angle about image-up moves the camera right and
            # +angle about image-right moves it down, hence the signs.
            rot = Rotation.from_rotvec(-math.radians(cam.yaw_deg) * up) * Rotation.from_rotvec(
                -math.radians(cam.pitch_deg) * right
            )
            offset = rot.apply(base_pos - center)
            if cam.distance is not None:
                offset *= cam.distance / spec.distance
            self.cameras[name] = Camera(name, center + offset, rot.as_matrix() @ base_R, fovy)

    def for_task(self, task: str) -> Rig:
        """This rig with ``task``'s framing (centre and distance) applied; the same angles."""
        if task == self.task:
            return self
        if self.task is not None:
            raise ValueError(f"rig {self.name!r} is framed for task {self.task!r}, not {task!r}")
        framing = self.spec.tasks.get(task)
        if framing is None:
            return Rig(self.spec, task)
        changes = {k: v for k, v in (("center", framing.center), ("distance", framing.distance)) if v is not None}
        return Rig(self.spec.model_copy(update=changes), task)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def names(self) -> list[str]:
        return list(self.cameras)


def available_rigs() -> list[str]:
    return sorted(p.stem for p in RIG_DIR.glob("*.yaml"))


def load_rig(name_or_path: str, task: str | None = None) -> Rig:
    """A preset name (``five15``) or a path to a rig YAML, framed for ``task`` if one is given."""
    path = Path(name_or_path)
    if not path.suffix:
        path = RIG_DIR / f"{name_or_path}.yaml"
        if not path.is_file():
            raise ConfigError(f"unknown rig {name_or_path!r}; presets: {', '.join(available_rigs())}")
    data = read_yaml(path)
    data.setdefault("name", path.stem)
    try:
        rig = Rig(RigSpec.model_validate(data))
    except ValueError as exc:
        raise ConfigError(f"invalid rig {path}: {exc}") from exc
    return rig if task is None else rig.for_task(task)
