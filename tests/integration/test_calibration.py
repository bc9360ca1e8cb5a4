"""Calibration on images of a ChArUco board rendered by MuJoCo at known poses.

The board image (cv2.aruco) is the texture of a flat quad on a mocap body (the "gripper"): its
corners sit at the board frame's metric coordinates, so every corner's world position is known
exactly. Two fixed MuJoCo cameras (known pose, fovy 45 degrees at 640x480, hence a known K with
the principal point at ((W - 1) / 2, (H - 1) / 2)) see it; shadows and reflections are off and
the board is emissive, so the lighting does not move the corners.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from dataset_fixtures import T0, write_episode
from scipy.spatial.transform import Rotation

from services.calibration.charuco import BoardSpec, CalibrationError, calibrate_intrinsics, read_images
from services.calibration.extrinsics import from_board_pose, hand_eye
from services.calibration.rigfile import write_rig
from services.cli import main as viewscale
from services.core.rig import Camera, load_rig, look_at
from services.dataset.build import BuildParams, build_dataset
from services.dataset.episodes import EpisodeError

W, H, FOVY = 640, 480, 45.0
BOARD = BoardSpec(squares_x=8, squares_y=6, square_length=0.035, marker_length=0.026)
PPS, MARGIN = 80, 40  # texture px per square, white margin px
TARGET = np.array([0.45, 0.0, 0.1])
MOUNT = np.eye(4)  # T_gripper_board: the board 6 cm beyond the flange, turned 30 degrees about z
MOUNT[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
MOUNT[:3, 3] = [0.02, -0.01, 0.06]
BOARD_CENTRE = np.array([BOARD.squares_x * BOARD.square_length / 2, BOARD.squares_y * BOARD.square_length / 2, 0])


def _camera(name: str, azimuth_deg: float) -> Camera:
    a = math.radians(azimuth_deg)
    pos = TARGET + 0.75 * np.array([math.cos(a) * math.cos(0.6), math.sin(a) * math.cos(0.6), math.sin(0.6)])
    return Camera(name, pos, look_at(pos, TARGET), FOVY)


CAMS = {"F": _camera("F", 0.0), "L": _camera("L", 20.0)}


def _T(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _quat_wxyz(R: np.ndarray) -> list[float]:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [float(w), float(x), float(y), float(z)]


def _scene_xml() -> str:
    m = MARGIN / PPS * BOARD.square_length
    img = BOARD.image(PPS, MARGIN)
    wm, hm = img.shape[1] / PPS * BOARD.square_length, img.shape[0] / PPS * BOARD.square_length
    # The quad is the printed image, margin included, in board coordinates (z = 0); wound so its
    # front faces -z (the printed side), texcoords (0, 0) at the image's top-left.
    verts = [(-m, -m, 0), (wm - m, -m, 0), (wm - m, hm - m, 0), (-m, hm - m, 0)]
    R, p = MOUNT[:3, :3], MOUNT[:3, 3]
    cams = "\n".join(
        f'  <camera name="{c.name}" pos="{" ".join(f"{v:.17g}" for v in c.position)}" '
        f'xyaxes="{" ".join(f"{v:.17g}" for v in c.mujoco_xyaxes)}" fovy="{FOVY}"/>'
        for c in CAMS.values()
    )
    return f"""<mujoco>
 <compiler inertiafromgeom="false"/>
 <visual><global offwidth="{W}" offheight="{H}"/><quality shadowsize="0"/>
  <headlight ambient="0.4 0.4 0.4" diffuse="0.5 0.5 0.5" specular="0 0 0"/></visual>
 <asset>
  <texture name="board" type="2d" file="board.png"/>
  <material name="board" texture="board" rgba="1 1 1 1" emission="1" specular="0" shininess="0" reflectance="0"/>
  <mesh name="board" inertia="shell" vertex="{" ".join(f"{v:.12g}" for q in verts for v in q)}"
        texcoord="0 0 1 0 1 1 0 1" face="0 3 2 0 2 1"/>
 </asset>
 <worldbody>
  <geom type="plane" size="2 2 0.1" pos="0 0 -0.3" rgba="0.3 0.3 0.3 1"/>
  <body name="gripper" mocap="true">
   <geom type="mesh" mesh="board" material="board" contype="0" conaffinity="0"
         pos="{" ".join(f"{v:.12g}" for v in p)}" quat="{" ".join(f"{v:.12g}" for v in _quat_wxyz(R))}"/>
  </body>
{cams}
 </worldbody>
