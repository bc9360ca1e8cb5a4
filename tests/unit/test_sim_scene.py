"""The scene's cameras are the rig's cameras: a known 3D point lands where Camera.project says
(measured: within 0.1 px at 320 x 240, 0.21 px at 84 x 84; asserted: 0.5 px)."""

import mujoco
import numpy as np
import pytest

from services.core.rig import load_rig
from sim.scene import MultiCameraRenderer, build_model, scene_xml
from sim.tasks import make_task

MARKER = (
    '    <body name="marker" pos="0 0 0">\n'
    '      <geom type="sphere" size="0.015" material="marker" contype="0" conaffinity="0"/>\n'
    "    </body>\n"
)
MARKER_MATERIAL = '    <material name="marker" rgba="1 0 1 1" emission="1" specular="0" shininess="0"/>\n'
# centres clear of the table (a half-hidden blob is off-centre) and in every view of the framing
POINTS = np.array([[0.5, 0.0, 0.1], [0.56, -0.1, 0.04], [0.42, 0.1, 0.2], [0.45, 0.08, 0.035]])


def _marker_model(rig, width, height):
    xml = scene_xml(make_task("lift"), rig, width, height)
    xml = xml.replace("  </worldbody>", MARKER + "  </worldbody>")
    # Emissive and matte: flat magenta whatever the lights, so shading cannot shift the centroid.
    xml = xml.replace("  </asset>", MARKER_MATERIAL + "  </asset>")
    model = mujoco.MjModel.from_xml_string(xml)
    gid = model.body_geomadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "marker")]
    return model, gid


def _centroid(img: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted centroid (u, v) of magenta pixels: weight = how magenta, so edge pixels count
    by their coverage; and the total weight (in pixels)."""
    f = img.astype(np.float64) / 255.0
    w = np.clip(np.minimum(f[..., 0], f[..., 2]) - f[..., 1], 0.0, 1.0)
    w[w < 0.15] = 0.0
    total = w.sum()
    vs, us = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    return np.array([(w * us).sum() / total, (w * vs).sum() / total]), float(total)


@pytest.mark.parametrize(
    "rig_name,width,height", [("five15", 320, 240), ("front_side_top", 200, 200), ("three30", 84, 84)]
)
def test_a_known_point_renders_where_the_calibration_projects_it(rig_name, width, height):
    rig = load_rig(rig_name)
    model, gid = _marker_model(rig, width, height)
    if width <= 84:
        model.geom_size[gid, 0] = 0.025  # a few pixels across even at 84 x 84
    data = mujoco.MjData(model)
    renderer = MultiCameraRenderer(model, rig.names, width, height)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "marker")
    worst = 0.0
    try:
        for p in POINTS:
            model.body_pos[body] = p
            mujoco.mj_forward(model, data)
            images = renderer.render(data)
            for name, cam in rig.cameras.items():
                uv, area = _centroid(images[name])
                assert area > 3.0, f"marker at {p} not visible in {name}"
                err = float(np.linalg.norm(uv - cam.project(p, width, height)[0]))
                worst = max(worst, err)
                assert err < 0.5, f"{name}: marker at {p} rendered {err:.2f} px from its projection"
    finally:
        renderer.close()
    print(f"{rig_name} {width}x{height}: worst reprojection error {worst:.3f} px")


def test_one_scene_update_for_all_cameras_draws_what_a_fresh_update_per_camera_draws():
    rig = load_rig("five15")
    model = build_model(make_task("can"), rig, 96, 72)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ours = MultiCameraRenderer(model, rig.names, 96, 72)
    reference = mujoco.Renderer(model, 72, 96)
    reference.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    reference.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    try:
        images = ours.render(data)
        for name in rig.names:
            reference.update_scene(data, camera=name)
            expected = reference.render()
            assert images[name].shape == (72, 96, 3) and images[name].dtype == np.uint8
            assert np.array_equal(images[name], expected), name
    finally:
        ours.close()
        reference.close()


def test_scene_has_one_camera_per_rig_camera_with_its_pose_and_field_of_view():
    rig = load_rig("five15")
    model = build_model(make_task("square"), rig)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    for name, cam in rig.cameras.items():
        cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        assert cid >= 0
        assert np.allclose(data.cam_xpos[cid], cam.position, atol=1e-9)
        # MuJoCo camera axes are OpenCV's with y and z flipped.
        R = data.cam_xmat[cid].reshape(3, 3)
        assert np.allclose(R @ np.diag([1, -1, -1]), cam.R_wc, atol=1e-9)
        assert model.cam_fovy[cid] == pytest.approx(cam.fovy_deg)
