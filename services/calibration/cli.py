"""``viewscale calibrate``: print a ChArUco board; calibrate a rig's cameras into a rig file.

    viewscale calibrate board --out board.png
    viewscale calibrate rig --images data/calib --board-pose board_pose.yaml --out deploy/rig.yaml
    viewscale calibrate rig --images data/calib --gripper-poses poses.yaml --out deploy/rig.yaml
    viewscale calibrate capture --config deploy/real.yaml --images data/calib --kind intrinsics

``--images`` holds one folder per camera, named as the camera::

    data/calib/F/intrinsics/*.png   the board moved around the view: tilted, near the corners
    data/calib/F/board/*.png        the board lying still at the pose in --board-pose
    data/calib/F/hand_eye/*.png     the board on the gripper, one image per pose in --gripper-poses
                                    (file stem = the pose's key; also used for the intrinsics when
                                    there is no intrinsics/ folder)

Pose files (YAML or JSON), in the robot base frame, metres, quaternions w x y z::

    # --board-pose: the board frame (origin at the printed top-left chessboard corner, x right,
    # y down the print, z into the board)
    position: [0.45, -0.10, 0.0]
    quat_wxyz: [0, 1, 0, 0]
    # --gripper-poses: the gripper (flange or EEF) pose the robot driver reported per image
    poses:
      "000": {position: [0.4, 0.0, 0.3], quat_wxyz: [0, 1, 0, 0]}

A user's mistake (an empty folder, an unreadable image, a board not found, an error above the
threshold) is one ``error:`` line, exit 2, and nothing is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

from services.calibration.charuco import IMAGE_KINDS, BoardSpec, CalibrationError, calibrate_intrinsics, read_images
from services.calibration.extrinsics import from_board_pose, hand_eye, pose_matrix
from services.calibration.rigfile import CameraCalibration, check_errors, write_rig
from services.core.config import ConfigError
from services.core.rig import CALIBRATION_MAX_ERROR_PX
from services.core.runtime import interrupt_on_signals


def _read_pose_file(path: str) -> dict:
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"pose file {p} does not exist")
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise CalibrationError(f"pose file {p} is not valid YAML or JSON: {exc}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"pose file {p} must hold a mapping")
    return data


def _pose(entry, where: str) -> np.ndarray:
    if not isinstance(entry, dict) or "position" not in entry or "quat_wxyz" not in entry:
        raise CalibrationError(f"{where}: a pose needs position [x, y, z] and quat_wxyz [w, x, y, z]")
    try:
        return pose_matrix(entry["position"], entry["quat_wxyz"])
    except (CalibrationError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{where}: {exc}") from None


def read_board_pose(path: str) -> np.ndarray:
    return _pose(_read_pose_file(path), str(path))


def read_gripper_poses(path: str) -> dict[str, np.ndarray]:
    data = _read_pose_file(path).get("poses")
    if not isinstance(data, dict) or not data:
        raise CalibrationError(f"pose file {path}: needs a non-empty 'poses' mapping (image stem -> pose)")
    return {str(k): _pose(v, f"{path}: pose {k!r}") for k, v in data.items()}


def calibrate_camera(
    name: str,
    folder: Path,
    board: BoardSpec,
    *,
    board_pose: np.ndarray | None = None,
    gripper_poses: dict[str, np.ndarray] | None = None,
) -> CameraCalibration:
    """One camera: intrinsics, then its pose in the base frame by one of the two methods."""
    if (board_pose is None) == (gripper_poses is None):
        raise CalibrationError("give either a board pose or gripper poses")
    if board_pose is not None:
        intr = calibrate_intrinsics(name, board, read_images(folder / "intrinsics", name))
        ext = from_board_pose(name, board, intr, read_images(folder / "board", name), board_pose)
        method = "charuco board at a measured pose"
    else:
        he_images = read_images(folder / "hand_eye", name)
        intr_dir = folder / "intrinsics"
        intr_images = read_images(intr_dir, name) if intr_dir.is_dir() else he_images
        intr = calibrate_intrinsics(name, board, intr_images)
        assert gripper_poses is not None
        ext = hand_eye(name, board, intr, he_images, gripper_poses)
        method = "hand-eye, charuco board on the gripper"
    return CameraCalibration(
        name, ext.position, ext.R_wc, intr.K, intr.D, intr.width, intr.height, intr.rms_px, ext.rms_px, method
    )


def _board(args: argparse.Namespace) -> BoardSpec:
    try:
        sx, sy = (int(v) for v in args.squares.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"--squares must look like 7x5, not {args.squares!r}") from None
    return BoardSpec(sx, sy, args.square_length, args.marker_length, args.dictionary)


def _err(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return 2


MAX_BOARD_PX = 20000  # a side of the printable board image


def _print_board(args: argparse.Namespace) -> int:
    try:
        board = _board(args)
        if args.px_per_square < 20:
            raise CalibrationError(f"--px-per-square must be at least 20, got {args.px_per_square}")
        margin = 2 * (args.px_per_square // 2)  # board.image's margins
        w, h = board.squares_x * args.px_per_square + margin, board.squares_y * args.px_per_square + margin
        if max(w, h) > MAX_BOARD_PX:  # (before, OpenCV's out-of-memory traceback)
            raise CalibrationError(
                f"the board would be {w}x{h} px; at most {MAX_BOARD_PX} px a side (lower --px-per-square: "
                "200 px per 40 mm square is 127 dpi, 472 is 300 dpi)"
            )
        out = Path(args.out)
        if out.is_dir():
            raise CalibrationError(f"--out {out} is a directory: name the image file, e.g. {out / 'board.png'}")
        if out.suffix.lower() not in (".png", ".bmp", ".tif", ".tiff"):
            raise CalibrationError(
                f"--out {out}: write the board losslessly (.png), not {out.suffix or 'a file without suffix'}"
            )
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CalibrationError(f"--out {out}: {exc.strerror or exc}") from None
        img = board.image(args.px_per_square)
        if not cv2.imwrite(str(out), img):
            raise CalibrationError(f"cannot write {out}")
    except CalibrationError as exc:
        return _err(str(exc))
    w_mm = board.squares_x * board.square_length * 1000
    h_mm = board.squares_y * board.square_length * 1000
    print(
        f"board {board.squares_x}x{board.squares_y} {board.dictionary} -> {out} ({img.shape[1]}x{img.shape[0]} px); "
        f"print it so the chessboard is {w_mm:g} x {h_mm:g} mm (squares {board.square_length * 1000:g} mm, markers "
        f"{board.marker_length * 1000:g} mm), measure a square and pass what you measured"
    )
    return 0


def _calibrate_rig(args: argparse.Namespace) -> int:
    try:
        board = _board(args)
        root = Path(args.images)
        if not root.is_dir():
            raise CalibrationError(f"--images {root} is not a directory")
        if args.cameras:
            names = [c.strip() for c in args.cameras.split(",") if c.strip()]
        else:
            names = sorted(p.name for p in root.iterdir() if p.is_dir())
        if not names:
            raise CalibrationError(f"no camera folders under {root} (one per camera, named as the camera)")
        if not args.max_error_px > 0:
            raise CalibrationError(f"--max-error-px must be positive, got {args.max_error_px}")
        board_pose = read_board_pose(args.board_pose) if args.board_pose else None
        gripper = read_gripper_poses(args.gripper_poses) if args.gripper_poses else None
        out = Path(args.out)
        if not out.parent.is_dir():
            raise CalibrationError(f"--out {out}: directory {out.parent} does not exist")
        # checked before the cameras are calibrated (before: after, or never: camera.rig cannot load a
        # rig file without a .yaml suffix, it is taken for a preset's name)
        if out.is_dir():
            raise CalibrationError(f"--out {out} is a directory: name the rig file, e.g. {out / 'rig.yaml'}")
        if out.suffix not in (".yaml", ".yml"):
            raise CalibrationError(
                f"--out {out}: a rig file is YAML, and camera.rig loads it by its .yaml suffix: "
                f"--out {out.with_suffix('.yaml')}"
            )
        results = []
        for name in names:
            c = calibrate_camera(name, root / name, board, board_pose=board_pose, gripper_poses=gripper)
            print(
                f"camera {name}: {c.width}x{c.height} fx {c.K[0, 0]:.1f} fy {c.K[1, 1]:.1f} "
                f"cx {c.K[0, 2]:.1f} cy {c.K[1, 2]:.1f}; intrinsics {c.intrinsics_rms_px:.3f} px, "
                f"extrinsics {c.extrinsics_rms_px:.3f} px; position {np.round(c.position, 4).tolist()} m",
                file=sys.stderr,
            )
            results.append(c)
        check_errors(results, args.max_error_px)
        rig = write_rig(out, args.name or out.stem, results, max_error_px=args.max_error_px)
    except (CalibrationError, ConfigError) as exc:
        return _err(str(exc))
    except OSError as exc:
        return _err(f"{exc.strerror or exc}: {exc.filename or args.out}")
    print(f"calibrated rig {rig.name!r} ({', '.join(rig.names)}) -> {out}")
    return 0


def _capture(args: argparse.Namespace) -> int:
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")  # a sim rig renders headless, as the camera service does
    from services.calibration.capture import Capture, next_command, run_capture
    from services.core.cli_args import service_overrides

    try:
        overrides = service_overrides(args.set, ("camera", "robot"))
    except ValueError as exc:
        return _err(str(exc))
    if args.count is not None and args.count < 1:
        return _err(f"--count must be at least 1, got {args.count}")
    if not 0 <= args.every < float("inf"):
        return _err(f"--every must be 0 or more seconds, got {args.every:g}")
    try:
        board = _board(args)
        # SIGTERM and SIGHUP (a closed terminal) stop it as Ctrl-C does, between two shots' files,
        # never in the middle of writing one (before: killed on the spot)
        interrupt_on_signals()
        with Capture(args.config, Path(args.images), args.kind, board, overrides) as cap:
            shots = run_capture(cap, args.count, args.every, say=lambda m: print(m, flush=True))
    except (CalibrationError, ConfigError, ConnectionError) as exc:  # (a router not there)
        return _err(str(exc))
    except KeyboardInterrupt as exc:
        print(f"interrupted ({exc or 'SIGINT'}): the shots taken are kept", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001  (a driver that cannot open: its reason, not a traceback)
        return _err(f"cannot open the {args.kind} capture: {type(exc).__name__}: {exc}")
    if not shots:
        print("no shot taken")
        return 1 if args.count else 0
    seen = {n: sum(1 for s in shots if s.corners[n]) for n in shots[0].corners}
    print(
        f"{len(shots)} shots of {args.kind}; with the board: "
        + ", ".join(f"{n} {k}" for n, k in seen.items())
        + f"\nnext, with every kind taken: {next_command(Path(args.images), args.kind)}"
    )
    return 0


CAPTURE_DESCRIPTION = """\
    viewscale calibrate capture --config deploy/real.yaml --images data/calib --kind intrinsics
    viewscale calibrate capture --config deploy/real.yaml --images data/calib --kind board
    viewscale calibrate capture --config deploy/real.yaml --images data/calib --kind hand_eye