</mujoco>"""


class Scene:
    def __init__(self):
        import mujoco

        from sim.scene import MultiCameraRenderer

        self._mj = mujoco
        ok, png = cv2.imencode(".png", BOARD.image(PPS, MARGIN))
        self.model = mujoco.MjModel.from_xml_string(_scene_xml(), {"board.png": png.tobytes()})
        self.data = mujoco.MjData(self.model)
        self.renderer = MultiCameraRenderer(self.model, list(CAMS), W, H)

    def render_board(self, T_base_board: np.ndarray) -> dict[str, np.ndarray]:
        """Every camera's BGR image of the board at ``T_base_board`` (moving the gripper to match)."""
        return self.render_gripper(T_base_board @ np.linalg.inv(MOUNT))

    def render_gripper(self, T_base_gripper: np.ndarray) -> dict[str, np.ndarray]:
        self.data.mocap_pos[0] = T_base_gripper[:3, 3]
        self.data.mocap_quat[0] = _quat_wxyz(T_base_gripper[:3, :3])
        self._mj.mj_forward(self.model, self.data)
        return {k: cv2.cvtColor(v, cv2.COLOR_RGB2BGR) for k, v in self.renderer.render(self.data).items()}


def _facing(cam: Camera, centre: np.ndarray, tilt_deg) -> np.ndarray:
    """T_base_board: the board centred on ``centre``, its printed face towards ``cam``, then tilted."""
    R = look_at(cam.position, centre) @ Rotation.from_euler("xyz", tilt_deg, degrees=True).as_matrix()
    return _T(R, centre - R @ BOARD_CENTRE)


def _intrinsic_views(cam: Camera, n: int, rng) -> list[np.ndarray]:
    views = []
    axis = (TARGET - cam.position) / np.linalg.norm(TARGET - cam.position)
    right, down = cam.R_wc[:, 0], cam.R_wc[:, 1]
    for _ in range(n):
        d = rng.uniform(0.42, 0.6)
        centre = cam.position + d * axis + d * (rng.uniform(-0.22, 0.22) * right + rng.uniform(-0.15, 0.15) * down)
        tilt = [
            rng.choice([-1, 1]) * rng.uniform(15, 40),
            rng.choice([-1, 1]) * rng.uniform(15, 40),
            rng.uniform(-30, 30),
        ]
        views.append(_facing(cam, centre, tilt))
    return views


_R_STAND = Rotation.from_euler("y", 20, degrees=True).as_matrix() @ np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]])
BOARD_POSE = _T(_R_STAND, np.array([0.45, 0.0, 0.08]) - _R_STAND @ BOARD_CENTRE)  # on a stand tilted 20 degrees


