"""Is an episode's camera calibration fit for camera-space data? Refuses missing or stale ones.

An episode records each camera's calibration as it was published (``camera/<name>/calibration``
and ``/pose``), but not when that calibration was made. The date is in the rig file the cameras
published from (``calibrated_at``, written by ``viewscale calibrate``), so the build checks each
episode against a rig file: ``--rig FILE`` if given, otherwise the rig the episode names.

For each view of a camera-space build (or a camera-frame state):
- missing: no calibration or pose recorded (refused where the pseudo-demo is made), or the rig
  cannot be found here to check it against;
- a camera the rig places by design (no ``calibrated_at``: the presets, every sim rig) is exact
  by construction and accepted as it was recorded;
- a calibrated camera is stale when the recorded calibration differs from the rig file's (the
  camera was recalibrated since, usually because it moved: pass the older rig file with
  ``--rig`` if that calibration still held when the episode was recorded), when it was
  calibrated more than ``max_age_days`` before the episode started, or after it.
"""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

import numpy as np

from services.core.config import ConfigError
from services.core.rig import Rig, load_rig
from services.dataset.episodes import CameraCalib

POSITION_TOL_M = 1e-4  # recorded vs rig file: the rig file's rounding is far below these
ROTATION_TOL = 1e-4
K_TOL_PX = 1e-3


def _rig(ref: str) -> Rig | str:
    # Read every time: a rig file is small, and it may be rewritten between two builds of one process.
    try:
        return load_rig(ref)
    except ConfigError as exc:
        return str(exc)


def _differs(calib: CameraCalib, cam) -> str | None:
    dp = float(np.abs(calib.camera.position - cam.position).max())
    dr = float(np.abs(calib.camera.R_wc - cam.R_wc).max())
    dk = float(np.abs(calib.K - cam.K(calib.width, calib.height)).max())
    if dp > POSITION_TOL_M:
        return f"position differs by {dp * 1000:.1f} mm"
    if dr > ROTATION_TOL:
        return "orientation differs"
    if dk > K_TOL_PX:
        return f"intrinsics differ by {dk:.2f} px"
    return None


def calibration_problems(
    source: str,
    calib: dict[str, CameraCalib | None],
    meta: dict[str, Any],
    rig: str | None,
    max_age_days: float,
) -> list[str]:
    """Why the recorded calibration of each view cannot be used; empty when all can.

    ``calib``: view -> what the episode recorded (None: nothing, refused elsewhere); ``meta``:
    the episode's metadata (rig, start_ns); ``rig``: the rig file to check against (None: the
    episode's own).
    """
    problems: list[str] = []
    ref = rig or str(meta.get("rig") or "")
    for view, c in calib.items():
        if c is None:
            continue
        r = _rig(ref) if ref else "the episode names no rig"
        if isinstance(r, str):
            problems.append(
                f"{source}: cannot check the calibration of camera {view!r} ({r}); "
                "pass the calibrated rig file the cameras used with --rig FILE"
            )
            continue
        cam = r.cameras.get(view)
        if cam is None:
            problems.append(f"{source}: rig {ref} has no camera {view!r} ({', '.join(r.names)})")
            continue
        if not cam.calibrated:
            continue  # placed by design: exact in sim
        assert cam.calibrated_at is not None
        when = f"calibrated {cam.calibrated_at:%Y-%m-%d %H:%M} UTC"
        diff = _differs(c, cam)
        if diff:
            problems.append(
                f"{source}: camera {view!r} calibration is stale: the recorded one differs from {ref} ({when}): "
                f"{diff}; it was recalibrated since this episode. If the old calibration held when it was "
                "recorded, build with --rig <that calibration's rig file>"
            )
            continue
        start_ns = int(meta.get("start_ns") or 0)
        if start_ns <= 0:
            problems.append(f"{source}: no recording time, so camera {view!r}'s calibration age is unknown")
            continue
        recorded = datetime.fromtimestamp(start_ns / 1e9, timezone.utc)
        age_days = (recorded - cam.calibrated_at).total_seconds() / 86400
        if age_days > max_age_days:
            problems.append(
                f"{source}: camera {view!r} calibration is stale: {when}, {age_days:.0f} days before the "
                f"episode was recorded ({recorded:%Y-%m-%d}); the limit is {max_age_days:g} days "
                "(--max-calibration-age-days). Recalibrate, or raise the limit if the camera did not move"
            )
        elif age_days < -1 / 24:
            problems.append(
                f"{source}: camera {view!r} was {when}, after the episode was recorded ({recorded:%Y-%m-%d %H:%M})"
            )
    return problems


def problems_of_info(info: dict[str, Any], views: tuple[str, ...], rig: str | None, max_age_days: float) -> list[str]:
    """The same checks on a built episode's ``episode.json`` (for episodes reused from an earlier build)."""
    calib = {}
    for v in views:
        c = info["views"][v].get("calib")
        calib[v] = CameraCalib.from_json(v, c) if c is not None else None
    name = info.get("source", {}).get("path", info.get("episode_id", "?")).rsplit("/", 1)[-1]
    return calibration_problems(name, calib, info.get("meta", {}), rig, max_age_days)
