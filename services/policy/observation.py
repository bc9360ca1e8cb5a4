"""What a GetAction request must hold, checked field by field before anything touches torch, and
the per-view model inputs made from it exactly as the dataset build made the training samples.

``PolicySpec`` is the torch-free description of a checkpoint (``policy.json``): horizons, image
size, action space, normaliser, and the calibrated cameras it can be served with. ``parse``
validates a request against it and raises ``InvalidRequest`` naming the field
(``images["FL"]: expected 2 frames, got 1``); ``model_inputs`` decodes and resizes the frames
(JPEG through the same DCT-scaled decode as ``viewscale dataset build``) and puts the robot state
into each view's state frame, normalised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from services.core.action_spaces import check_space, needs_calibration, state_vector
from services.core.geometry import quat_wxyz_to_matrix
from services.core.normalizer import Normalizer
from services.core.tensors import FrameSizeError, decode_resized, from_tensor
from services.pb.policy_pb2 import ActionRequest
from services.policy.aggregation import CompositionError, renormalise
from services.policy.config import MAX_REACH_M

MAX_SESSION_ID = 128
MAX_JPEG_BYTES = 8 << 20  # one frame
MAX_CAMERAS = 32


class InvalidRequest(ValueError):
    """A request field that cannot be used; the message starts with the field."""


@dataclass(frozen=True)
class CameraSpec:
    name: str
    width: int  # frame size the camera records (what requests must send)
    height: int
    K: np.ndarray  # (3, 3) at width x height
    R_ext: np.ndarray  # (3, 3) world-to-camera
    position: np.ndarray  # (3,) base frame

    def to_json(self) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "R_ext": self.R_ext.tolist(),
            "position": self.position.tolist(),
        }


@dataclass(frozen=True)
class PolicySpec:
    """A checkpoint as the server and the client see it (no weights, no torch)."""

    model_id: str
    sha256: str
    action_space: str
    state_frame: str
    To: int
    Tp: int
    n_action_steps: int
    image_size: tuple[int, int]  # (H, W) the model sees
    state_dim: int
    ddim_steps: int
    control_hz: float
    normalizer: Normalizer
    cameras: dict[str, CameraSpec]  # every camera this server can take frames from
    train_views: tuple[str, ...]  # the views the policy was trained on (default composition)
    unconditional: bool = False  # trained with condition dropout
    gammas: dict[str, float] = field(default_factory=dict)  # default composition weights

    @classmethod
    def from_info(cls, info: dict[str, Any], sha256: str, model_id: str) -> PolicySpec:
        model = info["model"]
        cameras: dict[str, CameraSpec] = {}
        for name, c in (info.get("calibration") or {}).items():
            if c is None:
                continue
            cameras[name] = CameraSpec(
                name,
                int(c["source_width"]),
                int(c["source_height"]),
                np.asarray(c["source_K"], dtype=np.float64),
                np.asarray(c["R_ext"], dtype=np.float64),
                np.asarray(c["position"], dtype=np.float64),
            )
        views = tuple(info.get("views") or cameras)
        return cls(
            model_id=model_id,
            sha256=sha256,
            action_space=check_space(info["action_space"]),
            state_frame=info.get("state_frame") or ("camera" if info["action_space"] == "camera" else "base"),
            To=int(model["obs_horizon"]),
            Tp=int(model["pred_horizon"]),
            n_action_steps=int(model["n_action_steps"]),
            image_size=(int(model["image_size"][0]), int(model["image_size"][1])),
            state_dim=int(model["state_dim"]),
            ddim_steps=int(model["noise"]["num_inference_steps"]),
            control_hz=float(info.get("control_hz") or 20.0),
            normalizer=Normalizer.from_dict(info["normalizer"]),
            cameras=cameras,
            train_views=views,
            unconditional=float((info.get("train") or {}).get("cond_dropout") or 0.0) > 0.0,
            gammas={v: 1.0 / len(views) for v in views},
        )

    @property
    def camera_order(self) -> list[str]:
        """Every camera, training views first (in training order): the composition's canonical order."""
        return [*self.train_views, *sorted(c for c in self.cameras if c not in self.train_views)]

    def needs_calibration(self) -> bool:
        return needs_calibration(self.action_space, self.state_frame)