def _gripper_poses(n: int, rng) -> list[np.ndarray]:
    """Gripper poses that show the board to both cameras, rotating about varied axes."""
    mid = (CAMS["F"].position + CAMS["L"].position) / 2
    base_board = _facing(Camera("mid", mid, look_at(mid, TARGET), FOVY), TARGET + [0.05, 0.02, 0.0], [0, 0, 0])
    poses = []
    for _ in range(n):
        dR = Rotation.from_rotvec(np.radians(rng.uniform(-25, 25, 3))).as_matrix()
        board = _T(dR @ base_board[:3, :3], base_board[:3, 3] + rng.uniform(-0.06, 0.06, 3))
        poses.append(board @ np.linalg.inv(MOUNT))
    return poses


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Rendered image folders in ``viewscale calibrate rig``'s layout, and the poses behind them."""
    root = tmp_path_factory.mktemp("calib")
    scene = Scene()
    rng = np.random.default_rng(7)
    for name, cam in CAMS.items():
        d = root / name / "intrinsics"
        d.mkdir(parents=True)
        for i, T in enumerate(_intrinsic_views(cam, 12, rng)):
            cv2.imwrite(str(d / f"{i:03d}.png"), scene.render_board(T)[name])
    for name, img in scene.render_board(BOARD_POSE).items():
        (root / name / "board").mkdir()
        cv2.imwrite(str(root / name / "board" / "000.png"), img)
    grippers = _gripper_poses(10, rng)
    poses = {}
    for i, T in enumerate(grippers):
        for name, img in scene.render_gripper(T).items():
            (root / name / "hand_eye").mkdir(exist_ok=True)
            cv2.imwrite(str(root / name / "hand_eye" / f"{i:03d}.png"), img)
        poses[f"{i:03d}"] = {"position": T[:3, 3].tolist(), "quat_wxyz": _quat_wxyz(T[:3, :3])}
    (root / "board_pose.yaml").write_text(
        yaml.safe_dump({"position": BOARD_POSE[:3, 3].tolist(), "quat_wxyz": _quat_wxyz(BOARD_POSE[:3, :3])})
    )
    (root / "gripper_poses.yaml").write_text(yaml.safe_dump({"poses": poses}))
    scene.renderer.close()
    # A partial board: slid so that most of it leaves F's view.
    partial = root / "partial"
    shift = _T(np.eye(3), CAMS["F"].R_wc[:, 0] * 0.5)
    img = Scene().render_board(shift @ BOARD_POSE)["F"]
    (partial / "F" / "board").mkdir(parents=True)
    cv2.imwrite(str(partial / "F" / "board" / "000.png"), img)
    return root


def _pose_errors(position, R_wc, cam: Camera) -> tuple[float, float]:
    """(mm, degrees) between an estimated camera pose and the true one."""
    dp = float(np.linalg.norm(np.asarray(position) - cam.position)) * 1000
    dR = Rotation.from_matrix(np.asarray(R_wc).T @ cam.R_wc).magnitude()
    return dp, math.degrees(dR)


def _k_errors(K: np.ndarray, cam: Camera) -> dict[str, float]:
    true = cam.K(W, H)
    return {
        k: abs(K[i, j] / true[i, j] - 1)
        for k, (i, j) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items()
    }


def test_intrinsics_within_one_percent(rendered):
    for name, cam in CAMS.items():
        intr = calibrate_intrinsics(name, BOARD, read_images(rendered / name / "intrinsics", name))
        err = _k_errors(intr.K, cam)
        print(f"{name}: rms {intr.rms_px:.3f} px, relative K errors { ({k: f'{v:.4%}' for k, v in err.items()}) }")
        assert max(err.values()) < 0.01, err
        assert intr.rms_px < 0.5
        assert not intr.skipped


def test_board_at_a_measured_pose_gives_the_camera_pose(rendered):
    for name, cam in CAMS.items():
        intr = calibrate_intrinsics(name, BOARD, read_images(rendered / name / "intrinsics", name))
        ext = from_board_pose(name, BOARD, intr, read_images(rendered / name / "board", name), BOARD_POSE)
        dp, dr = _pose_errors(ext.position, ext.R_wc, cam)
        print(f"{name}: board at a measured pose -> {dp:.2f} mm, {dr:.3f} deg (rms {ext.rms_px:.3f} px)")
        assert dp < 2.0 and dr < 0.2


def test_hand_eye_gives_the_camera_pose(rendered):
    poses = yaml.safe_load((rendered / "gripper_poses.yaml").read_text())["poses"]
    from services.calibration.cli import read_gripper_poses

    grippers = read_gripper_poses(str(rendered / "gripper_poses.yaml"))
    assert set(grippers) == set(poses)
    for name, cam in CAMS.items():
        intr = calibrate_intrinsics(name, BOARD, read_images(rendered / name / "intrinsics", name))
        ext = hand_eye(name, BOARD, intr, read_images(rendered / name / "hand_eye", name), grippers)
        dp, dr = _pose_errors(ext.position, ext.R_wc, cam)
        mount_mm = float(np.linalg.norm(ext.mount[:3, 3] - MOUNT[:3, 3])) * 1000
        print(f"{name}: hand-eye -> {dp:.2f} mm, {dr:.3f} deg (rms {ext.rms_px:.3f} px; mount off {mount_mm:.2f} mm)")
        assert dp < 2.0 and dr < 0.2


