"""docs/robot-client.md's loop, run as the page has it: its code drives the MuJoCo arm through a
real policy server on loopback (a tiny real checkpoint), with the arm as the page's ``robot``."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from policy_processes import start_server, stop

from services.core.rig import load_rig
from services.policy.client import PolicyClient

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "robot-client.md"


def page_code() -> str:
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(), re.S)
    assert len(blocks) == 1, f"{PAGE.name} should hold one python block, has {len(blocks)}"
    return blocks[0]


class SimArm:
    """The page's ``robot``: the sim's arm and the rig's cameras, at the size the policy was recorded at."""

    def __init__(self, world):
        self.world = world
        self.commands: list[tuple[np.ndarray, np.ndarray, float]] = []

    def images(self) -> dict[str, np.ndarray]:
        return self.world.render()

    def pose(self):
        s = self.world.robot()
        return s.eef_pos, s.eef_quat_wxyz, s.gripper

    def apply(self, dp, drot, gripper) -> None:
        self.commands.append((np.array(dp), np.array(drot), float(gripper)))
        self.world.step(dp, drot, gripper)


def test_the_pages_loop_drives_the_arm_with_the_policy(tiny_checkpoint):
    from sim.world import SimWorld

    page = {}
    exec(compile(page_code(), str(PAGE), "exec"), page)  # the page's imports and run_episode, as written
    proc, address = start_server(tiny_checkpoint, "--in-process")
    try:
        with PolicyClient(address) as c:
            info = c.info
        cams = {cam.name: (cam.width, cam.height) for cam in info.cameras}
        [(width, height)] = set(cams.values())
        world = SimWorld("lift", load_rig("three15"), width=width, height=height, control_hz=info.control_hz)
        try:
            world.reset(7)
            start = world.robot().eef_pos.copy()
            arm = SimArm(world)
            assert set(arm.images()) == set(cams)  # the rig the checkpoint was recorded with
            seconds = 3.0
            stats = page["run_episode"](arm, address, views=["F", "FL"], seconds=seconds)
            moved = np.linalg.norm(world.robot().eef_pos - start)
        finally:
            world.close()
    finally:
        stop(proc)

    ticks = int(seconds * info.control_hz)
    assert len(arm.commands) == ticks
    assert stats.failed == 0 and stats.requests >= 2, stats
    assert stats.underruns < ticks  # some ticks ran the policy's actions, not a hold
    executed = [dp for dp, drot, _ in arm.commands if np.any(dp) or np.any(drot)]
    assert len(executed) == ticks - stats.underruns
    assert moved > 1e-4, f"the arm did not move ({moved:.2e} m)"
    assert stats.requests - 1 <= len(stats.latency_s) <= stats.requests  # the last may still be in flight
