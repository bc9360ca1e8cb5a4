"""``viewscale eval``: closed-loop episodes of a trained policy through the real services.

    viewscale eval --checkpoint runs/lift --task lift --episodes 50 --views F --out runs/eval-lift-F
    viewscale eval --checkpoint runs/lift --task lift --episodes 50 --views F,FL,FR --workers 3 --out ...
    viewscale eval --expert --task lift --episodes 50 --out runs/eval-lift-expert      # the baseline row
    viewscale eval --server 127.0.0.1:50051 --task lift --episodes 10 --views F --out ...  # a running server

Starts the policy server (``viewscale serve``, in-process or with worker processes; or uses a
running one with ``--server``, its defaults read from GetPolicyInfo), then a
session stack on loopback as ``viewscale collect`` does -- router, the sim (the checkpoint's rig
and frame size), the recorder, and the teleop whose driver is the policy (``type: policy``: the
robot-side client and its chunk runner) -- and runs an evaluation session: every episode is
recorded to MCAP, success or failure, from seeds fixed per task and disjoint from every training
seed (``EVAL_SEEDS``), so every row of a table starts from the same scenes. Lockstep by default
(the sim waits for each command, so results do not depend on how loaded the machine is);
``--realtime`` runs at the control rate, where latency shows as underruns.

Writes ``report.json`` and ``report.md`` (success k/n with a Wilson 95% interval, episode lengths,
GetAction latency p50/p99, underruns, stale actions, degraded answers, one row per episode), the
rollouts under ``rollouts/``, service logs under ``logs/``, and with ``--video N`` MP4s of the
first N episodes from one camera with the outcome marked.
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from services.core.bus import Bus
from services.core.config import ConfigError, named_twice
from services.core.rig import load_rig
from services.core.runtime import EVALUATION, OutputError, child_env, exclusive, refuse_other_output, writable_dir
from services.core.stats import percentile, wilson
from services.policy.aggregation import CompositionError, renormalise
from services.policy.checkpoint import read_info, resolve_checkpoint
from services.session.collect import CollectError, LocalStack
from services.session.config import DEFAULT_MAX_TICKS, EVAL_SEED_FLOOR, EVAL_SEEDS, SessionConfig
from services.session.session import Session, SessionError, SessionResult
from services.session.video import write_video


class EvalError(RuntimeError):
    """The evaluation could not run; the message says why."""


@dataclass
class EvalSpec:
    task: str
    episodes: int = 50
    checkpoint: str | None = None  # None with expert
    expert: bool = False  # the scripted expert through the same path (the sanity row)
    views: list[str] | None = None  # composed views (default: the checkpoint's training views)
    gamma: dict[str, float] | None = None
    workers: int = 0  # policy worker processes (0: in-process)
    server: str | None = None  # a running `viewscale serve` (host:port) instead of starting one
    tls_ca: str | None = None  # that server serves TLS: the PEM file of the CA that signed its certificate
    rig: str | None = None  # default: the checkpoint's
    size: int | None = None  # frame size the sim renders (default: the checkpoint's cameras')
    realtime: bool = False
    seed: int | None = None  # first evaluation seed (default: EVAL_SEEDS[task])
    max_ticks: int | None = None
    video: int = 0  # MP4s of the first N episodes
    video_camera: str | None = None  # default: the first view


@dataclass
class EvalResult:
    report: dict[str, Any]
    out: Path
    rows: list[dict[str, Any]] = field(default_factory=list)


def _checkpoint_facts(path: str) -> dict[str, Any]:
    """What the evaluation needs from policy.json (without loading weights)."""
    ck = resolve_checkpoint(path)
    info = read_info(ck)
    cal = next((c for c in (info.get("calibration") or {}).values() if c), None)
    return {
        "path": str(ck),
        "rigs": info.get("rigs") or [],
        "tasks": info.get("tasks") or [],
        "views": info.get("views") or [],
        "control_hz": info.get("control_hz") or 20.0,
        "size": (int(cal["source_width"]), int(cal["source_height"])) if cal else None,
    }


def _server_facts(address: str, tls_ca: str | None = None, timeout_s: float = 15.0) -> dict[str, Any]:
    """What the evaluation needs, asked of a running policy server (GetPolicyInfo)."""
    from services.policy.client import PolicyClient, PolicyError

    token = os.environ.get("VIEWSCALE_DRIVER__TOKEN")
    try:
        ca = Path(tls_ca).read_bytes() if tls_ca else None
    except OSError as exc:
        raise EvalError(f"--tls-ca {tls_ca}: {exc.strerror}") from None
    # a server that is down, or still starting, is retried for timeout_s: said after a moment,
    # rather than a silent wait (the error at the end says why it never answered)
    waiting = threading.Timer(
        2.0, lambda: print(f"waiting for the policy server at {address} (up to {timeout_s:.0f} s)", flush=True)
    )
    waiting.daemon = True
    waiting.start()
    try:
        with PolicyClient(
            address, session_id="eval-info", token=token, tls_ca=ca, connect_timeout_s=timeout_s
        ) as client:
            info = client.info
    except PolicyError as exc:
        said = str(exc)  # (most name the address already: not twice)
        raise EvalError(f"--server: {said}" if address in said else f"--server {address}: {said}") from None
    except ValueError as exc:  # a --tls-ca file that holds no certificate
        raise EvalError(f"--tls-ca {tls_ca}: {exc}") from None
    finally:
        waiting.cancel()
    cams = list(info.cameras)
    return {
        "path": f"{info.model_id} served by {address}",
        "rigs": [],
        "tasks": [],
        "views": list(info.default_views),
        "cameras": [c.name for c in cams],
        "control_hz": info.control_hz or 20.0,
        "size": (int(cams[0].width), int(cams[0].height)) if cams else None,
    }


class PolicyServer:
    """``viewscale serve`` as a subprocess on a free loopback port; a context manager. It runs in
    this process's folder, where a relative --checkpoint, --out or --rig means what it means here."""

    def __init__(
        self,
        checkpoint: str,
        log_dir: Path,
        views: list[str] | None,
        workers: int,
        rig: str,
        task: str,
        ready_timeout_s: float = 300.0,
    ):
        cmd = [
            sys.executable,
            "-m",
            "services.policy",
            "serve",
            "--checkpoint",
            checkpoint,
            "--listen",
            "127.0.0.1:0",
            "--rig",
            rig,
            "--task",
            task,
            "--log-dir",
            str(log_dir),
        ]
        if views:
            cmd += ["--views", ",".join(views)]
        if workers:
            cmd += ["--workers", str(workers)]
        self.cmd = cmd
        self.log_path = log_dir / "policy.log"
        self.ready_timeout_s = ready_timeout_s
        self.proc: subprocess.Popen | None = None
        self.address = ""

    def __enter__(self) -> PolicyServer:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "a") as log:
            self.proc = subprocess.Popen(self.cmd, stdout=subprocess.PIPE, stderr=log, text=True, env=child_env())
        deadline = time.monotonic() + self.ready_timeout_s
        for line in self.proc.stdout:
            if line.startswith("ready policy "):
                self.address = line.split()[2]
                return self
            if time.monotonic() > deadline:
                break
        self.__exit__()
        tail = "\n".join(self.log_path.read_text(errors="replace").splitlines()[-15:])
        raise EvalError(f"the policy server did not start; last log lines:\n{tail}")

    def __exit__(self, *exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc is not None and self.proc.stdout:
            self.proc.stdout.close()


def _episode_rows(result, stats: dict[str, dict]) -> list[dict[str, Any]]:
    rows = []
    for a in result.attempts:
        s = stats.get(a.episode_id, {})
        lat = s.get("latency_ms", [])
        rows.append(
            {
                "seed": a.seed,
                "episode_id": a.episode_id,
                "success": bool(a.success),
                "ticks": a.ticks,
                "seconds": round(a.seconds, 2),
                "path": a.meta.path if a.meta is not None else "",
                "flags": list(a.meta.flags) if a.meta is not None else [],
                "requests": s.get("requests"),
                "latency_p50_ms": percentile(lat, 0.5),
                "underruns": s.get("underruns"),
                "stale_dropped": s.get("stale_dropped"),
                "degraded": s.get("degraded"),
                "failed_requests": s.get("failed"),
                "first_error": s.get("first_error"),
                "refused": s.get("refused"),
            }
        )
    return rows


def summarise(
    spec: EvalSpec, rows: list[dict[str, Any]], latencies: list[float], facts: dict | None, seconds: float
) -> dict[str, Any]:
    n = len(rows)
    k = sum(r["success"] for r in rows)
    lo, hi = wilson(k, n)
    ok_ticks = [r["ticks"] for r in rows if r["success"]]

    def total(key: str) -> int | None:
        return None if spec.expert else sum(r[key] or 0 for r in rows)

    return {
        "task": spec.task,
        "checkpoint": facts["path"] if facts else None,
        "expert": spec.expert,
        "views": spec.views,
        "workers": spec.workers,
        "server": spec.server,
        "realtime": spec.realtime,
        "episodes": n,
        "successes": k,
        "success_rate": k / n if n else 0.0,
        "wilson95": [round(lo, 4), round(hi, 4)],
        "seeds": [rows[0]["seed"], rows[-1]["seed"]] if rows else [],
        "ticks_success_mean": round(statistics.mean(ok_ticks), 1) if ok_ticks else None,
        "ticks_all_mean": round(statistics.mean(r["ticks"] for r in rows), 1) if rows else None,
        "getaction_ms_p50": percentile(latencies, 0.5),
        "getaction_ms_p99": percentile(latencies, 0.99),
        "requests": total("requests"),
        "underruns": total("underruns"),
        "stale_dropped": total("stale_dropped"),
        "degraded_answers": total("degraded"),
        "failed_requests": total("failed_requests"),
        "first_error": next((r["first_error"] for r in rows if r.get("first_error")), None),
        # episodes the policy teleop would not drive in, and why (the first)
        "refused_episodes": None if spec.expert else sum(bool(r.get("refused")) for r in rows),
        "refused": next((r["refused"] for r in rows if r.get("refused")), None),
        "wall_s": round(seconds, 1),
    }


def format_report(rep: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    who = "scripted expert" if rep["expert"] else f"{rep['checkpoint']} views {','.join(rep['views'] or [])}"
    lines = [
        f"# Evaluation: {rep['task']}, {who}",
        "",
        f"**{rep['successes']}/{rep['episodes']} successful** ({100 * rep['success_rate']:.0f} %, Wilson 95% "
        f"{100 * rep['wilson95'][0]:.0f}-{100 * rep['wilson95'][1]:.0f} %), seeds {rep['seeds'][0]}.."
        f"{rep['seeds'][-1]}, {'real time' if rep['realtime'] else 'lockstep'}, {rep['wall_s']:.0f} s.",
        "",
    ]
    if rep.get("interrupted"):
        lines += [
            f"**Interrupted ({rep['interrupted']}) after {rep['episodes']} of {rep['episodes_asked']} episodes**: "
            "these are the episodes that ran to their end; the one cut short is kept among the rollouts, "
            "flagged, and not counted.",
            "",
        ]
    lines.append(f"- ticks: {rep['ticks_success_mean']} mean over the successes, {rep['ticks_all_mean']} over all")
    if not rep["expert"]:
        lines += [
            f"- GetAction: p50 {rep['getaction_ms_p50']:.1f} ms, p99 {rep['getaction_ms_p99']:.1f} ms over "
            f"{rep['requests']} requests"
            if rep["getaction_ms_p50"] is not None
            else f"- GetAction: no answer to any of {rep['requests'] or 0} requests",
            f"- underruns {rep['underruns']}, stale actions dropped {rep['stale_dropped']}, degraded answers "
            f"{rep['degraded_answers']}, failed requests {rep['failed_requests']}",
        ]
        if rep.get("first_error"):
            lines.append(f"- first failed request: {rep['first_error']}")
        if rep.get("refused"):
            lines.append(f"- the policy held the arm still in {rep['refused_episodes']} episodes: {rep['refused']}")
    lines += ["", "| seed | outcome | ticks | requests | p50 ms | underruns | file |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        p50 = f"{r['latency_p50_ms']:.1f}" if r["latency_p50_ms"] is not None else "-"
        lines.append(
            f"| {r['seed']} | {'success' if r['success'] else 'FAIL'} | {r['ticks']} | "
            f"{r['requests'] if r['requests'] is not None else '-'} | {p50} | "
            f"{r['underruns'] if r['underruns'] is not None else '-'} | {Path(r['path']).name} |"
        )
    return "\n".join(lines) + "\n"


def _check_gamma(spec: EvalSpec, views: list[str]) -> None:
    """The server's rules for composition weights, before any process starts: a request it would
    refuse every time would make the whole evaluation a row of failures."""
    if spec.expert:
        raise EvalError("--gamma weights the policy's views: not with --expert")
    unknown = [v for v in spec.gamma if v not in views]
    if unknown:
        raise EvalError(f"--gamma names {', '.join(unknown)}: not among the composed views {','.join(views)} (--views)")
    # the composition's own rules (a view left out keeps a positive default weight on the server)
    try:
        renormalise({v: spec.gamma.get(v, 1.0) for v in views}, views)
    except CompositionError as exc:
        raise EvalError(f"--gamma {','.join(f'{v}={g}' for v, g in spec.gamma.items())}: {exc}") from None


def _check_numbers(spec: EvalSpec) -> None:
    """The numeric flags, checked before anything starts (they were found out by the sim's or the
    session's config a few seconds in, as a multi-line validation error, or not at all)."""
    for flag, value, low, high in [
        ("--max-ticks", spec.max_ticks, 1, None),
        ("--seed", spec.seed, 0, None),
        ("--video", spec.video, 0, None),
        ("--workers", spec.workers, 0, None),
        ("--size", spec.size, 16, 4096),
    ]:
        if value is not None and (value < low or (high is not None and value > high)):
            bound = f"{low}..{high}" if high is not None else f"at least {low}"
            raise EvalError(f"{flag} must be {bound}, got {value}")


def evaluate(spec: EvalSpec, out: Path, progress: Callable[[str], None] = print) -> EvalResult:
    t0 = time.monotonic()
    out = Path(out)
    if spec.task not in DEFAULT_MAX_TICKS:
        raise EvalError(f"unknown task {spec.task!r}; tasks: {', '.join(DEFAULT_MAX_TICKS)}")
    if spec.episodes < 1:
        raise EvalError(f"--episodes must be at least 1, got {spec.episodes}")
    _check_numbers(spec)
    if spec.expert and (spec.checkpoint or spec.server or spec.tls_ca):
        raise EvalError("--expert evaluates the scripted expert: leave out --checkpoint, --server and --tls-ca")
    if spec.expert and (spec.views or spec.workers):  # (before: taken, unchecked, and meaning nothing)
        raise EvalError(
            "--views and --workers are the policy's: not with --expert (--video-camera picks the videos' camera)"
        )
    facts = None
    if not spec.expert:
        if spec.server:
            if spec.checkpoint or spec.workers:
                raise EvalError("--server evaluates a running policy server: leave out --checkpoint and --workers")
            facts = _server_facts(spec.server, spec.tls_ca)
            unknown = [v for v in spec.views or [] if v not in facts["cameras"]]
            if unknown:
                raise EvalError(
                    f"the server at {spec.server} has no camera {', '.join(unknown)}; "
                    f"it knows {', '.join(facts['cameras'])} (start it with the rig holding them: --rig)"
                )
        elif not spec.checkpoint:
            raise EvalError("--checkpoint is required (or --server, or --expert for the scripted baseline)")
        elif spec.tls_ca:  # (the server it starts listens on loopback, in plaintext)
            raise EvalError("--tls-ca is for a running server that serves TLS: give it with --server")
        else:
            facts = _checkpoint_facts(spec.checkpoint)
        if facts["tasks"] and spec.task not in facts["tasks"]:
            progress(f"note: {facts['path']} was trained on {', '.join(facts['tasks'])}, evaluated on {spec.task}")
    policy_rig = facts["rigs"][0] if facts and len(facts["rigs"]) == 1 else None
    rig = spec.rig or policy_rig or "five15"
    size = spec.size or (facts["size"][0] if facts and facts["size"] else 84)
    views = spec.views or (facts["views"] if facts else None)
    if spec.gamma:
        _check_gamma(spec, views or [])
    try:
        cameras = list(load_rig(rig).cameras)  # a typo in --rig: one line now, not from the sim later
    except ConfigError as exc:
        raise EvalError(f"--rig: {exc}") from None
    twice = named_twice(views or [])
    if twice:
        raise EvalError(f"--views names {', '.join(twice)} more than once")
    missing = [v for v in views or [] if v not in cameras]
    if missing and not spec.expert:
        given = "--views" if spec.views else f"--views (default: the policy's views, {','.join(views or [])})"
        which = (
            ""
            if spec.rig
            else " (the policy's rig: --rig renders another)"
            if policy_rig
            else " (the default: --rig names the rig the sim renders)"
        )
        raise EvalError(
            f"{given}: rig {rig}{which} has no camera {', '.join(missing)}; its cameras: {', '.join(cameras)}"
        )
    video_camera = spec.video_camera or (views[0] if views else cameras[0])
    if spec.video and video_camera not in cameras:  # (found out once every episode had run, before)
        raise EvalError(f"--video-camera {video_camera}: rig {rig} has no such camera ({', '.join(cameras)})")
    if spec.seed is not None and spec.seed < EVAL_SEED_FLOOR and not spec.expert:
        progress(
            f"note: --seed {spec.seed} is below {EVAL_SEED_FLOOR}, among the seeds collection records: "
            "a policy trained on such episodes is evaluated on its training scenes"
        )
    rollouts = out / "rollouts"
    if rollouts.exists() and any(rollouts.glob("*.mcap")):
        raise EvalError(f"{rollouts} already holds rollouts: pick another --out (or remove it)")
    held = contextlib.ExitStack()
    try:
        refuse_other_output(out, "--out", EVALUATION)  # (a report and rollouts among other files)
        writable_dir(out, "--out")
        # one evaluation per folder: a second one would record over its rollouts and statistics
        held.enter_context(exclusive(out, "evaluation"))
    except OutputError as exc:
        raise EvalError(str(exc)) from None
    with held:
        stats_file = out / "logs" / "policy_stats.jsonl"
        stats_file.parent.mkdir(parents=True, exist_ok=True)
        stats_file.unlink(missing_ok=True)

        sim = [
            f"rig={rig}",
            f"task={spec.task}",
            f"realtime={str(spec.realtime).lower()}",
            f"width={size}",
            f"height={size}",
            "command_timeout_s=120",
        ]
        teleop: list[str] = []
        seed0 = spec.seed if spec.seed is not None else EVAL_SEEDS[spec.task]
        cfg_kw = dict(
            task=spec.task,
            rig=rig,
            episodes=spec.episodes,
            seed=seed0,
            evaluation=True,
            max_ticks=spec.max_ticks,
            control_hz=facts["control_hz"] if facts else 20.0,
        )

        def run_session(server_address: str | None):
            if server_address is not None:
                teleop[:] = [
                    "driver.type=policy",
                    f"driver.server={server_address}",
                    f"driver.blocking={str(not spec.realtime).lower()}",
                    f"driver.stats_file={stats_file}",
                ]
                if spec.tls_ca:
                    teleop.append(f"driver.tls_ca={Path(spec.tls_ca).resolve()}")
                if views:
                    teleop.append("driver.views=[" + ",".join(views) + "]")
                if spec.gamma:
                    teleop.append("driver.gamma={" + ",".join(f"{k}: {v}" for k, v in spec.gamma.items()) + "}")
            overrides = {"sim": sim, "recorder": [f"out_dir={rollouts}"], "teleop": teleop}
            who = "the scripted expert" if spec.expert else f"the policy ({', '.join(views or [])})"
            progress(
                f"evaluating {who} on {spec.task}: {spec.episodes} episodes from seed {seed0}, rig {rig}, "
                f"{size}x{size}, {'real time' if spec.realtime else 'lockstep'}"
            )
            with LocalStack(out, None, overrides) as stack:
                progress(f"services ready on {stack.endpoint}; logs in {stack.log_dir}")
                cfg = SessionConfig(bus=stack.bus_config(), **cfg_kw)
                with Bus(cfg.bus) as bus:
                    sessions.append(Session(cfg, bus, progress=progress))
                    try:
                        return sessions[-1].run()
                    except (SessionError, TimeoutError) as exc:
                        stack.check_alive(grace_s=3.0)
                        raise CollectError(str(exc)) from exc

        def report(result: SessionResult, interrupted: str | None = None) -> tuple[dict, list[dict]]:
            stats = {}
            if stats_file.is_file():
                for line in stats_file.read_text().splitlines():
                    row = json.loads(line)
                    stats[row["episode_id"]] = row
            rows = _episode_rows(result, stats)
            latencies = [x for st in stats.values() for x in st["latency_ms"]]
            rep = summarise(replace(spec, views=views), rows, latencies, facts, time.monotonic() - t0)
            rep["rig"], rep["size"] = rig, size
            rep["episodes_asked"], rep["interrupted"] = spec.episodes, interrupted
            (out / "report.json").write_text(json.dumps({"summary": rep, "episodes": rows}, indent=2) + "\n")
            (out / "report.md").write_text(format_report(rep, rows))
            return rep, rows

        sessions: list[Session] = []
        try:
            if spec.expert:
                result = run_session(None)
            elif spec.server:
                progress(f"policy server {spec.server}: {facts['path']}")
                result = run_session(spec.server)
            else:
                with PolicyServer(facts["path"], out / "logs", views, spec.workers, rig, spec.task) as server:
                    progress(f"policy server ready on {server.address} ({spec.workers or 'no'} workers)")
                    result = run_session(server.address)
        except KeyboardInterrupt as exc:
            # the episodes that ran to their end are evaluated: a report of them, marked as
            # interrupted (the one cut short is kept among the rollouts, flagged, and not counted)
            done = getattr(sessions[-1], "result", None) if sessions else None
            if done is not None and done.attempts:
                rep, _ = report(done, interrupted=str(exc) or "SIGINT")
                lo, hi = rep["wilson95"]
                progress(
                    f"{spec.task}: {rep['successes']}/{rep['episodes']} successful in the {rep['episodes']} of "
                    f"{spec.episodes} episodes that ran to their end ({100 * rep['success_rate']:.0f} %, Wilson 95% "
                    f"{100 * lo:.0f}-{100 * hi:.0f} %); report {out / 'report.md'}"
                )
            raise

        rep, rows = report(result)
        if spec.video:
            for r in rows[: spec.video]:
                path = write_video(
                    Path(r["path"]), video_camera, out / "videos" / f"{Path(r['path']).stem}.mp4", r["success"]
                )
                progress(f"video {path}")
        return EvalResult(rep, out, rows)