def test_a_blurred_board_is_refused_naming_the_camera(rendered):
    images = [(n, cv2.GaussianBlur(img, (0, 0), 6)) for n, img in read_images(rendered / "F" / "intrinsics", "F")]
    with pytest.raises(
        CalibrationError, match=r"camera F: the board is usable in only 0 of 12 images.*board not found"
    ):
        calibrate_intrinsics("F", BOARD, images)


def test_a_partial_board_is_refused_naming_the_camera(rendered):
    intr = calibrate_intrinsics("F", BOARD, read_images(rendered / "F" / "intrinsics", "F"))
    with pytest.raises(CalibrationError, match=r"camera F: the board at its measured pose is not usable.*corners"):
        from_board_pose("F", BOARD, intr, read_images(rendered / "partial" / "F" / "board", "F"), BOARD_POSE)


BOARD_ARGS = ["--squares", "8x6", "--square-length", "0.035", "--marker-length", "0.026"]


def test_cli_writes_a_rig_that_projects_like_the_true_cameras(rendered, tmp_path):
    out = tmp_path / "lab.yaml"
    cmd = [sys.executable, "-m", "services.cli", "calibrate", "rig", "--images", str(rendered), "--cameras", "F,L"]
    cmd += ["--board-pose", str(rendered / "board_pose.yaml"), "--out", str(out), *BOARD_ARGS]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert r.returncode == 0, r.stderr
    assert "calibrated rig 'lab' (F, L)" in r.stdout
    rig = load_rig(str(out))
    assert rig.calibrated and rig.names == ["F", "L"]
    # Every corner of the board, anywhere in the workspace, lands where the true camera puts it.
    rng = np.random.default_rng(1)
    points = TARGET + rng.uniform(-0.15, 0.15, (200, 3))
    for name, cam in CAMS.items():
        got = rig.cameras[name]
        assert got.calibrated_at is not None and got.reprojection_px < 0.5
        assert datetime.now(timezone.utc) - got.calibrated_at < timedelta(minutes=5)
        err = np.abs(got.project(points, W, H) - cam.project(points, W, H)).max()
        print(f"{name}: max projection difference {err:.3f} px over 200 workspace points")
        assert err < 1.0
        msg = got.calibration_msg(W, H, 0)
        back, K = Camera.from_msgs(msg, got.pose_msg(0))
        np.testing.assert_allclose(K, got.K(W, H))
        np.testing.assert_allclose(back.project(points, W, H), got.project(points, W, H), atol=1e-6)


def test_a_board_shot_taken_by_capture_calibrates_the_camera_pose(rendered, tmp_path, capsys):
    """`calibrate capture --kind board` through a real OpenCV camera (an MJPG recording of the
    rendered board at its measured pose stands in for camera F), then `calibrate rig` on what it
    saved: the pose within the same bounds as from the rendered PNGs. The intrinsics images are the
    rendered ones, put where an earlier capture session would have saved them."""
    img = cv2.imread(str(rendered / "F" / "board" / "000.png"))
    video = tmp_path / "F-board.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (W, H))
    for _ in range(200):
        writer.write(img)
    writer.release()
    calib = tmp_path / "calib"
    shutil.copytree(rendered / "F" / "intrinsics", calib / "F" / "intrinsics")
    session = tmp_path / "session.yaml"
    camera = {"driver": {"type": "opencv", "cameras": {"F": {"source": str(video)}}}, "rig": str(tmp_path / "lab.yaml")}
    session.write_text(yaml.safe_dump({"camera": camera | {"width": W, "height": H, "fps": 20.0}}))
    capture = ["calibrate", "capture", "--config", str(session), "--images", str(calib), "--kind", "board"]
    assert viewscale([*capture, "--count", "1", *BOARD_ARGS]) == 0
    assert f"[000] F {BOARD.n_corners}/{BOARD.n_corners} corners" in capsys.readouterr().out
    out = tmp_path / "lab.yaml"
    rig_args = ["--images", str(calib), "--board-pose", str(rendered / "board_pose.yaml"), "--out", str(out)]
    assert viewscale(["calibrate", "rig", *rig_args, *BOARD_ARGS]) == 0, capsys.readouterr().err
    cam = load_rig(str(out)).cameras["F"]
    dp, dr = _pose_errors(cam.position, cam.R_wc, CAMS["F"])
    print(f"F from a captured board shot -> {dp:.2f} mm, {dr:.3f} deg")
    assert dp < 2.0 and dr < 0.2