@dataclass
class Parsed:
    """A validated request, still raw: frames undecoded, states as arrays."""

    session_id: str
    seq: int
    views: list[str]  # cameras to compose, in the spec's canonical order
    frames: dict[str, list[bytes | np.ndarray]]  # view -> To frames (JPEG bytes or (H, W, 3) uint8)
    eef_pos: np.ndarray  # (To, 3)
    eef_quat_wxyz: np.ndarray  # (To, 4)
    gripper: np.ndarray  # (To,)
    obs_stamp_ns: int  # the newest state's stamp
    gamma: dict[str, float]  # over `views`, summing to one
    seed: int | None
    unconditional: bool


def _finite(values, n: int, name: str) -> np.ndarray:
    arr = np.asarray(list(values), dtype=np.float64)
    if arr.shape != (n,):
        raise InvalidRequest(f"{name}: expected {n} values, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise InvalidRequest(f"{name}: not finite ({arr.tolist()})")
    return arr


def check_session_id(sid: str) -> None:
    """InvalidRequest unless ``sid`` names a session: 1-MAX_SESSION_ID printable characters (a
    session is kept by its id: an id of megabytes would be kept too)."""
    if not sid or len(sid) > MAX_SESSION_ID or not sid.isprintable():
        raise InvalidRequest(f"session_id: must be 1-{MAX_SESSION_ID} printable characters, got {sid[:40]!r}")


def parse(req: ActionRequest, spec: PolicySpec, default_views: list[str], max_reach_m: float = MAX_REACH_M) -> Parsed:
    """Check every field of ``req``; raise InvalidRequest naming the first bad one."""
    sid = req.session_id
    check_session_id(sid)
    if req.seq == 0:  # (unset: the first request went through and every later one was ABORTED, "not newer")
        raise InvalidRequest(
            "seq: 0 or not set: number each session's requests 1, 2, 3, ... (a newer one cancels an older one)"
        )
    order = spec.camera_order
    wanted = list(req.views) or list(default_views)
    unknown = [v for v in wanted if v not in spec.cameras]
    if unknown:
        raise InvalidRequest(f"views: unknown camera {unknown[0]!r} (this server knows {', '.join(order)})")
    if len(set(wanted)) != len(wanted):
        raise InvalidRequest(f"views: a camera is named twice ({', '.join(wanted)})")
    views = [v for v in order if v in wanted]
    if len(req.cameras) > MAX_CAMERAS:
        raise InvalidRequest(f"cameras: {len(req.cameras)} cameras, at most {MAX_CAMERAS}")
    by_name: dict[str, Any] = {}
    for cam in req.cameras:
        if cam.name in by_name:
            raise InvalidRequest(f"images[{cam.name!r}]: sent twice")
        by_name[cam.name] = cam
    frames: dict[str, list[bytes | np.ndarray]] = {}
    for v in views:
        cam = by_name.get(v)
        if cam is None:
            # (names as sent, shortened and escaped: the request is the caller's)
            sent = ", ".join(n[:40] for n in by_name)[:200].encode("ascii", "backslashreplace").decode() or "none"
            raise InvalidRequest(f"images[{v!r}]: missing (the request composes {', '.join(views)}; it sent {sent})")
        if len(cam.frames) != spec.To:
            raise InvalidRequest(f"images[{v!r}]: expected {spec.To} frames, got {len(cam.frames)}")
        c = spec.cameras[v]
        got: list[bytes | np.ndarray] = []
        for i, f in enumerate(cam.frames):
            where = f"images[{v!r}][{i}]"
            kind = f.WhichOneof("data")
            if kind == "jpeg":
                data = f.jpeg
                if len(data) > MAX_JPEG_BYTES:
                    raise InvalidRequest(f"{where}: {len(data)} bytes of JPEG, at most {MAX_JPEG_BYTES}")
                if len(data) < 4 or data[:2] != b"\xff\xd8" or data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
                    raise InvalidRequest(f"{where}: not a complete JPEG ({len(data)} bytes)")
                got.append(bytes(data))
            elif kind == "rgb":
                t = f.rgb
                if t.dtype not in ("|u1", "uint8"):
                    raise InvalidRequest(f"{where}: raw frames must be uint8, got dtype {t.dtype!r}")
                if list(t.shape) != [c.height, c.width, 3]:
                    raise InvalidRequest(f"{where}: expected shape ({c.height}, {c.width}, 3), got {tuple(t.shape)}")
                try:
                    got.append(from_tensor(t))
                except ValueError as exc:
                    raise InvalidRequest(f"{where}: {exc}") from None
            else:
                raise InvalidRequest(f"{where}: no image data (jpeg or rgb)")
        frames[v] = got
    if len(req.states) != spec.To:
        raise InvalidRequest(f"states: expected {spec.To} states, got {len(req.states)}")
    pos, quat, grip = [], [], []
    for i, s in enumerate(req.states):
        p = _finite(s.eef_pos, 3, f"states[{i}].eef_pos")
        if (reach := float(np.linalg.norm(p))) > max_reach_m:
            raise InvalidRequest(
                f"states[{i}].eef_pos: {reach:.4g} m from the robot's base, farther than {max_reach_m:g} m "
                "(positions are in metres, in the base frame; the server's max_reach_m)"
            )
        pos.append(p)
        q = _finite(s.eef_quat_wxyz, 4, f"states[{i}].eef_quat_wxyz")
        if abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise InvalidRequest(f"states[{i}].eef_quat_wxyz: not a unit quaternion (norm {np.linalg.norm(q):.4f})")
        quat.append(q)
        if not math.isfinite(s.gripper) or not -0.01 <= s.gripper <= 1.01:
            raise InvalidRequest(f"states[{i}].gripper: must be in [0, 1], got {s.gripper}")
        grip.append(min(max(s.gripper, 0.0), 1.0))
    stamps = [s.stamp_ns for s in req.states]
    if any(b < a for a, b in zip(stamps, stamps[1:])):
        raise InvalidRequest("states: stamps must not decrease (oldest first)")
    unknown = [k for k in req.gamma if k not in views]
    if unknown:
        raise InvalidRequest(f"gamma[{unknown[0]!r}]: not one of the composed views ({', '.join(views)})")
    gamma = {v: float(req.gamma.get(v, spec.gammas.get(v, 1.0))) if req.gamma else 1.0 for v in views}
    try:
        gamma = renormalise(gamma, views)  # the composition's rules: finite, non-negative, not all zero
    except CompositionError as exc:
        raise InvalidRequest(f"gamma: {exc}") from None
    if req.unconditional and not spec.unconditional:
        raise InvalidRequest("unconditional: this checkpoint was trained without condition dropout")
    return Parsed(
        sid,
        int(req.seq),
        views,
        frames,
        np.stack(pos),
        np.stack(quat),
        np.asarray(grip),
        int(stamps[-1]),
        gamma,
        int(req.seed) if req.HasField("seed") else None,
        bool(req.unconditional),
    )


def _resize_rgb(rgb: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    h, w = size_hw
    if rgb.shape[:2] == (h, w):
        return rgb
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)


def model_inputs(parsed: Parsed, spec: PolicySpec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per view: frames (To, H, W, 3) uint8 at the model's size and state (To, D) float32 normalised."""
    H, W = spec.image_size
    R = quat_wxyz_to_matrix(parsed.eef_quat_wxyz)  # (To, 3, 3)
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for v in parsed.views:
        c = spec.cameras[v]
        imgs = []
        for i, f in enumerate(parsed.frames[v]):
            if isinstance(f, np.ndarray):
                imgs.append(_resize_rgb(f, (H, W)))
                continue
            try:
                img = decode_resized(f, (W, H), (c.width, c.height))
            except FrameSizeError as exc:
                raise InvalidRequest(
                    f"images[{v!r}][{i}]: the frame is {exc}, the camera's calibration says {c.width}x{c.height}"
                ) from None
            if img is None:
                raise InvalidRequest(f"images[{v!r}][{i}]: undecodable JPEG")
            imgs.append(img)
        state = np.zeros((spec.To, 0), np.float32)
        if spec.state_dim:
            s = state_vector(
                parsed.eef_pos, R, parsed.gripper, spec.state_frame, R_ext=c.R_ext, cam_position=c.position
            )
            state = spec.normalizer.normalize_state(s).astype(np.float32)
        out[v] = (np.stack(imgs), state)
    return out
