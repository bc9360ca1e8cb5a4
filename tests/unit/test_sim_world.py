"""SimWorld: determinism (open-loop replay), IK tracking, the gripper, the arm in the images,
the action limits, and clear errors on bad input."""

import math
import threading

import mujoco
import numpy as np
import pytest

from services.core.geometry import quat_wxyz_to_matrix as quat_to_mat
from services.core.geometry import rot_z
from services.core.rig import load_rig
from services.core.robot_types import EefDelta
from services.robot.safety import Safety, SafetyConfig
from sim.backends import SimRobot
from sim.experts import make_expert
from sim.ik import SiteIk
from sim.scene import ARM_JOINTS, EEF_SITE, R_DOWN
from sim.world import MAX_LEAD, SimWorld

ZERO = np.zeros(3)


@pytest.fixture(scope="module")
def front():
    return load_rig("front")


def _rollout(world: SimWorld, actions, render: bool):
    eef, objs = [], []
    for dp, drot, g in actions:
        world.step(dp, drot, g)
        if render:
            world.render()
        eef.append(np.concatenate([world.robot().eef_pos, world.robot().eef_quat_wxyz]))
        objs.append(np.concatenate([p.pos for p in world.objects().values()]))
    return np.array(eef), np.array(objs)


def test_same_seed_and_actions_replay_the_same_trajectory_bit_for_bit(front):
    # Record an expert episode on one world, replay its actions open loop on another that
    # also renders every tick: rendering must not perturb the physics.
    with SimWorld("lift", front) as a, SimWorld("lift", front) as b:
        a.reset(7)
        expert = make_expert("lift")
        actions, eef_a = [], []
        for _ in range(40):
            action = expert.act(a.robot(), a.objects())
            actions.append(action)
            a.step(*action)
            eef_a.append(np.concatenate([a.robot().eef_pos, a.robot().eef_quat_wxyz]))
        assert a.success()
        b.reset(7)
        eef_b, _ = _rollout(b, actions, render=True)
        assert np.array_equal(np.array(eef_a), eef_b)
        assert b.success()
        # A reset with the same seed on a used world starts the same episode again.
        a.reset(7)
        again, _ = _rollout(a, actions, render=False)
        assert np.array_equal(again, eef_b)


def test_seeds_randomize_object_poses_deterministically(front):
    with SimWorld("square", front) as w:
        poses = {}
        for seed in (0, 1, 0):
            w.reset(seed)
            assert w.seed == seed
            nut = w.objects()["nut"]
            poses.setdefault(seed, []).append(np.concatenate([nut.pos, nut.quat_wxyz]))
        assert np.array_equal(poses[0][0], poses[0][1])
        assert not np.allclose(poses[0][0], poses[1][0])
        assert not w.success()


def test_ik_solves_poses_of_the_arm_itself():
    world = SimWorld("lift", load_rig("front"))
    ik = SiteIk(world.model, EEF_SITE, ARM_JOINTS)
    home = world.robot().joint_pos
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = home + rng.uniform(-0.4, 0.4, size=6)
        pos, R = ik.forward(q)
        res = ik.solve(home, pos, R)
        assert res.pos_err < 1e-4 and res.rot_err < 1e-3, res
        got_pos, got_R = ik.forward(res.q)
        assert np.allclose(got_pos, pos, atol=1e-4)


def test_the_arm_follows_a_commanded_pose(front):
    goal = np.array([0.58, 0.15, 0.08])
    goal_R = rot_z(0.6) @ R_DOWN
    with SimWorld("lift", front) as w:
        w.reset(0)
        for _ in range(60):
            r = w.robot()
            R = quat_to_mat(r.eef_quat_wxyz)
            rvec = _rotvec(goal_R @ R.T)
            w.step(goal - r.eef_pos, rvec, 0.0)
        target_pos, target_R = w.target()
        assert np.allclose(target_pos, goal, atol=1e-3)
        for _ in range(10):  # hold still: the arm settles on the target
            w.step(ZERO, ZERO, 0.0)
        r = w.robot()
        assert np.linalg.norm(r.eef_pos - goal) < 2e-3
        assert np.linalg.norm(_rotvec(goal_R @ quat_to_mat(r.eef_quat_wxyz).T)) < 0.01
        assert np.linalg.norm(r.joint_vel) < 0.05