def test_cli_refuses_bad_input_with_one_error_line(rendered, tmp_path, capsys):
    out = tmp_path / "rig.yaml"
    base = ["calibrate", "rig", "--out", str(out), "--board-pose", str(rendered / "board_pose.yaml"), *BOARD_ARGS]

    empty = tmp_path / "empty"
    (empty / "F" / "intrinsics").mkdir(parents=True)
    bad = tmp_path / "bad"
    (bad / "F" / "intrinsics").mkdir(parents=True)
    (bad / "F" / "intrinsics" / "000.png").write_bytes(b"not a png")
    cases = [
        (["--images", str(empty)], r"^error: camera F: no images \(.*\) in .*empty/F/intrinsics$"),
        (["--images", str(bad)], r"^error: camera F: cannot read image .*000\.png$"),
        (
            ["--images", str(rendered), "--cameras", "F", "--max-error-px", "0.01"],
            r"^error: camera F: reprojection error 0\.\d+ px .* above the 0\.01 px threshold; nothing written",
        ),
        # refused before any camera is calibrated (before: a folder failed after them all; a file without
        # .yaml was written, and camera.rig took its path for an unknown preset's name)
        (["--images", str(empty), "--out", str(tmp_path)], r"^error: --out .* is a directory: name the rig file"),
        (
            ["--images", str(empty), "--out", str(tmp_path / "lab")],
            r"^error: --out .*/lab: a rig file is YAML, and camera.rig loads it by its .yaml suffix: .*/lab\.yaml$",
        ),
    ]
    for extra, pattern in cases:
        code = viewscale(base + extra)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2
        assert len([line for line in err if line.startswith("error:")]) == 1
        assert any(__import__("re").match(pattern, line) for line in err), err
        assert not out.exists() and not list(tmp_path.glob("*.tmp"))


def test_board_image_is_written(tmp_path, capsys):
    assert viewscale(["calibrate", "board", "--out", str(tmp_path / "b.png"), "--px-per-square", "50"]) == 0
    img = cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (5 * 50 + 50, 7 * 50 + 50)
    assert "280 x 200 mm" in capsys.readouterr().out
    # into a folder not made yet (before: 'cannot write'); too large a board is refused before OpenCV
    # tries to allocate it (before: its out-of-memory traceback)
    assert viewscale(["calibrate", "board", "--out", str(tmp_path / "new" / "b.png"), "--px-per-square", "20"]) == 0
    assert (tmp_path / "new" / "b.png").is_file()
    assert viewscale(["calibrate", "board", "--out", str(tmp_path / "huge.png"), "--px-per-square", "100000"]) == 2
    assert "the board would be 800000x600000 px; at most 20000" in capsys.readouterr().err
    assert not (tmp_path / "huge.png").exists()
    # a folder as --out (before: 'write the board losslessly (.png), not no suffix')
    assert viewscale(["calibrate", "board", "--out", str(tmp_path / "new")]) == 2
    assert f"--out {tmp_path / 'new'} is a directory: name the image file" in capsys.readouterr().err
    assert viewscale(["calibrate", "board", "--out", str(tmp_path / "board")]) == 2
    assert "write the board losslessly (.png), not a file without suffix" in capsys.readouterr().err
    # a negative square (before: 'marker length 0.03 m must be ... below the square length -1.0 m')
    assert viewscale(["calibrate", "board", "--out", str(tmp_path / "b2.png"), "--square-length", "-1"]) == 2
    assert "error: square length -1.0 m must be a positive number of metres" in capsys.readouterr().err


