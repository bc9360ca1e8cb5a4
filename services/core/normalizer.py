"""Normalisation of actions, robot state and images, saved with the dataset and the checkpoint.

Actions (..., 7) = (dp, drot, gripper):
- dp and drot are each divided by one isotropic scale and get no offset, so any rotation M of a
  block commutes with normalisation: norm(M x) = M norm(x). The multi-view composition at
  inference applies per-view camera rotations to normalised actions and relies on this.
- The scale of a block is the largest Euclidean norm of that block over every training
  pseudo-demo (the dataset build fits it on its training episodes only).
  A component never exceeds the vector's norm, so no normalised component exceeds 1 -- in any
  view's frame, held-out views included, since the norm does not depend on the frame.
- The gripper closure is mapped affinely from its range ([0, 1], widened if the data leave it)
  to [-1, 1].
Robot state (..., D) is min-max normalised per component to [-1, 1]; a component that never
varies maps to 0. Images (uint8, 0..255) go to [-1, 1].

Every map is ``x_n = (x - offset) / scale`` with per-component vectors, so a torch module can
hold ``action_offset``/``action_scale`` as buffers. numpy only; serialised as a JSON-able dict.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

VERSION = 1
_EPS = 1e-8


@dataclass(frozen=True)
class Normalizer:
    pos_scale: float  # dp block: largest |dp| over all pseudo-demos (m)
    rot_scale: float  # drot block: largest |drot| over all pseudo-demos (rad)
    state_min: np.ndarray  # (D,) per-component minimum of the robot state
    state_max: np.ndarray  # (D,) per-component maximum
    gripper_min: float = 0.0  # gripper closure range mapped to [-1, 1]
    gripper_max: float = 1.0
    image_min: float = 0.0  # raw pixel range mapped to [-1, 1]
    image_max: float = 255.0
    state_names: tuple[str, ...] = field(default=())  # labels of the D state components

    # -- fitting ---------------------------------------------------------------------------

    @classmethod
    def fit(
        cls, actions: Iterable[np.ndarray], states: Iterable[np.ndarray], state_names: Iterable[str] = ()
    ) -> Normalizer:
        """Fit over every pseudo-demo: ``actions`` and ``states`` are iterables of (N_i, 7) and (N_i, D)."""
        acc = NormalizerStats()
        for a in actions:
            acc.add_actions(a)
        for s in states:
            acc.add_states(s)
        return acc.normalizer(state_names)

    # -- vectors ---------------------------------------------------------------------------

    @property
    def action_scale(self) -> np.ndarray:
        g = (self.gripper_max - self.gripper_min) / 2.0
        return np.array([self.pos_scale] * 3 + [self.rot_scale] * 3 + [g], dtype=np.float64)

    @property
    def action_offset(self) -> np.ndarray:
        g = (self.gripper_max + self.gripper_min) / 2.0
        return np.array([0.0] * 6 + [g], dtype=np.float64)

    @property
    def state_scale(self) -> np.ndarray:
        half = (np.asarray(self.state_max) - np.asarray(self.state_min)) / 2.0
        return np.where(half > _EPS, half, 1.0)

    @property
    def state_offset(self) -> np.ndarray:
        return (np.asarray(self.state_max) + np.asarray(self.state_min)) / 2.0

    # -- maps ------------------------------------------------------------------------------

    def normalize_action(self, a: np.ndarray) -> np.ndarray:
        return ((np.asarray(a) - self.action_offset) / self.action_scale).astype(np.result_type(a, np.float32))

    def unnormalize_action(self, a_n: np.ndarray) -> np.ndarray:
        return (np.asarray(a_n) * self.action_scale + self.action_offset).astype(np.result_type(a_n, np.float32))

    def normalize_state(self, s: np.ndarray) -> np.ndarray:
        return ((np.asarray(s) - self.state_offset) / self.state_scale).astype(np.result_type(s, np.float32))

    def unnormalize_state(self, s_n: np.ndarray) -> np.ndarray:
        return (np.asarray(s_n) * self.state_scale + self.state_offset).astype(np.result_type(s_n, np.float32))

    def normalize_image(self, img: np.ndarray) -> np.ndarray:
        """uint8 pixels -> float32 in [-1, 1] (layout unchanged)."""
        half = (self.image_max - self.image_min) / 2.0
        return ((np.asarray(img, dtype=np.float32) - (self.image_min + half)) / half).astype(np.float32)

    # -- serialisation ---------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return {
            "version": VERSION,
            "action": {
                "layout": ["dp_x", "dp_y", "dp_z", "drot_x", "drot_y", "drot_z", "gripper"],
                "pos_scale": float(self.pos_scale),
                "rot_scale": float(self.rot_scale),
                "gripper_min": float(self.gripper_min),
                "gripper_max": float(self.gripper_max),
            },
            "state": {
                "names": list(self.state_names),
                "min": [float(v) for v in np.asarray(self.state_min)],
                "max": [float(v) for v in np.asarray(self.state_max)],
            },
            "image": {"min": float(self.image_min), "max": float(self.image_max), "out": [-1.0, 1.0]},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Normalizer:
        if d.get("version") != VERSION:
            raise ValueError(f"normalizer version {d.get('version')!r} is not {VERSION}")
        a, s, im = d["action"], d["state"], d["image"]
        return cls(
            pos_scale=float(a["pos_scale"]),
            rot_scale=float(a["rot_scale"]),
            gripper_min=float(a["gripper_min"]),
            gripper_max=float(a["gripper_max"]),
            state_min=np.asarray(s["min"], dtype=np.float64),
            state_max=np.asarray(s["max"], dtype=np.float64),
            state_names=tuple(s.get("names", ())),
            image_min=float(im["min"]),
            image_max=float(im["max"]),
        )

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Normalizer:
        return cls.from_dict(json.loads(Path(path).read_text()))


class NormalizerStats:
    """Running statistics, so a dataset build can fit the normalizer one pseudo-demo at a time."""

    def __init__(self) -> None:
        self.pos_max = 0.0
        self.rot_max = 0.0
        self.grip_min = 0.0
        self.grip_max = 1.0
        self.state_min: np.ndarray | None = None
        self.state_max: np.ndarray | None = None

    def add_actions(self, a: np.ndarray) -> None:
        a = np.asarray(a, dtype=np.float64).reshape(-1, 7)
        if a.size == 0:
            return
        if not np.all(np.isfinite(a)):
            raise ValueError("actions contain NaN or inf")
        self.pos_max = max(self.pos_max, float(np.linalg.norm(a[:, 0:3], axis=1).max()))
        self.rot_max = max(self.rot_max, float(np.linalg.norm(a[:, 3:6], axis=1).max()))
        self.grip_min = min(self.grip_min, float(a[:, 6].min()))
        self.grip_max = max(self.grip_max, float(a[:, 6].max()))

    def add_states(self, s: np.ndarray) -> None:
        s = np.asarray(s, dtype=np.float64)
        if s.size == 0:
            return
        s = s.reshape(-1, s.shape[-1])
        if not np.all(np.isfinite(s)):
            raise ValueError("states contain NaN or inf")
        lo, hi = s.min(axis=0), s.max(axis=0)
        if self.state_min is None:
            self.state_min, self.state_max = lo, hi
        else:
            self.state_min = np.minimum(self.state_min, lo)
            self.state_max = np.maximum(self.state_max, hi)

    def normalizer(self, state_names: Iterable[str] = ()) -> Normalizer:
        if self.state_min is None or self.state_max is None:
            raise ValueError("no robot states to fit the normalizer on")
        # A block that never moves keeps scale 1 rather than dividing by zero.
        return Normalizer(
            pos_scale=self.pos_max if self.pos_max > _EPS else 1.0,
            rot_scale=self.rot_max if self.rot_max > _EPS else 1.0,
            state_min=self.state_min,
            state_max=self.state_max,
            gripper_min=self.grip_min,
            gripper_max=self.grip_max,
            state_names=tuple(state_names),
        )
