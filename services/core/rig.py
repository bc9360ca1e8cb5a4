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

Calibrated cameras (a lab's rig, written by ``viewscale calibrate``) give their pose and
intrinsics explicitly instead of a placement, and the rig's centre, framing and ``fovy_deg`` do
not move them::

    cameras:
      F:
        position: [1.12, 0.03, 0.71]        # optical centre in the world (= robot base) frame, m
        R_wc: [[..., ..., ...], [...], [...]]  # camera-to-world rotation, row by row: its columns
                                            # are the optical axes x right, y down, z forward
        intrinsics: {width: 640, height: 480, fx: 1085.2, fy: 1084.9, cx: 318.7, cy: 241.2,
                     distortion: [k1, k2, p1, p2, k3]}   # OpenCV plumb_bob, at width x height
        reprojection_px: 0.21               # RMS reprojection error of the calibration
        calibrated_at: 2025-03-01T09:30:00+00:00   # UTC when no offset is given

``K`` of a calibrated camera is its measured one, scaled to the requested image size as a plain
resize does (pixel-centre convention: ``c' = (c + 0.5) s - 0.5``); ``project`` applies the
distortion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import cached_property
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from pydantic import Field, field_validator, model_validator
from scipy.spatial.transform import Rotation

from services.core.config import ConfigError, Frozen, read_yaml
from services.core.topics import WORLD_FRAME

RIG_DIR = Path(__file__).resolve().parent / "rigs"  # shipped as package data
CALIBRATION_MAX_AGE_DAYS = 30.0  # default: a calibration older than this when an episode is recorded is stale
CALIBRATION_MAX_ERROR_PX = 1.0  # default: a calibration with a larger RMS reprojection error is refused
_CALIBRATED_FIELDS = ("position", "R_wc", "intrinsics", "reprojection_px", "calibrated_at")


class IntrinsicsSpec(Frozen):
    width: int = Field(gt=0)  # image width the intrinsics were measured at (px)
    height: int = Field(gt=0)  # image height the intrinsics were measured at (px)
    fx: float = Field(gt=0)  # focal length along x (px)
    fy: float = Field(gt=0)  # focal length along y (px)
    cx: float  # principal point x (px, pixel-centre convention)
    cy: float  # principal point y (px, pixel-centre convention)
    distortion: tuple[float, ...] = ()  # OpenCV plumb_bob k1 k2 p1 p2 [k3]; empty: none

    @field_validator("distortion")
    @classmethod
    def _distortion_length(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) not in (0, 4, 5):
            raise ValueError(f"distortion must be k1 k2 p1 p2 [k3] (4 or 5 numbers), got {len(v)}")
        return v


class CameraSpec(Frozen):
    yaw_deg: float = 0.0  # rotation to the camera's left about the base view's image-up axis through the centre
    pitch_deg: float = 0.0  # rotation upward about the base view's image-right axis through the centre
    azimuth_deg: float | None = None  # absolute placement instead of yaw/pitch: view azimuth (0 = from +x)
    elevation_deg: float | None = None  # absolute placement instead of yaw/pitch: height angle (90 = top-down)
    distance: float | None = None  # metres from the centre; default: the rig's
    fovy_deg: float | None = None  # vertical field of view; default: the rig's
    # A calibrated camera instead of a placement: all of these, none of the above.
    position: tuple[float, float, float] | None = None  # optical centre, world (= robot base) frame (m)
    R_wc: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]] | None = (
        None  # camera-to-world rotation row by row; its columns are the optical axes (x right, y down, z forward)
    )
    intrinsics: IntrinsicsSpec | None = None  # measured K and distortion at one image size
    reprojection_px: float | None = Field(None, ge=0)  # RMS reprojection error of the calibration (px)
    calibrated_at: datetime | None = None  # when it was calibrated (UTC when no offset is given)
    method: str | None = None  # how the pose was measured (board at a measured pose, hand-eye), for the record

    @model_validator(mode="after")
    def _calibrated_or_placed(self) -> CameraSpec:
        given = [f for f in _CALIBRATED_FIELDS if getattr(self, f) is not None]
        if not given:
            if self.method is not None:
                raise ValueError("method belongs to a calibrated camera (position, R_wc, intrinsics, ...)")
            return self
        missing = [f for f in _CALIBRATED_FIELDS if getattr(self, f) is None]
        if missing:
            raise ValueError(f"a calibrated camera needs {', '.join(_CALIBRATED_FIELDS)}; missing {', '.join(missing)}")
        placed = [
            f
            for f in ("yaw_deg", "pitch_deg", "azimuth_deg", "elevation_deg", "distance", "fovy_deg")
            if getattr(self, f) not in (None, 0.0)
        ]
        if placed:
            raise ValueError(f"a calibrated camera has an explicit pose; drop the placement fields {', '.join(placed)}")
        R = np.asarray(self.R_wc, dtype=np.float64)
        if not np.all(np.isfinite(R)) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise ValueError("R_wc must be a rotation matrix (orthonormal rows, determinant +1)")
        return self

    @property
    def calibrated(self) -> bool:
        return self.intrinsics is not None


