"""Is a rig's calibration fit for use? The checks ``viewscale check`` runs against the cameras."""

from __future__ import annotations

from datetime import datetime, timezone

from services.core.rig import CALIBRATION_MAX_AGE_DAYS, CALIBRATION_MAX_ERROR_PX, Rig


def check_rig(
    rig: Rig,
    sizes: dict[str, tuple[int, int]] | None = None,
    max_error_px: float = CALIBRATION_MAX_ERROR_PX,
    max_age_days: float = CALIBRATION_MAX_AGE_DAYS,
    now: datetime | None = None,
    require_calibrated: bool = True,
) -> list[str]:
    """Problems in plain words; empty when the rig is fit for use.

    ``sizes``: camera name -> (width, height) the cameras deliver; None skips the camera checks.
    A camera must deliver exactly the size it was calibrated at: another capture mode of the same
    sensor is often a crop or a binning whose K differs, which no rescaling of K can tell.
    ``require_calibrated``: False in sim, where a camera placed by design is exact (the renderer
    uses its numbers), so only names are checked for it.
    """
    now = now or datetime.now(timezone.utc)
    problems: list[str] = []
    if sizes is not None:
        missing = [n for n in rig.names if n not in sizes]
        extra = [n for n in sizes if n not in rig.cameras]
        if missing:
            problems.append(f"rig {rig.name!r} has camera {', '.join(missing)} but no such camera was opened")
        if extra:
            problems.append(f"camera {', '.join(extra)} is not in rig {rig.name!r} ({', '.join(rig.names)})")
    for name, cam in rig.cameras.items():
        if not cam.calibrated or cam.intrinsics is None:
            if not require_calibrated:
                continue
            problems.append(f"camera {name} is not calibrated (placed by design): run `viewscale calibrate rig`")
            continue
        intr = cam.intrinsics
        if sizes is not None and name in sizes:
            w, h = sizes[name]
            if (w, h) != (intr.width, intr.height):
                problems.append(
                    f"camera {name} delivers {w}x{h} images but was calibrated at {intr.width}x{intr.height}: "
                    "capture at the calibrated size or recalibrate"
                )
        err = cam.reprojection_px
        if err is None or not err <= max_error_px:
            problems.append(f"camera {name}: reprojection error {err} px is above {max_error_px:g} px")
        assert cam.calibrated_at is not None
        age = (now - cam.calibrated_at).total_seconds() / 86400
        if age > max_age_days:
            problems.append(
                f"camera {name} was calibrated {age:.0f} days ago ({cam.calibrated_at:%Y-%m-%d}), "
                f"more than {max_age_days:g} days"
            )
        elif age < -1 / 24:
            problems.append(f"camera {name}: calibration date {cam.calibrated_at.isoformat()} is in the future")
    return problems