The cameras are opened through the same drivers as the services, from the session file, with the
camera service not running (it would hold the devices). A shot saves, for every camera, its first
frame captured after the shot was asked for, as <images>/<camera>/<kind>/<NNN>.png (lossless), and
says how many board corners each holds. Shot numbers go on from the images already there: a second
session adds shots, it never replaces one.

hand_eye takes the arm's EEF pose from robot/state on the session's bus: run the router, the robot
service and a teleop (the SpaceMouse, to move the arm between shots) with the same session file, as
for a collection. The arm stays the robot service's, behind its safety layer; this command never
connects to it. The pose is read before and after the frames (a shot while the arm moves is
refused) and written under the key NNN to <images>/hand_eye_poses.yaml, the --gripper-poses file
of `calibrate rig`.

Interactive: Enter takes a shot, q and Enter (or Ctrl-D) ends. --count N --every S: N shots S
seconds apart, hands-free while someone moves the board. Frames are taken at camera.width x
camera.height, the size the session records; --set camera.width=1280 --set camera.height=720
takes them at the device's size for finer corners (the rig file's K is scaled to the recorded size).
"""


def _board_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--squares", default="7x5", help="squares along x and y of the board (default 7x5)")
    p.add_argument("--square-length", type=float, default=0.04, help="printed square side in m (default 0.04)")
    p.add_argument("--marker-length", type=float, default=0.03, help="printed marker side in m (default 0.03)")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ArUco dictionary (default DICT_5X5_100)")


def add_calibrate_command(subparsers: argparse._SubParsersAction) -> None:
    """Register ``calibrate board`` and ``calibrate rig`` on the top-level ``viewscale`` parser."""
    p = subparsers.add_parser("calibrate", help="ChArUco camera calibration into a rig file")
    sub = p.add_subparsers(dest="calibrate_command", required=True, metavar="ACTION")

    b = sub.add_parser("board", help="write a printable ChArUco board image")
    b.add_argument("--out", required=True, help="image file to write (.png)")
    b.add_argument("--px-per-square", type=int, default=200, help="image pixels per square (default 200)")
    _board_options(b)
    b.set_defaults(func=_print_board)

    r = sub.add_parser(
        "rig",
        help="intrinsics and base-frame poses of every camera -> a calibrated rig YAML",
        description=(__doc__ or "").split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    r.add_argument("--images", required=True, help="directory with one image folder per camera (see above)")
    r.add_argument("--out", required=True, help="rig YAML to write (replaced only when every camera passes)")
    how = r.add_mutually_exclusive_group(required=True)
    how.add_argument("--board-pose", help="pose file: the board lies still at this pose (images in <camera>/board/)")
    how.add_argument("--gripper-poses", help="pose file: the board is on the gripper (images in <camera>/hand_eye/)")
    r.add_argument("--cameras", default=None, help="comma-separated cameras (default: every folder under --images)")
    r.add_argument("--name", default=None, help="rig name (default: the output file's stem)")
    r.add_argument(
        "--max-error-px",
        type=float,
        default=CALIBRATION_MAX_ERROR_PX,
        help=f"refuse a camera whose RMS reprojection error is above this (default {CALIBRATION_MAX_ERROR_PX:g} px)",
    )
    _board_options(r)
    r.set_defaults(func=_calibrate_rig)

    # (capture itself is imported when it runs: it brings the camera drivers and zenoh, which every
    # `viewscale` command would otherwise load while building its parser)
    c = sub.add_parser(
        "capture",
        help="take the images `calibrate rig` reads, from every camera of a session file at once",
        description=CAPTURE_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    c.add_argument("--config", required=True, help="the session's YAML (e.g. deploy/real.yaml)")
    c.add_argument("--images", required=True, help="the folder `calibrate rig --images` reads (e.g. data/calib)")
    c.add_argument("--kind", required=True, choices=IMAGE_KINDS, help="which images (see above)")
    c.add_argument("--count", type=int, default=None, help="take this many shots, hands-free (default: one per Enter)")
    c.add_argument("--every", type=float, default=2.0, help="seconds between --count shots (default 2)")
    c.add_argument(
        "--set", action="append", default=[], metavar="SERVICE.KEY=VALUE", help="override, e.g. camera.width=1280"
    )
    _board_options(c)
    c.set_defaults(func=_capture)
