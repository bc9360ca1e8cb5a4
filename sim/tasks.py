"""The three tasks, modelled on robomimic's lift, can (PickPlaceCan) and square (NutAssemblySquare).

Each task adds its objects to the scene, samples their start poses from a seeded generator,
names the bodies whose poses are reported as privileged state, and decides success from
those poses alone (so a recorded ``TaskState`` is enough to relabel success).

Geometry (metres, world frame; the table top is z = 0):
- lift: a 4 cm red cube anywhere in a 16 x 20 cm patch in front of the robot, any yaw; success
  when its centre is more than ``LIFT_HEIGHT`` above its resting height.
- can: a blue can (r 3 cm, 10 cm tall) on the robot's right (y < 0); success when it rests
  inside the green bin on the left (its centre over the bin floor, not held above it).
- square: an orange square nut with a handle, any yaw, on the right; success when it has
  gone down the fixed purple peg on the left.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping

import numpy as np

from services.core.geometry import yaw_quat
from services.core.robot_types import ObjectPose

TASKS = ("lift", "can", "square")

# lift
CUBE_HALF = 0.02
LIFT_HEIGHT = 0.04
# can
CAN_RADIUS = 0.03
CAN_HALF_HEIGHT = 0.05
BIN_CENTER = (0.5, 0.2)
BIN_INNER_HALF = 0.1  # square bin, inner half width
BIN_WALL_HEIGHT = 0.06
BIN_FLOOR_TOP = 0.01
# square
NUT_HOLE_HALF = 0.025  # half width of the square hole
NUT_RIM = 0.015  # rim width around the hole
NUT_HALF_THICK = 0.0125
NUT_HANDLE_LEN = 0.06
NUT_HANDLE_HALF_WIDTH = 0.01
NUT_GRASP_OFFSET = NUT_HOLE_HALF + NUT_RIM + NUT_HANDLE_LEN / 2  # handle centre, nut frame +x
PEG_CENTER = (0.5, 0.15)
PEG_HALF = 0.015
PEG_HEIGHT = 0.1


class Task(ABC):
    name: str
    horizon: int  # ticks at 20 Hz an episode may take (robomimic-like budgets)
    objects: tuple[str, ...]  # bodies reported as privileged state

    def assets_xml(self) -> str:
        return ""

    @abstractmethod
    def worldbody_xml(self) -> str: ...

    @abstractmethod
    def place(self, rng: np.random.Generator | None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Start pose (pos, quat_wxyz) of each free body; nominal poses when ``rng`` is None."""

    @abstractmethod
    def success(self, objects: Mapping[str, ObjectPose]) -> bool: ...


def _uniform(rng: np.random.Generator | None, lo: float, hi: float) -> float:
    return 0.5 * (lo + hi) if rng is None else float(rng.uniform(lo, hi))


class Lift(Task):
    name = "lift"
    horizon = 150
    objects = ("cube",)

    def assets_xml(self) -> str:
        return '    <material name="cube" rgba="0.85 0.12 0.1 1"/>'

    def worldbody_xml(self) -> str:
        h = CUBE_HALF
        return f"""    <body name="cube" pos="0.5 0 {h}">
      <freejoint name="cube"/>
      <geom name="cube" type="box" size="{h} {h} {h}" material="cube" density="800"/>
    </body>"""

    def place(self, rng):
        x, y = _uniform(rng, 0.42, 0.58), _uniform(rng, -0.1, 0.1)
        yaw = _uniform(rng, -math.pi, math.pi)
        return {"cube": (np.array([x, y, CUBE_HALF]), yaw_quat(yaw))}

    def success(self, objects):
        return bool(objects["cube"].pos[2] > CUBE_HALF + LIFT_HEIGHT)