def test_deltas_integrate_into_the_target_within_the_step_and_box_limits(front):
    # The speed caps and the box are the safety layer's (services.robot.safety): the sim arm
    # runs behind it exactly as hardware does.
    limits = SafetyConfig()
    with SimWorld("lift", front) as w:
        w.reset(0)
        arm = Safety(SimRobot(w), limits, w.control_hz)
        arm.read()
        p0, R0 = w.target()
        arm.apply(EefDelta(np.array([0.0, 0.01, 0.0]), np.array([0.0, 0.0, 0.05]), 0.0))
        p1, R1 = w.target()
        assert np.allclose(p1 - p0, [0.0, 0.01, 0.0], atol=1e-12)
        assert np.allclose(R1, _rotmat([0.0, 0.0, 0.05]) @ R0, atol=1e-12)  # composes on the left
        # A huge step is clipped to the per-tick limit ...
        arm.read()
        arm.apply(EefDelta(np.array([0.0, 0.0, 1.0]), ZERO, 0.0))
        p2, _ = w.target()
        assert np.linalg.norm(p2 - p1) == pytest.approx(limits.max_speed / w.control_hz)
        # ... and the target never leaves the workspace box nor runs far ahead of the arm.
        for _ in range(40):
            arm.read()
            arm.apply(EefDelta(np.array([0.0, 0.0, 1.0]), ZERO, 0.0))
            p, _ = w.target()
            assert p[2] <= limits.workspace_hi[2] + 1e-12
            assert np.linalg.norm(p - w.robot().eef_pos) <= MAX_LEAD + 1e-9
        assert w.robot().eef_pos[2] > limits.workspace_hi[2] - 0.01


def test_pressing_into_the_table_does_not_wind_up_the_target(front):
    with SimWorld("lift", front) as w:
        w.reset(3)
        arm = Safety(SimRobot(w), SafetyConfig(), w.control_hz)  # the box and the lead limit together
        for _ in range(40):
            arm.read()
            arm.apply(EefDelta(np.array([0.0, 0.0, -0.03]), ZERO, 1.0))
        p, _ = w.target()
        r = w.robot()
        assert r.eef_pos[2] > -0.005  # the fingers stop on the table
        assert np.linalg.norm(p - r.eef_pos) <= MAX_LEAD + 1e-9
        for _ in range(3):  # the way back up starts at once
            arm.read()
            arm.apply(EefDelta(np.array([0.0, 0.0, 0.03]), ZERO, 1.0))
        assert w.robot().eef_pos[2] > r.eef_pos[2] + 0.02


def test_gripper_closes_and_opens(front):
    with SimWorld("lift", front) as w:
        w.reset(0)
        assert w.robot().gripper < 0.01
        for _ in range(5):
            w.step(ZERO, ZERO, 1.0)
        assert w.robot().gripper > 0.97
        for _ in range(5):
            w.step(ZERO, ZERO, 0.0)
        assert w.robot().gripper < 0.03
        for _ in range(5):
            w.step(ZERO, ZERO, 0.5)
        assert w.robot().gripper == pytest.approx(0.5, abs=0.03)


