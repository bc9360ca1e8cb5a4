"""A contact sheet of a built dataset, for a person to check frames and axes at a glance.

Rows are views, column groups are episodes; each group shows the pseudo-demo's first, middle
and last cached frame. On each frame:
- white:   the EEF path from the robot states, as the pseudo-demo stores them;
- cyan:    the path integrated from the pseudo-demo's own actions, in their own frame (camera
           space: summed in the optical frame and projected with K alone, so a wrong R_ext
           shows as a path that leaves the gripper);
- magenta: the next Tp steps of that path from the shown tick, and a dot at the EEF;
- red/green/blue: the base frame's x/y/z axes (10 cm) at the first EEF position.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.core.geometry import rot6d_to_matrix
from services.core.rig import scale_K

WHITE, CYAN, MAGENTA, YELLOW = (255, 255, 255), (0, 255, 255), (255, 0, 255), (255, 255, 0)
AXES = ((255, 60, 60), (60, 255, 60), (80, 120, 255))
LABEL_H = 18


def _project_cam(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) optical-frame points -> (N, 2) pixels; NaN behind the camera."""
    uvw = points_cam @ K.T
    z = uvw[:, 2:3]
    out = uvw[:, :2] / np.where(z > 1e-6, z, np.nan)
    return out


def trajectories(
    state: np.ndarray, action: np.ndarray, ends: np.ndarray, space: str, state_frame: str, calib: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray]:
    """EEF positions in the camera's optical frame: (state path, action-integrated path), (n, 3) each.

    The action path restarts from the state at each segment start and then only sums actions.
    """
    R_ext = np.asarray(calib["R_ext"])
    cam_pos = np.asarray(calib["position"])
    pos, rot = state[:, 0:3].astype(np.float64), rot6d_to_matrix(state[:, 3:9])
    if state_frame == "camera":
        pos_cam = pos
        pos_base, rot_base = pos @ R_ext + cam_pos, R_ext.T @ rot  # R_ext^T p_c + position, R_ext^T R_c
    else:
        pos_base, rot_base = pos, rot
        pos_cam = (pos - cam_pos) @ R_ext.T
    a = action.astype(np.float64)
    path = np.empty_like(pos_cam)
    start = 0
    for end in ends:
        if space == "camera":
            # dp_v is a displacement in the optical frame: sum it there.
            path[start] = pos_cam[start]
            for k in range(start, end - 1):
                path[k + 1] = path[k] + a[k, 0:3]
        else:
            p = pos_base[start].copy()
            path[start] = (p - cam_pos) @ R_ext.T
            for k in range(start, end - 1):
                step = a[k, 0:3] if space == "base" else rot_base[k] @ a[k, 0:3]  # eef: dp = R dp_e
                p = p + step
                path[k + 1] = (p - cam_pos) @ R_ext.T
        start = int(end)
    return pos_cam, path


def _polyline(img: np.ndarray, uv: np.ndarray, color, thickness: int) -> None:
    ok = np.all(np.isfinite(uv), axis=1) & np.all(np.abs(uv) < 1e5, axis=1)
    run: list[np.ndarray] = []
    for good, p in zip(ok, uv):
        if good:
            run.append(p)
        elif run:
            _draw_run(img, run, color, thickness)
            run = []
    if run:
        _draw_run(img, run, color, thickness)


def _draw_run(img, run, color, thickness) -> None:
    if len(run) >= 2:
        pts = np.round(np.asarray(run) * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, color, thickness, cv2.LINE_AA, shift=4)