class Can(Task):
    name = "can"
    horizon = 300
    objects = ("can", "bin")

    def assets_xml(self) -> str:
        return """    <material name="can" rgba="0.1 0.3 0.85 1"/>
    <material name="can_top" rgba="0.8 0.8 0.82 1"/>
    <material name="bin" rgba="0.2 0.6 0.25 1"/>"""

    def worldbody_xml(self) -> str:
        bx, by = BIN_CENTER
        a, t, hw = BIN_INNER_HALF, 0.01, BIN_WALL_HEIGHT / 2
        f = BIN_FLOOR_TOP / 2
        return f"""    <body name="can" pos="0.5 -0.15 {CAN_HALF_HEIGHT}">
      <freejoint name="can"/>
      <geom name="can" type="cylinder" size="{CAN_RADIUS} {CAN_HALF_HEIGHT}" material="can" density="400"/>
      <geom class="visual" type="cylinder" size="{CAN_RADIUS + 0.001} 0.004" pos="0 0 {CAN_HALF_HEIGHT - 0.004}"
            material="can_top"/>
    </body>
    <body name="bin" pos="{bx} {by} 0">
      <geom type="box" size="{a + t} {a + t} {f}" pos="0 0 {f}" material="bin"/>
      <geom type="box" size="{a + t} {t / 2} {hw}" pos="0 {a + t / 2} {hw}" material="bin"/>
      <geom type="box" size="{a + t} {t / 2} {hw}" pos="0 {-a - t / 2} {hw}" material="bin"/>
      <geom type="box" size="{t / 2} {a} {hw}" pos="{a + t / 2} 0 {hw}" material="bin"/>
      <geom type="box" size="{t / 2} {a} {hw}" pos="{-a - t / 2} 0 {hw}" material="bin"/>
    </body>"""

    def place(self, rng):
        x, y = _uniform(rng, 0.42, 0.58), _uniform(rng, -0.24, -0.1)
        yaw = _uniform(rng, -math.pi, math.pi)
        return {"can": (np.array([x, y, CAN_HALF_HEIGHT]), yaw_quat(yaw))}

    def success(self, objects):
        can, bin_ = objects["can"].pos, objects["bin"].pos
        inside = bool(np.all(np.abs(can[:2] - bin_[:2]) < BIN_INNER_HALF))
        resting = can[2] < BIN_FLOOR_TOP + CAN_HALF_HEIGHT + 0.02
        return inside and bool(resting)


class Square(Task):
    name = "square"
    horizon = 400
    objects = ("nut", "peg")

    def assets_xml(self) -> str:
        return """    <material name="nut" rgba="0.95 0.55 0.1 1"/>
    <material name="peg" rgba="0.45 0.2 0.65 1"/>"""

    def worldbody_xml(self) -> str:
        a, r, t = NUT_HOLE_HALF, NUT_RIM, NUT_HALF_THICK
        side = a + r / 2  # rim bar centre distance from the hole centre
        hx = a + r + NUT_HANDLE_LEN / 2
        px, py = PEG_CENTER
        return f"""    <body name="nut" pos="0.5 -0.15 {t}">
      <freejoint name="nut"/>
      <geom type="box" size="{a + r} {r / 2} {t}" pos="0 {side} 0" material="nut" density="600"/>
      <geom type="box" size="{a + r} {r / 2} {t}" pos="0 {-side} 0" material="nut" density="600"/>
      <geom type="box" size="{r / 2} {a} {t}" pos="{side} 0 0" material="nut" density="600"/>
      <geom type="box" size="{r / 2} {a} {t}" pos="{-side} 0 0" material="nut" density="600"/>
      <geom name="handle" type="box" size="{NUT_HANDLE_LEN / 2} {NUT_HANDLE_HALF_WIDTH} {t}" pos="{hx} 0 0"
            material="nut" density="600"/>
    </body>
    <body name="peg" pos="{px} {py} 0">
      <geom type="box" size="{PEG_HALF} {PEG_HALF} {PEG_HEIGHT / 2}" pos="0 0 {PEG_HEIGHT / 2}" material="peg"/>
    </body>"""

    def place(self, rng):
        x, y = _uniform(rng, 0.42, 0.56), _uniform(rng, -0.2, -0.08)
        yaw = _uniform(rng, -math.pi, math.pi)
        return {"nut": (np.array([x, y, NUT_HALF_THICK]), yaw_quat(yaw))}

    def success(self, objects):
        nut, peg = objects["nut"].pos, objects["peg"].pos
        around = float(np.linalg.norm(nut[:2] - peg[:2])) < 0.02
        down = nut[2] < 0.04
        return around and bool(down)


def make_task(name: str) -> Task:
    """The task called ``name``; a ValueError names the valid ones otherwise."""
    classes = {"lift": Lift, "can": Can, "square": Square}
    if not isinstance(name, str) or name not in classes:
        raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(TASKS)}")
    return classes[name]()
