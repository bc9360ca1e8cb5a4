import math

import numpy as np
import pytest

from services.core.config import ConfigError
from services.core.rig import Camera, available_rigs, load_rig


def test_presets_exist():
    assert {"front", "three15", "five15", "three30", "front_side_top"} <= set(available_rigs())
    assert load_rig("five15").names == ["F", "FL", "FR", "FU", "FD"]


@pytest.mark.parametrize("rig", ["front", "three15", "five15", "three30", "front_side_top"])
def test_every_camera_looks_at_the_centre_with_a_proper_rotation(rig):
    r = load_rig(rig)
    centre = np.array(r.spec.center)
    for cam in r.cameras.values():
        assert np.allclose(cam.R_wc.T @ cam.R_wc, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(cam.R_wc), 1.0)
        uv = cam.project(centre, 84, 84)[0]
        assert np.allclose(uv, [41.5, 41.5], atol=1e-9)  # principal point, pixel-centre convention


def test_rotations_are_fifteen_degrees_around_the_centre():
    r = load_rig("five15")
    centre = np.array(r.spec.center)
    f = r.cameras["F"].position - centre
    for name in ("FL", "FR", "FU", "FD"):
        v = r.cameras[name].position - centre
        angle = math.degrees(math.acos(f @ v / np.linalg.norm(f) / np.linalg.norm(v)))
        assert angle == pytest.approx(15.0, abs=1e-9)
        assert np.linalg.norm(v) == pytest.approx(np.linalg.norm(f))
    assert r.cameras["FU"].position[2] > r.cameras["F"].position[2] > r.cameras["FD"].position[2]
    # FL moves to the camera's own left: against the image-right axis of F.
    right = r.cameras["F"].R_wc[:, 0]
    assert (r.cameras["FL"].position - r.cameras["F"].position) @ right < 0
    assert (r.cameras["FR"].position - r.cameras["F"].position) @ right > 0


def test_projection_matches_pinhole_math():
    cam = load_rig("front").cameras["F"]
    p = np.array([0.6, 0.1, 0.05])
    pc = cam.R_ext @ (p - cam.position)
    K = cam.K(224, 160)
    u = K[0, 0] * pc[0] / pc[2] + K[0, 2]
    v = K[1, 1] * pc[1] / pc[2] + K[1, 2]
    assert np.allclose(cam.project(p, 224, 160)[0], [u, v])


def test_messages_round_trip_to_the_same_camera():
    cam = load_rig("five15").cameras["FU"]
    back, K = Camera.from_msgs(cam.calibration_msg(96, 64, 123), cam.pose_msg(123))
    assert back.name == "FU"
    assert np.allclose(back.R_wc, cam.R_wc, atol=1e-9)
    assert np.allclose(back.position, cam.position)
    assert np.allclose(K, cam.K(96, 64))
    assert back.fovy_deg == pytest.approx(cam.fovy_deg)


def test_mujoco_axes_flip_y_and_z():
    cam = load_rig("front").cameras["F"]
    x, y = np.array(cam.mujoco_xyaxes[:3]), np.array(cam.mujoco_xyaxes[3:])
    assert np.allclose(x, cam.R_wc[:, 0]) and np.allclose(y, -cam.R_wc[:, 1])
    assert np.allclose(np.cross(x, y), -cam.R_wc[:, 2])  # MuJoCo looks down its -z


def test_unknown_rig_names_the_presets(tmp_path):
    with pytest.raises(ConfigError, match="five15"):
        load_rig("six15")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\ncameras: {}\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_rig(str(bad))