# -- camera-space dataset builds refuse a missing or stale calibration ------------------------------


def _calibrated_rig(path: Path, at: datetime, shift: float = 0.0) -> Path:
    """A calibrated two-camera rig: the five15 cameras F and FL written as measured ones."""
    from services.calibration.rigfile import CameraCalibration

    src = load_rig("five15")
    cams = []
    for n in ("F", "FL"):
        c = src.cameras[n]
        K = c.K(64, 48)
        K[0, 2] += 0.7  # an off-centre principal point, as measured
        cams.append(
            CameraCalibration(
                n, c.position + [shift, 0, 0], c.R_wc, K, np.array([0.01, 0, 0, 0, 0]), 64, 48, 0.2, 0.3, "test"
            )
        )
    write_rig(path, path.stem, cams, calibrated_at=at)
    return path


def test_dataset_build_refuses_missing_or_stale_calibration(tmp_path):
    recorded = datetime.fromtimestamp(T0 / 1e9, timezone.utc)
    rig = _calibrated_rig(tmp_path / "lab.yaml", recorded - timedelta(days=3))
    raw = tmp_path / "raw"
    write_episode(raw, "ep0", 24, rig=str(rig), cameras=["F", "FL"])
    params = BuildParams(views=("F", "FL"), space="camera", image_size=(32, 24), Tp=4, Ta=2)
    result = build_dataset(raw, tmp_path / "ds", params, contact_episodes=0)  # fresh enough: builds
    assert result.built == 1

    # Recalibrated since (the camera moved 5 mm): the episode's calibration is no longer the rig's.
    _calibrated_rig(rig, recorded + timedelta(days=10), shift=0.005)
    with pytest.raises(EpisodeError, match=r"ep0\.mcap: camera 'F' calibration is stale: .*differs.*5\.0 mm"):
        build_dataset(raw, tmp_path / "ds", params, contact_episodes=0)
    # ... unless the build is pointed at the calibration that held then.
    old = _calibrated_rig(tmp_path / "lab-old.yaml", recorded - timedelta(days=3))
    params_old = BuildParams(views=("F", "FL"), space="camera", image_size=(32, 24), Tp=4, Ta=2, rig=str(old))
    assert build_dataset(raw, tmp_path / "ds", params_old, contact_episodes=0).reused == 1

    # Calibrated 40 days before the recording: stale under the 30-day default, fine with a longer limit.
    _calibrated_rig(old, recorded - timedelta(days=40))
    with pytest.raises(EpisodeError, match=r"camera 'F' calibration is stale: calibrated .* 40 days before"):
        build_dataset(raw, tmp_path / "ds2", params_old, contact_episodes=0)
    lenient = BuildParams(
        views=("F",), space="camera", image_size=(32, 24), Tp=4, Ta=2, rig=str(old), max_calibration_age_days=60
    )
    assert build_dataset(raw, tmp_path / "ds2", lenient, contact_episodes=0).built == 1
    # Base-frame data does not need a calibration at all.
    base = BuildParams(views=("F",), space="base", image_size=(32, 24), Tp=4, Ta=2)
    assert build_dataset(raw, tmp_path / "ds3", base, contact_episodes=0).built == 1

    # A rig the build cannot find: nothing to check the calibration against.
    raw2 = tmp_path / "raw2"
    write_episode(raw2, "ep1", 24, rig=str(rig), cameras=["F"])
    rig.unlink()
    code = viewscale(
        ["dataset", "build", "--raw", str(raw2), "--views", "F", "--space", "camera", "--out", str(tmp_path / "ds4")]
    )
    assert code == 2


def test_sim_recordings_need_no_calibration_date(tmp_path):
    raw = tmp_path / "raw"
    write_episode(raw, "sim", 24, rig="five15", cameras=["F"])
    params = BuildParams(views=("F",), space="camera", image_size=(32, 24), Tp=4, Ta=2)
    assert build_dataset(raw, tmp_path / "ds", params, contact_episodes=0).built == 1
