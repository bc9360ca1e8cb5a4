"""``viewscale check --config deploy/real.yaml``: is this rig ready to record?

Before a collection session a lab wants one answer per part, in plain words, from the same
config the session will run with: every camera opens and delivers frames at the rate asked, the
calibration file describes these cameras (names, image sizes, reprojection error, age), the
arm answers with a state inside the workspace, and, where the teleop drives with a policy, its
server answers and the policy fits the session (views, frame size, control rate, camera poses).
Each part is checked through the same driver registry the services use, so what passes here is
what the services will open. Nothing is
published and no episode is started; the robot is connected to and read, never moved (a driver
may still set up its control channel: the UR driver uploads its control script on connect).

The command prints one line per finding (``ok`` / ``FAIL``) and exits non-zero when any part
fails, so it can gate a script (``viewscale check ... && viewscale collect ...``).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.calibration.check import check_rig
from services.camera.config import CAMERA_DRIVERS, CameraConfig, stand_in_rig
from services.core.action_spaces import needs_calibration
from services.core.clock import Rate, now_ns
from services.core.config import ConfigError, load_config
from services.core.rig import Rig, load_rig, served_camera_gap
from services.robot.config import ROBOT_DRIVERS, RobotConfig
from services.teleop.config import TeleopConfig

PARTS = ("cameras", "calibration", "robot", "policy")


@dataclass(frozen=True)
class Finding:
    part: str  # what was checked: "camera F", "calibration", "robot"
    ok: bool
    text: str  # what was seen, in plain words

    def line(self) -> str:
        return f"{'ok  ' if self.ok else 'FAIL'}  {self.part:<14} {self.text}"


@dataclass(frozen=True)
class CameraReport:
    name: str
    frames: int  # distinct frames delivered during the check
    fps: float  # achieved frames per second
    size: tuple[int, int] | None  # (width, height) of the frames the driver delivers
    native: tuple[int, int] | None  # the device's own resolution, where the driver reports it
    latency_ms: float | None  # capture stamp to delivery, median
    exposure: float | None  # as the device reports it (driver units)


def _describe_error(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def measure_cameras(cfg: CameraConfig, seconds: float, rig: Rig | None = None) -> list[CameraReport]:
    """Open the camera group the camera service would, grab at its rate for ``seconds`` (``rig``:
    instead of ``cfg.rig``)."""
    rig = rig if rig is not None else load_rig(cfg.rig)
    driver = CAMERA_DRIVERS.build(cfg.driver, rig=rig, width=cfg.width, height=cfg.height)
    try:
        names = list(driver.cameras)
        driver.grab(now_ns())  # the first grab may set things up (a render context, a stream's first key frame)
        last: dict[str, int] = {}
        first: dict[str, int] = {}
        frames = dict.fromkeys(names, 0)
        sizes: dict[str, tuple[int, int]] = {}
        latencies: dict[str, list[float]] = {n: [] for n in names}
        rate = Rate(cfg.fps)
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            grabbed = driver.grab(now_ns())
            received = now_ns()
            for name, frame in grabbed.items():
                if last.get(name) == frame.stamp_ns:
                    continue  # the same frame again: the camera delivered nothing new
                last[name] = frame.stamp_ns
                first.setdefault(name, frame.stamp_ns)
                frames[name] += 1
                sizes[name] = (int(frame.rgb.shape[1]), int(frame.rgb.shape[0]))
                latencies[name].append((received - frame.stamp_ns) / 1e6)
            rate.sleep()
        stats = driver.stats()
        reports = []
        for name in names:
            st = stats.get(name)
            lat = latencies[name]
            # Rate from the frames' own capture stamps: the first to the last distinct frame.
            span_s = (last.get(name, 0) - first.get(name, 0)) / 1e9
            fps = (frames[name] - 1) / span_s if frames[name] > 1 and span_s > 0 else 0.0
            reports.append(
                CameraReport(
                    name=name,
                    frames=frames[name],
                    fps=fps,
                    size=sizes.get(name),
                    native=getattr(st, "resolution", None),
                    latency_ms=float(np.median(lat)) if lat else None,
                    exposure=getattr(st, "exposure", None),
                )
            )
        return reports
    finally:
        driver.close()


def camera_findings(cfg: CameraConfig, reports: Iterable[CameraReport], min_fps_fraction: float) -> list[Finding]:
    out = []
    for r in reports:
        part = f"camera {r.name}"
        if r.frames == 0:
            out.append(Finding(part, False, "delivered no frame: is it plugged in, is the source right?"))
            continue
        details = [f"{r.size[0]}x{r.size[1]}" if r.size else "size unknown"]
        if r.native and r.native != r.size:
            details.append(f"(device {r.native[0]}x{r.native[1]}, resized)")
        details.append(f"{r.fps:.1f} fps of {cfg.fps:g} asked")
        if r.latency_ms is not None:
            details.append(f"latency {r.latency_ms:.0f} ms")
        if r.exposure is not None:
            details.append(f"exposure {r.exposure:g}")
        ok = r.fps >= min_fps_fraction * cfg.fps
        text = ", ".join(details)
        if not ok:
            text += f": below {min_fps_fraction:.0%} of the rate asked (bandwidth, exposure or a busy USB bus?)"
        out.append(Finding(part, ok, text))
    return out


def calibration_findings(
    cfg: CameraConfig, sizes: dict[str, tuple[int, int]] | None, max_error_px: float, max_age_days: float
) -> list[Finding]:
    rig = load_rig(cfg.rig)
    sim = cfg.world == "sim"
    problems = check_rig(rig, sizes, max_error_px, max_age_days, require_calibrated=not sim)
    if problems:
        return [Finding("calibration", False, p) for p in problems]
    how = "exact in sim" if sim and not any(c.calibrated for c in rig.cameras.values()) else "calibrated"
    seen = "match the cameras" if sizes is not None else "(cameras not opened)"
    return [Finding("calibration", True, f"{cfg.rig}: {', '.join(rig.cameras)} {how}, {seen}")]


def robot_findings(cfg: RobotConfig) -> list[Finding]:
    """Connect, read one state, check it is inside the workspace box; never command the arm."""
    try:
        driver = ROBOT_DRIVERS.build(cfg.driver, control_hz=cfg.control_hz)
    except Exception as exc:  # noqa: BLE001  (any driver's connect failure is a finding, not a crash)
        return [Finding("robot", False, f"{cfg.driver.type}: cannot connect: {_describe_error(exc)}")]
    try:
        snap = driver.read()
        fault = driver.fault()
    except Exception as exc:  # noqa: BLE001
        return [
            Finding(
                "robot", False, f"{cfg.driver.type}: connected but reading its state failed: {_describe_error(exc)}"
            )
        ]
    finally:
        driver.close()
    pos = np.asarray(snap.eef_pos, dtype=np.float64)
    where = "(" + ", ".join(f"{v:.3f}" for v in pos) + ") m"
    if not np.all(np.isfinite(pos)):
        return [Finding("robot", False, f"{cfg.driver.type}: the EEF position is not finite: {where}")]
    lo, hi = np.asarray(cfg.safety.workspace_lo), np.asarray(cfg.safety.workspace_hi)
    outside = [axis for axis, v, a, b in zip("xyz", pos, lo, hi) if not a <= v <= b]
    text = f"{cfg.driver.type}: EEF at {where}, gripper {snap.gripper:.2f}, {len(snap.joint_pos)} joints"
    if fault:
        return [Finding("robot", False, f"{text}: it cannot move: {fault}")]
    if outside:
        return [
            Finding(
                "robot",
                False,
                f"{text}: outside the safety workspace on {', '.join(outside)} "
                f"(box {tuple(lo)}..{tuple(hi)}): move the arm in, or fix safety.workspace_lo/hi",
            )
        ]
    return [Finding("robot", True, text)]


def policy_findings(teleop: TeleopConfig, cameras: CameraConfig, robot: RobotConfig) -> list[Finding]:
    """The policy server a policy teleop would drive with: it answers, and what it was trained with
    fits this session: the views are cameras here, sent at the size the policy expects, at the
    control rate it was trained at, and (a camera-space policy) placed where the server has them.
    Each of these, wrong, fails every GetAction or moves the arm wrong in the session itself."""
    from services.policy.client import PolicyClient, PolicyError

    d = teleop.driver
    if d.type != "policy":
        return [Finding("policy", False, f"teleop.driver.type is {d.type}, not policy: there is no policy to check")]
    try:
        ca = Path(d.tls_ca).read_bytes() if d.tls_ca else None
        with PolicyClient(
            d.server, session_id="check", token=d.token, tls_ca=ca, connect_timeout_s=min(d.connect_timeout_s, 10.0)
        ) as client:
            info = client.info
    except (PolicyError, OSError, ValueError) as exc:
        return [Finding("policy", False, f"{d.server}: {_describe_error(exc)}")]
    served = {c.name: c for c in info.cameras}
    views = list(d.views or info.default_views)
    findings = [
        Finding(
            "policy",
            True,
            f"{info.model_id} at {d.server}: {info.action_space} space, views {','.join(views)}, "
            f"trained at {info.control_hz:g} Hz",
        )
    ]
    if abs(info.control_hz - robot.control_hz) > 1e-3 * info.control_hz:
        findings.append(
            Finding(
                "policy",
                False,
                f"the policy was trained at {info.control_hz:g} Hz, the robot ticks at {robot.control_hz:g} Hz "
                "(robot.control_hz): each action is one tick's motion, so the arm would move "
                f"{robot.control_hz / info.control_hz:.2f}x as fast; set robot.control_hz to {info.control_hz:g}",
            )
        )
    names = list(getattr(cameras.driver, "cameras", None) or [])
    try:  # (a sim rig is framed for the sim's task)
        rig = load_rig(cameras.rig, getattr(cameras.driver, "task", None))
    except ConfigError as exc:
        rig = None
        findings.append(Finding("policy", False, f"camera.rig {cameras.rig!r}: {_describe_error(exc)}"))
    names = names or (rig.names if rig is not None else [])
    camera_space = needs_calibration(info.action_space, info.state_frame)
    for v in views:
        part = f"policy view {v}"
        if v not in served:
            findings.append(Finding(part, False, f"the policy server has no camera {v} ({', '.join(served)})"))
            continue
        if names and v not in names:
            findings.append(Finding(part, False, f"this session has no camera {v} ({', '.join(names)})"))
            continue
        c = served[v]
        if (c.width, c.height) != (cameras.width, cameras.height):
            findings.append(
                Finding(
                    part,
                    False,
                    f"the camera service sends {cameras.width}x{cameras.height} frames, the policy server expects "
                    f"{c.width}x{c.height} (the size its demonstrations were recorded at): every GetAction "
                    f"would be refused; set camera.width/height to {c.width}x{c.height}",
                )
            )
            continue
        if not camera_space or rig is None or v not in rig.cameras:
            findings.append(Finding(part, True, f"{c.width}x{c.height}"))
            continue
        here = rig.cameras[v]
        gap = served_camera_gap(c, here, here.K(c.width, c.height), (c.width, c.height))
        if gap:
            findings.append(
                Finding(
                    part,
                    False,
                    f"camera.rig {cameras.rig} has it {gap} from the calibration the policy server computes its "
                    f"camera-frame actions with (they would move the arm the wrong way): serve with "
                    f"--rig {cameras.rig}",
                )
            )
        else:
            findings.append(Finding(part, True, f"{c.width}x{c.height}, placed as the server has it"))
    return findings


def run_check(
    config: str | None,
    overrides: dict[str, list[str]] | None = None,
    seconds: float = 3.0,
    min_fps_fraction: float = 0.9,
    max_error_px: float = 1.0,
    max_age_days: float = 30.0,
    parts: Iterable[str] | None = None,
) -> list[Finding]:
    """Every finding for the session ``config`` describes (sections ``camera``, ``robot`` and
    ``teleop``). ``parts``: None for all (the policy only where the teleop drives with one)."""
    overrides = overrides or {}
    default_parts = parts is None
    parts = set(PARTS if parts is None else parts)
    findings: list[Finding] = []
    loaded: dict[str, Any] = {}

    def section(model, name: str):  # each section read once, whichever parts need it
        if name not in loaded:
            loaded[name] = load_config(model, config, overrides.get(name, []), section=name)
        return loaded[name]

    sizes: dict[str, tuple[int, int]] | None = None
    if parts & {"cameras", "calibration"}:
        cam_cfg = section(CameraConfig, "camera")
        rig = None
        try:
            load_rig(cam_cfg.rig)  # both parts need it: say once what is wrong with it
        except ConfigError as exc:
            if "calibration" in parts:  # (--only cameras: before the rig file is written, not a failure)
                why = f"camera.rig {cam_cfg.rig!r}: {_describe_error(exc)}"
                how = "" if "calibrate rig" in why else " (write one with `viewscale calibrate rig`)"
                findings.append(Finding("calibration", False, why + how))
            parts.discard("calibration")
            # cameras are checked before they are calibrated too (before: left out without a line)
            rig = stand_in_rig(cam_cfg)
            if rig is None and "cameras" in parts:
                findings.append(Finding("cameras", False, f"{cam_cfg.driver.type}: not checked: they need camera.rig"))
                parts.discard("cameras")
        if "cameras" in parts:
            try:
                reports = measure_cameras(cam_cfg, seconds, rig)
            except Exception as exc:  # noqa: BLE001  (a driver that cannot open is the finding)
                findings.append(Finding("cameras", False, f"{cam_cfg.driver.type}: {_describe_error(exc)}"))
            else:
                findings += camera_findings(cam_cfg, reports, min_fps_fraction)
                sizes = {r.name: r.native or r.size for r in reports if r.size}
        if "calibration" in parts:
            try:
                findings += calibration_findings(cam_cfg, sizes, max_error_px, max_age_days)
            except ConfigError as exc:
                findings.append(Finding("calibration", False, _describe_error(exc)))
    if "robot" in parts:
        findings += robot_findings(section(RobotConfig, "robot"))
    if "policy" in parts:
        teleop_cfg = section(TeleopConfig, "teleop")
        if teleop_cfg.driver.type == "policy" or not default_parts:
            findings += policy_findings(teleop_cfg, section(CameraConfig, "camera"), section(RobotConfig, "robot"))
    return findings
