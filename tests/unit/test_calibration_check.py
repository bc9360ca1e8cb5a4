from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from services.calibration.charuco import CalibrationError
from services.calibration.check import check_rig
from services.calibration.rigfile import CameraCalibration, write_rig
from services.core.config import ConfigError
from services.core.rig import load_rig

NOW = datetime(2025, 3, 1, 12, 0, tzinfo=timezone.utc)


def _cal(name: str, err: float = 0.3) -> CameraCalibration:
    c = load_rig("five15").cameras[name]
    K = c.K(640, 480)
    K[0, 2] += 1.5
    return CameraCalibration(name, c.position, c.R_wc, K, np.array([0.02, -0.01, 0, 0, 0]), 640, 480, 0.2, err, "t")


def _rig(tmp_path, at=NOW - timedelta(days=2), errs=(0.3, 0.4)):
    return write_rig(tmp_path / "lab.yaml", "lab", [_cal("F", errs[0]), _cal("FL", errs[1])], calibrated_at=at)


def test_a_fresh_matching_rig_has_no_problems(tmp_path):
    rig = _rig(tmp_path)
    assert check_rig(rig, {"F": (640, 480), "FL": (640, 480)}, now=NOW) == []
    assert check_rig(rig, None, now=NOW) == []


def test_calibrated_camera_reads_back_with_its_intrinsics(tmp_path):
    rig = _rig(tmp_path)
    cam = rig.cameras["F"]
    assert cam.calibrated and rig.calibrated
    assert cam.calibrated_at == NOW - timedelta(days=2)
    np.testing.assert_allclose(cam.K(640, 480), _cal("F").K, atol=1e-8)
    np.testing.assert_allclose(cam.K(320, 240)[0, 2], (_cal("F").K[0, 2] + 0.5) / 2 - 0.5)
    assert cam.reprojection_px == pytest.approx(0.3)


def test_problems_in_plain_words(tmp_path):
    rig = _rig(tmp_path, at=NOW - timedelta(days=45), errs=(0.3, 0.9))
    problems = check_rig(rig, {"F": (1280, 720), "X": (640, 480)}, max_error_px=0.5, max_age_days=30, now=NOW)
    text = "\n".join(problems)
    assert "rig 'lab' has camera FL but no such camera was opened" in text
    assert "camera X is not in rig 'lab' (F, FL)" in text
    assert "camera F delivers 1280x720 images but was calibrated at 640x480" in text
    assert "camera FL: reprojection error 0.9 px is above 0.5 px" in text
    assert "camera F was calibrated 45 days ago (2025-01-15), more than 30 days" in text
    assert check_rig(load_rig("five15"), None, now=NOW)[0] == (
        "camera F is not calibrated (placed by design): run `viewscale calibrate rig`"
    )


def test_writer_refuses_an_error_above_the_threshold(tmp_path):
    with pytest.raises(CalibrationError, match=r"camera FL: reprojection error 1\.700 px .* above the 1 px threshold"):
        write_rig(tmp_path / "r.yaml", "r", [_cal("F"), _cal("FL", 1.7)], max_error_px=1.0)
    assert not list(tmp_path.iterdir())


def test_rig_yaml_refuses_half_a_calibration(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text("cameras:\n  F: {position: [1, 0, 1], yaw_deg: 5}\n")
    with pytest.raises(ConfigError, match="a calibrated camera needs .* missing R_wc, intrinsics"):
        load_rig(str(p))