def draw_tile(
    frame: np.ndarray,
    row: int,
    pos_cam: np.ndarray,
    path: np.ndarray,
    K: np.ndarray,
    Tp: int,
    axes_cam: np.ndarray | None,
    label: str,
    size: tuple[int, int],
) -> np.ndarray:
    img = cv2.resize(np.ascontiguousarray(frame), size, interpolation=cv2.INTER_NEAREST)
    if K is not None:
        _polyline(img, _project_cam(pos_cam, K), WHITE, 1)
        _polyline(img, _project_cam(path, K), CYAN, 1)
        _polyline(img, _project_cam(path[row : row + Tp], K), MAGENTA, 2)
        if axes_cam is not None:
            o = _project_cam(axes_cam[0:1], K)[0]
            for i in range(3):
                e = _project_cam(axes_cam[i + 1 : i + 2], K)[0]
                if np.all(np.isfinite(o)) and np.all(np.isfinite(e)):
                    cv2.arrowedLine(
                        img,
                        tuple(int(x) for x in np.round(o)),
                        tuple(int(x) for x in np.round(e)),
                        AXES[i],
                        1,
                        cv2.LINE_AA,
                        tipLength=0.25,
                    )
        c = _project_cam(pos_cam[row : row + 1], K)[0]
        if np.all(np.isfinite(c)) and np.all(np.abs(c) < 1e5):
            cv2.circle(img, (int(round(c[0])), int(round(c[1]))), 3, YELLOW, -1, cv2.LINE_AA)
    out = np.zeros((size[1] + LABEL_H, size[0], 3), np.uint8)
    out[LABEL_H:] = img
    cv2.putText(out, label, (3, LABEL_H - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.38, WHITE, 1, cv2.LINE_AA)
    return out


def contact_sheet(ds_dir: Path, meta: dict[str, Any], max_episodes: int = 3, tile_height: int = 168) -> np.ndarray:
    """(H, W, 3) uint8 RGB contact sheet of the dataset at ``ds_dir``."""
    W, H = meta["image_size"]["width"], meta["image_size"]["height"]
    scale = max(1, int(round(tile_height / H)))
    tile = (W * scale, H * scale)
    space, state_frame, Tp = meta["action_space"], meta["state_frame"], int(meta["Tp"])
    rows = []
    for v in meta["views"]:
        tiles = []
        for ei, e in enumerate(meta["episodes"][:max_episodes]):
            d = ds_dir / "episodes" / e["dir"]
            ev = e["views"][v]
            calib = ev["calib"] if "calib" in ev else meta["cameras"].get(v)
            frames = np.load(d / f"{v}.frames.npy", mmap_mode="r")
            n = len(frames)
            if n == 0:
                blank = np.zeros((tile[1], tile[0], 3), np.uint8)
                tiles += [
                    draw_tile(
                        blank, 0, np.zeros((0, 3)), np.zeros((0, 3)), None, Tp, None, f"{v} #{ei}: no frames", tile
                    )
                ] * 3
                continue
            state, action = np.load(d / f"{v}.state.npy"), np.load(d / f"{v}.action.npy")
            tick, ends = np.load(d / f"{v}.tick.npy"), np.load(d / f"{v}.ends.npy")
            K = pos_cam = path = axes_cam = None
            if calib is not None:
                K = scale_K(np.asarray(calib["K"]), (W, H), tile)
                pos_cam, path = trajectories(state, action, ends, space, state_frame, calib)
                R_ext, cam_pos = np.asarray(calib["R_ext"]), np.asarray(calib["position"])
                p0 = (pos_cam[0] @ R_ext) + cam_pos  # first EEF position, base frame
                pts = np.vstack([p0, p0 + 0.1 * np.eye(3)])
                axes_cam = (pts - cam_pos) @ R_ext.T
            for r in (0, n // 2, n - 1):
                tiles.append(
                    draw_tile(
                        frames[r],
                        r,
                        pos_cam if pos_cam is not None else np.zeros((0, 3)),
                        path if path is not None else np.zeros((0, 3)),
                        K,
                        Tp,
                        axes_cam,
                        f"{v}  t={int(tick[r])}  #{ei}",
                        tile,
                    )
                )
        rows.append(np.hstack(tiles))
    sheet = np.vstack(rows)
    lines = [
        f"space={space} state={state_frame}  white: state path  cyan: action path  magenta: next Tp  "
        f"axes: base x/y/z (10 cm)"
    ]
    lines += [f"#{ei} {e['id']}" for ei, e in enumerate(meta["episodes"][:max_episodes])]
    legend = np.zeros((LABEL_H * len(lines) + 4, sheet.shape[1], 3), np.uint8)
    for li, text in enumerate(lines):
        cv2.putText(legend, text, (3, LABEL_H * (li + 1) - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.4, WHITE, 1, cv2.LINE_AA)
    return np.vstack([legend, sheet])


def write_contact_sheet(ds_dir: Path, meta: dict[str, Any], out: Path, max_episodes: int = 3) -> Path:
    sheet = contact_sheet(ds_dir, meta, max_episodes)
    tmp = out.with_name(out.stem + ".tmp.png")
    if not cv2.imwrite(str(tmp), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {out}")
    tmp.replace(out)
    return out