def test_the_arm_is_in_every_image():
    rig = load_rig("five15")
    with SimWorld("lift", rig, 84, 84) as w:
        w.reset(0)
        with_arm = w.render()
        robot = {mujoco.mj_name2id(w.model, mujoco.mjtObj.mjOBJ_BODY, b) for b in ("base", "link1", "link2")}
        robot |= {b for b in range(w.model.nbody) if w.model.body_rootid[b] in robot}
        for g in range(w.model.ngeom):
            if w.model.geom_bodyid[g] in robot:
                w.model.geom_rgba[g, 3] = 0.0
                w.model.geom_matid[g] = -1
        without = w.render()
        eef = w.robot().eef_pos
        for name, cam in rig.cameras.items():
            changed = np.any(with_arm[name] != without[name], axis=-1)
            assert changed.mean() > 0.03, f"{name}: the arm covers {changed.mean():.1%} of the image"
            u, v = np.round(cam.project(eef, 84, 84)[0]).astype(int)
            # the EEF point lies between the open fingers, about 10 px either side of it at 84 px
            assert changed[max(v - 3, 0) : v + 4, max(u - 13, 0) : u + 14].any(), (
                f"{name}: no gripper at its projection"
            )


def test_render_gives_one_rgb_image_per_camera():
    rig = load_rig("three15")
    with SimWorld("can", rig, width=96, height=64) as w:
        w.reset(1)
        images = w.render()
        assert list(images) == rig.names
        for img in images.values():
            assert img.shape == (64, 96, 3) and img.dtype == np.uint8
            assert img.std() > 10  # a scene, not a blank buffer


def test_snapshot_shapes_and_ranges(front):
    with SimWorld("can", front) as w:
        w.reset(2)
        r = w.robot()
        assert r.eef_pos.shape == (3,) and r.eef_quat_wxyz.shape == (4,)
        assert np.linalg.norm(r.eef_quat_wxyz) == pytest.approx(1.0)
        assert r.joint_pos.shape == r.joint_vel.shape == (6,)
        assert 0.0 <= r.gripper <= 1.0
        assert np.allclose(quat_to_mat(r.eef_quat_wxyz), R_DOWN, atol=1e-3)  # home points down
        assert set(w.objects()) == {"can", "bin"}
        assert w.task == "can" and w.control_hz == 20.0 and w.seed == 2


def test_bad_input_is_a_clear_value_error(front):
    with pytest.raises(ValueError, match="lift, can, square"):
        SimWorld("stack", front)
    with pytest.raises(ValueError, match="lift, can, square"):
        make_expert("stack")
    with SimWorld("lift", front) as w:
        assert w.seed is None
        for bad in ("3", 1.5, -1, True, None, 2**64):
            with pytest.raises(ValueError, match="seed must be a non-negative int"):
                w.reset(bad)
        w.reset(np.int64(3))
        with pytest.raises(ValueError, match="dp must be 3 finite numbers"):
            w.step([0.0, 0.0], ZERO, 0.0)
        with pytest.raises(ValueError, match="drot must be 3 finite numbers"):
            w.step(ZERO, [math.nan, 0.0, 0.0], 0.0)
        with pytest.raises(ValueError, match="gripper must be one finite number"):
            w.step(ZERO, ZERO, "closed")


def _rotvec(R: np.ndarray) -> np.ndarray:
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, R.reshape(-1))
    v = np.empty(3)
    mujoco.mju_quat2Vel(v, quat, 1.0)
    return v


def _rotmat(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    quat = np.empty(4)
    mujoco.mju_axisAngle2Quat(quat, v / np.linalg.norm(v), float(np.linalg.norm(v)))
    m = np.empty(9)
    mujoco.mju_quat2Mat(m, quat)
    return m.reshape(3, 3)


def test_any_thread_may_render_next(front):
    # A service may render from a worker thread after the main thread did (never at once).
    with SimWorld("lift", front) as w:
        w.reset(0)
        here = w.render()
        there: dict = {}
        worker = threading.Thread(target=lambda: there.update(w.render()))
        worker.start()
        worker.join()
        assert np.array_equal(there["F"], here["F"])
        assert np.array_equal(w.render()["F"], here["F"])


def test_the_sim_configs_rate_limit_is_one_tick_per_physics_step():
    from sim.config import MAX_CONTROL_HZ
    from sim.scene import TIMESTEP

    assert MAX_CONTROL_HZ == pytest.approx(1 / TIMESTEP)
