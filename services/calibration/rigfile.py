"""The calibrated rig file: what ``viewscale calibrate`` writes and every service reads.

One YAML per rig (format in ``services/core/rig.py``): per camera its pose in the robot base
frame, its intrinsics at the calibration image size, the RMS reprojection error and the date.
A calibration whose error is above the threshold is refused, and nothing is written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import yaml

from services.calibration.charuco import CalibrationError
from services.core.config import ConfigError
from services.core.rig import CALIBRATION_MAX_ERROR_PX, Rig, load_rig


@dataclass
class CameraCalibration:
    """One camera's calibration, ready to be written."""

    name: str
    position: np.ndarray  # (3,) base frame (m)
    R_wc: np.ndarray  # (3, 3) camera -> base, optical axes as columns
    K: np.ndarray  # (3, 3) at width x height
    D: np.ndarray  # (4,) or (5,) plumb_bob
    width: int
    height: int
    intrinsics_rms_px: float
    extrinsics_rms_px: float
    method: str  # "board at a measured pose" or "hand-eye, board on the gripper"

    @property
    def reprojection_px(self) -> float:
        """The worse of the two fits: what the file records and the threshold applies to."""
        return max(self.intrinsics_rms_px, self.extrinsics_rms_px)


def _f(v: float) -> float:
    return float(f"{float(v):.12g}")


def camera_entry(c: CameraCalibration, calibrated_at: datetime) -> dict:
    return {
        "position": [_f(v) for v in c.position],
        "R_wc": [[_f(v) for v in row] for row in c.R_wc],
        "intrinsics": {
            "width": int(c.width),
            "height": int(c.height),
            "fx": _f(c.K[0, 0]),
            "fy": _f(c.K[1, 1]),
            "cx": _f(c.K[0, 2]),
            "cy": _f(c.K[1, 2]),
            "distortion": [_f(v) for v in c.D],
        },
        "reprojection_px": round(c.reprojection_px, 4),
        "calibrated_at": calibrated_at.astimezone(timezone.utc).isoformat(timespec="seconds"),
        "method": c.method,
    }


def check_errors(cameras: list[CameraCalibration], max_error_px: float) -> None:
    bad = [c for c in cameras if not c.reprojection_px <= max_error_px]
    if bad:
        parts = [
            f"camera {c.name}: reprojection error {c.reprojection_px:.3f} px "
            f"(intrinsics {c.intrinsics_rms_px:.3f}, extrinsics {c.extrinsics_rms_px:.3f})"
            for c in bad
        ]
        raise CalibrationError(
            f"{'; '.join(parts)} above the {max_error_px:g} px threshold; nothing written "
            "(retake sharper images with the board flat and fully in view, or raise --max-error-px)"
        )


def write_rig(
    path: str | Path,
    name: str,
    cameras: list[CameraCalibration],
    *,
    max_error_px: float = CALIBRATION_MAX_ERROR_PX,
    calibrated_at: datetime | None = None,
) -> Rig:
    """Write the calibrated rig YAML atomically and return it as read back; refuses errors above
    ``max_error_px``."""
    if not cameras:
        raise CalibrationError("no cameras to write")
    check_errors(cameras, max_error_px)
    at = calibrated_at or datetime.now(timezone.utc)
    doc = {"name": name, "cameras": {c.name: camera_entry(c, at) for c in cameras}}
    path = Path(path)
    header = (
        f"# Calibrated rig {name!r}, written by `viewscale calibrate` (services/calibration).\n"
        "# Poses in the robot base frame; R_wc row by row (columns: optical x right, y down, z forward);\n"
        "# intrinsics at the calibration image size; reprojection_px: RMS error of the worse fit.\n"
    )
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))
    try:
        rig = load_rig(str(tmp))  # what the rest of the system will read, before it replaces anything
    except ConfigError as exc:
        tmp.unlink(missing_ok=True)
        raise CalibrationError(f"the rig file would not read back: {exc}") from exc
    os.replace(tmp, path)
    return rig


def read_calibrated_rig(path: str | Path) -> Rig:
    """A rig file whose every camera is calibrated."""
    rig = load_rig(str(path))
    placed = [n for n, c in rig.cameras.items() if not c.calibrated]
    if placed:
        raise CalibrationError(f"rig {path}: camera {', '.join(placed)} not calibrated (placed by design)")
    return rig