@dataclass(frozen=True)
class Intrinsics:
    """A camera's measured pinhole model at one image size (OpenCV conventions)."""

    width: int
    height: int
    K: np.ndarray  # (3, 3) at width x height
    D: np.ndarray  # (N,) plumb_bob distortion, N in (0, 4, 5)

    @classmethod
    def from_spec(cls, s: IntrinsicsSpec) -> Intrinsics:
        K = np.array([[s.fx, 0.0, s.cx], [0.0, s.fy, s.cy], [0.0, 0.0, 1.0]])
        return cls(s.width, s.height, K, np.asarray(s.distortion, dtype=np.float64))

    def K_at(self, width: int, height: int) -> np.ndarray:
        """K for the image resized to (width, height), in OpenCV's pixel-centre convention."""
        return scale_K(self.K, (self.width, self.height), (width, height))


def scale_K(K: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """K of an image of ``size`` (w, h) resized to ``new_size``, in OpenCV's pixel-centre convention."""
    sx, sy = new_size[0] / size[0], new_size[1] / size[1]
    K = np.array(K, dtype=np.float64)
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def camera_gap(
    R_ext_a, position_a, K_a, size_a: tuple[int, int], R_ext_b, position_b, K_b, size_b: tuple[int, int]
) -> str:
    """How camera b differs from camera a, e.g. 'placed 23.0 mm and 2.10 degrees away, intrinsics
    3.0 px apart' ('' within 1 mm, 1 mrad and half a pixel; K_b is compared at a's frame size)."""
    dp = float(np.linalg.norm(np.asarray(position_b, dtype=np.float64) - np.asarray(position_a, dtype=np.float64)))
    R_a, R_b = np.asarray(R_ext_a, dtype=np.float64), np.asarray(R_ext_b, dtype=np.float64)
    dr = float(np.arccos(np.clip((np.trace(R_b @ R_a.T) - 1.0) / 2.0, -1.0, 1.0)))
    dk = float(np.abs(scale_K(np.asarray(K_b, dtype=np.float64), size_b, size_a) - np.asarray(K_a)).max())
    parts = []
    if dp > 1e-3 or dr > 1e-3:
        parts.append(f"placed {dp * 1000:.1f} mm and {np.degrees(dr):.2f} degrees away")
    if dk > 0.5:
        parts.append(f"intrinsics {dk:.1f} px apart")
    return ", ".join(parts)


def served_camera_gap(served, camera: Camera, K: np.ndarray, size: tuple[int, int]) -> str:
    """``camera_gap`` from a camera as a policy server describes it (a ``CameraInfo``: row-major
    ``R_ext`` and ``K`` at ``width`` x ``height``, ``position``) to ``camera`` with ``K`` at ``size``."""
    return camera_gap(
        np.reshape(served.R_ext, (3, 3)),
        served.position,
        np.reshape(served.K, (3, 3)),
        (served.width, served.height),
        camera.R_ext,
        camera.position,
        K,
        size,
    )


def distort(xy: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N, 2) normalised image coordinates -> distorted ones (OpenCV plumb_bob, k1 k2 p1 p2 [k3])."""
    if len(D) == 0 or not np.any(D):
        return xy
    k1, k2, p1, p2 = D[:4]
    k3 = D[4] if len(D) > 4 else 0.0
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


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
    """One calibrated pinhole camera of a rig (exact in sim: the renderer uses the same numbers).

    A placed camera has an ideal K from ``fovy_deg``; a measured one (``intrinsics``) its
    calibrated K and distortion, with ``reprojection_px`` and ``calibrated_at`` from its
    calibration (``fovy_deg`` then follows from fy, for the sim renderer).
    """

    def __init__(
        self,
        name: str,
        position: np.ndarray,
        R_wc: np.ndarray,
        fovy_deg: float | None = None,
        *,
        intrinsics: Intrinsics | None = None,
        reprojection_px: float | None = None,
        calibrated_at: datetime | None = None,
    ):
        self.name = name
        self.position = np.asarray(position, dtype=np.float64)  # (3,) world
        self.R_wc = np.asarray(R_wc, dtype=np.float64)  # (3, 3) camera -> world, OpenCV axes
        self.intrinsics = intrinsics
        if fovy_deg is None:
            if intrinsics is None:
                raise ValueError(f"camera {name!r}: give fovy_deg or intrinsics")
            fovy_deg = math.degrees(2.0 * math.atan((intrinsics.height / 2.0) / intrinsics.K[1, 1]))
        self.fovy_deg = float(fovy_deg)
        self.reprojection_px = reprojection_px
        self.calibrated_at = calibrated_at

    @property
    def calibrated(self) -> bool:
        """Measured (``viewscale calibrate``) rather than placed by design."""
        return self.calibrated_at is not None

    @property
    def R_ext(self) -> np.ndarray:
        """World-to-camera rotation (the paper's R^ext)."""
        return self.R_wc.T

    @property
    def t_ext(self) -> np.ndarray:
        return -self.R_ext @ self.position

    def K(self, width: int, height: int) -> np.ndarray:
        if self.intrinsics is not None:
            return self.intrinsics.K_at(width, height)
        f = (height / 2.0) / math.tan(math.radians(self.fovy_deg) / 2.0)
        return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        """Distortion coefficients (plumb_bob), zeros for a placed camera."""
        if self.intrinsics is None or len(self.intrinsics.D) == 0:
            return np.zeros(5)
        return np.pad(self.intrinsics.D, (0, 5 - len(self.intrinsics.D)))

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world -> (N, 3) optical frame."""
        return (np.asarray(points_world) - self.position) @ self.R_ext.T

    def project(self, points_world: np.ndarray, width: int, height: int) -> np.ndarray:
        """(N, 3) world points -> (N, 2) pixel coordinates (u right, v down)."""
        pc = self.to_camera(np.atleast_2d(points_world))
        K = self.K(width, height)
        if self.intrinsics is None or not np.any(self.intrinsics.D):
            uvw = pc @ K.T
            return uvw[:, :2] / uvw[:, 2:3]
        xy = distort(pc[:, :2] / pc[:, 2:3], self.intrinsics.D)
        return xy @ K[:2, :2].T + K[:2, 2]

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
            D=[float(v) for v in self.D],
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
        D = np.asarray(calib.D, dtype=np.float64)
        ideal = (
            K[0, 0] == K[1, 1]
            and abs(K[0, 2] - (calib.width - 1) / 2.0) < 1e-9
            and abs(K[1, 2] - (calib.height - 1) / 2.0) < 1e-9
            and not np.any(D)
        )
        # A measured K (off-centre principal point, fx != fy, distortion) is kept as it is.
        intr = None if ideal else Intrinsics(int(calib.width), int(calib.height), K, D if len(D) in (4, 5) else D[:0])
        name = pose.child_frame_id or calib.frame_id
        return cls(name, np.array([t.x, t.y, t.z]), R_wc, fovy, intrinsics=intr), K


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


def _orthonormal(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``R`` (a written matrix carries rounding)."""
    u, _, vt = np.linalg.svd(R)
    return u @ vt


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
            if cam.calibrated:  # a measured camera stays where it is, whatever the framing
                assert cam.position is not None and cam.R_wc is not None and cam.intrinsics is not None
                at = cam.calibrated_at
                self.cameras[name] = Camera(
                    name,
                    np.asarray(cam.position, dtype=np.float64),
                    _orthonormal(np.asarray(cam.R_wc, dtype=np.float64)),
                    intrinsics=Intrinsics.from_spec(cam.intrinsics),
                    reprojection_px=cam.reprojection_px,
                    calibrated_at=at if at is None or at.tzinfo else at.replace(tzinfo=timezone.utc),
                )
                continue
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

    @property
    def calibrated(self) -> bool:
        """Every camera measured (``viewscale calibrate``), none placed by design."""
        return all(c.calibrated for c in self.cameras.values())


def available_rigs() -> list[str]:
    return sorted(p.stem for p in RIG_DIR.glob("*.yaml"))


def placeholder_rig(names: list[str]) -> Rig:
    """A rig of these camera names at placeholder poses: for opening cameras before their rig file
    is written (``viewscale check``, ``viewscale calibrate capture``); never for recording."""
    return Rig(RigSpec(name="uncalibrated", cameras={n: CameraSpec() for n in names}))


def _no_rig_file(path: Path) -> str:
    return (
        f"no rig file {path}: calibrate the cameras to write it (`viewscale calibrate capture`, then "
        f"`viewscale calibrate rig ... --out {path}`: README, Calibration), or name a preset "
        f"({', '.join(available_rigs())})"
    )


def load_rig(name_or_path: str, task: str | None = None) -> Rig:
    """A preset name (``five15``) or a path to a rig YAML, framed for ``task`` if one is given."""
    path = Path(name_or_path)
    if not path.suffix:
        # a preset's name, or a rig file's path without its suffix: deploy/lab for deploy/lab.yaml
        # (before, only an absolute one was found)
        is_path = "/" in name_or_path
        path = Path(f"{name_or_path}.yaml") if is_path else RIG_DIR / f"{name_or_path}.yaml"
        if not path.is_file():
            unknown = f"unknown rig {name_or_path!r}; presets: {', '.join(available_rigs())}"
            raise ConfigError(_no_rig_file(path) if is_path else unknown)
    elif not path.exists():  # (before: "config file deploy/rig-calibrated.yaml does not exist", no way on)
        raise ConfigError(_no_rig_file(path))
    data = read_yaml(path)
    data.setdefault("name", path.stem)
    try:
        rig = Rig(RigSpec.model_validate(data))
    except ValueError as exc:
        raise ConfigError(f"invalid rig {path}: {exc}") from exc
    return rig if task is None else rig.for_task(task)
