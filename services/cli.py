"""``viewscale``: the command line of the whole system.

    viewscale collect --task lift --episodes 10 --rig five15 --out data/raw
    viewscale dataset build --raw data/raw --views F,FL,FR,FU,FD --space camera --out data/ds
    viewscale dataset info data/ds
    viewscale train --data data/ds --preset tiny --steps 2000 --out runs/lift-five15-camera
    viewscale router --listen tcp/0.0.0.0:7447
    viewscale credentials --out deploy/zenoh/secrets
    viewscale episode start --task pour --rig five15 ; viewscale episode stop --success

Errors a user can cause print one ``error:`` line and exit with code 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import os
import sys
from pathlib import Path


def _collect(args: argparse.Namespace) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from services.core.config import ConfigError
    from services.core.rig import load_rig
    from services.core.runtime import OutputError, interrupt_on_signals
    from services.session.collect import CollectError, collect, first_seed
    from services.session.config import EVAL_SEED_FLOOR
    from sim.config import MAX_CONTROL_HZ, MIN_CONTROL_HZ

    try:
        load_rig(args.rig)  # fail fast on a typo, before starting anything
        if args.task not in ("lift", "can", "square"):
            raise ConfigError(f"unknown task {args.task!r}; tasks: lift, can, square")
        if args.episodes < 1:
            raise ConfigError(f"--episodes must be at least 1, got {args.episodes}")
        if not MIN_CONTROL_HZ <= args.hz <= MAX_CONTROL_HZ:  # (before: the sim's traceback, or a hang at 1e-9)
            raise ConfigError(
                f"--hz must be {MIN_CONTROL_HZ:g}..{MAX_CONTROL_HZ:g} (the sim's physics steps every "
                f"{1e3 / MAX_CONTROL_HZ:g} ms), got {args.hz:g}"
            )
        if args.max_ticks is not None and args.max_ticks < 1:
            raise ConfigError(f"--max-ticks must be at least 1, got {args.max_ticks}")
        _check_size(args.size)
        seed = first_seed(Path(args.out), args.task, args.seed)  # (after the seeds --out holds, if not asked)
        last_seed = seed + 3 * args.episodes  # failed attempts move on to the next seed
        if seed < 0 or last_seed >= EVAL_SEED_FLOOR:
            raise ConfigError(
                f"--seed: collection seeds stay below {EVAL_SEED_FLOOR} (seeds from there on are "
                f"the evaluation's), got {seed} (with retries up to {last_seed})"
            )
        extra: dict[str, list[str]] = {}
        for item in args.set:
            service, _, rest = item.partition(".")
            if not rest:
                raise ConfigError(f"--set {item!r} must name a service: sim.width=224, recorder.queue_size=256")
            extra.setdefault(service, []).append(rest)
        # the episode in progress is closed and kept (flagged) and every service is stopped
        interrupt_on_signals()
        result = collect(
            args.task,
            args.episodes,
            args.rig,
            Path(args.out),
            config=args.config,
            seed=seed,
            size=args.size,
            realtime=not args.fast,
            control_hz=args.hz,
            max_ticks=args.max_ticks,
            extra=extra,
            auth=args.auth,
        )
    except (CollectError, ConfigError, OutputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _interrupted(exc, Path(args.out), "episodes")
    return 0 if len(result.recorded) >= args.episodes else 1


def _interrupted(exc: KeyboardInterrupt, folder: Path, what: str) -> int:
    """The line of a collection or evaluation stopped by a signal: the services it started are
    stopped, and where what was recorded is, or that nothing was (before: "... so far are in OUT"
    for a folder a signal during the start had never made)."""
    n = len(list(folder.glob("*.mcap"))) if folder.is_dir() else 0
    kept = f"{n} {what} in {folder}" if n else f"no {what} recorded"
    print(f"interrupted ({exc or 'SIGINT'}): services stopped; {kept}", file=sys.stderr)
    return 130


def _eval(args: argparse.Namespace) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from services.core.config import ConfigError
    from services.core.runtime import interrupt_on_signals
    from services.policy.checkpoint import CheckpointError
    from services.session.collect import CollectError
    from services.session.evaluate import EvalError, EvalSpec, evaluate

    views = [v.strip() for v in args.views.split(",") if v.strip()] if args.views else None
    gamma = None
    if args.gamma:
        try:
            gamma = {k.strip(): float(v) for k, v in (item.split("=", 1) for item in args.gamma.split(","))}
        except ValueError:
            print(f"error: --gamma must look like F=0.5,FL=0.25, got {args.gamma!r}", file=sys.stderr)
            return 2
    try:
        spec = EvalSpec(
            task=args.task,
            episodes=args.episodes,
            checkpoint=args.checkpoint,
            expert=args.expert,
            views=views,
            gamma=gamma,
            workers=args.workers,
            server=args.server,
            tls_ca=args.tls_ca,
            rig=args.rig,
            size=args.size,
            realtime=args.realtime,
            seed=args.seed,
            max_ticks=args.max_ticks,
            video=args.video,
            video_camera=args.video_camera,
        )
        interrupt_on_signals()
        result = evaluate(spec, Path(args.out))
    except (EvalError, CollectError, ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _interrupted(exc, Path(args.out) / "rollouts", "rollouts")
    r = result.report
    print(
        f"{r['task']}: {r['successes']}/{r['episodes']} successful ({100 * r['success_rate']:.0f} %, "
        f"Wilson 95% {100 * r['wilson95'][0]:.0f}-{100 * r['wilson95'][1]:.0f} %)"
    )
    if not r["expert"] and r["getaction_ms_p50"] is not None:
        print(
            f"GetAction p50 {r['getaction_ms_p50']:.1f} ms, p99 {r['getaction_ms_p99']:.1f} ms; "
            f"underruns {r['underruns']}, degraded answers {r['degraded_answers']}"
        )
    print(f"report {result.out / 'report.md'}; rollouts {result.out / 'rollouts'}")
    if not r["expert"] and r["failed_requests"]:
        every = r["failed_requests"] == r["requests"]
        print(
            f"{'error' if every else 'warning'}: {r['failed_requests']} of {r['requests']} GetAction requests failed "
            f"(the robot held still meanwhile); the first: {r['first_error']}",
            file=sys.stderr,
        )
        if every:  # not a policy that failed the task: nothing was evaluated
            return 1
    if not r["expert"] and r.get("refused"):
        every = r["refused_episodes"] == r["episodes"]
        print(
            f"{'error' if every else 'warning'}: the policy held the arm still in {r['refused_episodes']} of "
            f"{r['episodes']} episodes: {r['refused']}",
            file=sys.stderr,
        )
        if every:
            return 1
    return 0


def _check_size(size: int | None) -> None:
    """--size of collect and rerender: square frames the renderer and the dataset take."""
    from services.core.config import ConfigError

    if size is not None and not 16 <= size <= 4096:
        raise ConfigError(f"--size must be 16..4096 px, got {size}")


def _rerender(args: argparse.Namespace) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from services.core.config import ConfigError
    from services.core.runtime import RECORDINGS, OutputError, interrupt_on_signals, output_dir, refuse_other_output
    from services.dataset.build import find_episodes
    from services.dataset.store import DatasetError
    from sim.rerender import rerender

    try:
        _check_size(args.size)
        out = Path(args.out)
        for raw in (Path(p) for p in args.raw if Path(p).is_dir()):
            # its episodes would be read back as recordings: the next run re-renders the re-renders
            if raw.resolve() == out.resolve():
                raise ConfigError(f"--out {out} is a --raw folder: write the re-rendered episodes to another one")
            if raw.resolve() in out.resolve().parents:  # (before: taken, and read back the same way)
                beside = raw.resolve().parent / f"{raw.resolve().name}-{Path(args.rig).stem}"
                raise ConfigError(
                    f"--out {out} is inside the --raw folder {raw}: the re-rendered episodes would be read back "
                    f"as recordings of {raw} (re-rendered again by the next rerender, built along with them); "
                    f"write them beside it, e.g. --out {beside}"
                )
        episodes = find_episodes([Path(p) for p in args.raw])  # a wrong --raw: no empty --out left behind
        refuse_other_output(out, "--out", RECORDINGS)
        # Ctrl-C, SIGTERM, SIGHUP: the episode being rendered is dropped (its .part removed), those
        # done are kept, and the same command renders the rest
        interrupt_on_signals()
        with output_dir(out, "--out", keep_empty=False):  # taken back if nothing was written in it
            result = rerender(
                episodes,  # (the files found: the folders are not walked again)
                args.rig,
                Path(args.out),
                args.size,
                progress=lambda m: print(m, file=sys.stderr, flush=True),
            )
    except (ConfigError, DatasetError, OutputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        n = len(list(out.glob("*.mcap"))) if out.is_dir() else 0
        print(
            f"interrupted ({exc or 'SIGINT'}): {n} re-rendered episodes in {out}; run the same command to render "
            "the rest",
            file=sys.stderr,
        )
        return 130
    done = result.written
    kept = [e for e in done if e.kept]
    if done:
        print(
            f"re-rendered {len(done) - len(kept)} of {len(result.episodes)} episodes through {args.rig}"
            + (f" ({len(kept)} re-rendered before, kept)" if kept else "")
            + f" -> {args.out}"
        )
    else:
        print(f"re-rendered none of {len(result.episodes)} episodes through {args.rig}: nothing written to {args.out}")
    for e in result.episodes:
        if e.error:
            print(f"  skipped {e.source.name}: {e.error}")
    return 0 if done and len(done) == len(result.episodes) else 1


def _experiment(args: argparse.Namespace) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from services.core.config import ConfigError
    from services.core.runtime import OutputError, interrupt_on_signals, writable_dir
    from services.experiment.runner import ExperimentError, Runner

    try:
        if args.task not in ("lift", "can", "square"):
            raise ConfigError(f"unknown task {args.task!r}; tasks: lift, can, square")
        say = lambda m: print(m, flush=True)
        seeds = None
        if args.seeds is not None:
            try:
                seeds = [int(x) for x in args.seeds.split(",")]
            except ValueError:
                raise ConfigError(f"--seeds {args.seeds!r}: expected integers separated by commas (0,1,2)") from None
        runner = Runner(
            args.question, args.task, args.scale, Path(args.root), progress=say, only=args.only, seeds=seeds
        )
        writable_dir(args.root, "--root")  # (its cache and the tables go there)
        interrupt_on_signals()
        runner.run(table_only=args.table_only)
    except (ConfigError, ExperimentError, OutputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(
            f"interrupted ({exc or 'SIGINT'}): finished stages are kept; run the same command to resume",
            file=sys.stderr,
        )
        return 130
    return 0


def _episode(args: argparse.Namespace) -> int:
    """Drive the recorder by hand (hardware sessions): start/stop/discard/status."""
    from services.core.bus import Bus, BusConfig
    from services.recorder.control import describe_reply, episode_control, episode_request

    for flag, value, unit in (("--timeout", args.timeout, "seconds"), ("--hz", args.hz, "Hz")):
        if not 0 < value < math.inf:  # a timeout of -1 would be zenoh's "forever"; nan or inf: no number at all
            print(f"error: {flag} must be a positive number of {unit}, got {value:g}", file=sys.stderr)
            return 2
    if not 0 <= args.seed < 2**64:  # (before: a ValueError traceback from the protobuf field)
        print(f"error: --seed must be an integer from 0 to 2**64-1, got {args.seed}", file=sys.stderr)
        return 2
    req = episode_request(
        args.action,
        episode_id=args.id,
        task=args.task,
        rig=args.rig,
        seed=args.seed,
        control_hz=args.hz,
        success=args.success,
    )
    try:
        cfg = BusConfig(
            mode="client",
            connect=[args.connect],
            connect_timeout_s=min(args.timeout, 5.0),
            user=args.user,
            password_file=args.password_file,
        )
        with Bus(cfg) as bus:
            reply = episode_control(bus, req, args.timeout)
    except (TimeoutError, RuntimeError, ConnectionError, ValueError) as exc:  # ValueError: config, credentials
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not reply.ok:
        print(f"error: {reply.error}", file=sys.stderr)
        return 2
    print(describe_reply(args.action, reply))
    return 0


def _router(args: argparse.Namespace) -> int:
    from services.router.__main__ import main as router_main

    if args.acl and not args.users:  # (checked here too: the module's parser would name itself, not viewscale)
        print("error: --acl needs --users: its rules name users that must authenticate", file=sys.stderr)
        return 2
    argv = sum((["--listen", e] for e in args.listen or []), [])
    argv += ["--users", args.users] if args.users else []
    argv += ["--acl", args.acl] if args.acl else []
    return router_main(argv)


def _credentials(args: argparse.Namespace) -> int:
    from services.router.credentials import SERVICE_USERS, USERS_FILE, write_credentials

    # (a name given twice is written once: the summary said it twice; an empty --users is an error,
    # not every user of the ACL)
    users = list(dict.fromkeys(u.strip() for u in args.users.split(","))) if args.users is not None else SERVICE_USERS
    try:
        write_credentials(Path(args.out), users, force=args.force)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    print(f"wrote {len(users)} passwords to {out} (owner-only): {out / USERS_FILE} for the router,")
    print(f"  {', '.join(f'{u}.password' for u in users)} for the services (bus.password_file)")
    return 0


def _check(args: argparse.Namespace) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")  # a sim rig renders headless, as the camera service does
    from services.core.cli_args import service_overrides
    from services.core.config import ConfigError
    from services.session.check import PARTS, run_check

    try:  # (a service check reads no settings of, sim.x=1, was ignored without a word before)
        overrides = service_overrides(args.set, ("camera", "robot", "teleop"))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for flag, value in (("--seconds", args.seconds), ("--max-error-px", args.max_error_px)):
        if not value > 0:  # (a limit of 0 or less would fail every real camera's calibration)
            print(f"error: {flag} must be positive, got {value:g}", file=sys.stderr)
            return 2
    if not args.max_age_days >= 0:
        print(f"error: --max-age-days must be 0 or more, got {args.max_age_days:g}", file=sys.stderr)
        return 2
    every = list(PARTS)
    parts = None if args.only is None else [p.strip() for p in args.only.split(",") if p.strip()]
    unknown = sorted(set(parts or []) - set(every))
    if unknown or parts == []:
        print(f"error: --only {', '.join(unknown) or args.only}: choose from {', '.join(every)}", file=sys.stderr)
        return 2
    try:
        findings = run_check(
            args.config,
            overrides,
            seconds=args.seconds,
            max_error_px=args.max_error_px,
            max_age_days=args.max_age_days,
            parts=parts,
        )
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for f in findings:
        print(f.line())
    failed = [f for f in findings if not f.ok]
    print(f"{len(findings) - len(failed)} ok, {len(failed)} failed" + (": fix the FAIL lines above" if failed else ""))
    return 1 if failed else 0


def _add_optional(sub, module: str, register: str) -> None:
    """Subcommands that live with their feature (dataset, train) register themselves."""
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        if exc.name and (exc.name == module or module.startswith(exc.name)):
            return  # feature not installed in this build
        raise
    getattr(mod, register)(sub)


def build_parser() -> argparse.ArgumentParser:
    from services.core.cli_args import log_level_arg

    parser = argparse.ArgumentParser(prog="viewscale", description="Scale camera views instead of demonstrations.")
    parser.add_argument(
        "--log-level",
        default="WARNING",
        type=log_level_arg,
        help="logging level: DEBUG, INFO, WARNING, ERROR or CRITICAL (default WARNING); "
        "serve and worker log at their own log_level setting (INFO)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("collect", help="record scripted-expert episodes in sim through the real services")
    p.add_argument("--task", default="lift", help="lift, can or square (default lift)")
    p.add_argument("--episodes", type=int, default=10, help="successful episodes to record (default 10)")
    p.add_argument("--rig", default="five15", help="camera rig preset or YAML (default five15)")
    p.add_argument("--out", default="data/raw", help="directory for the episode MCAP files (default data/raw)")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="first seed; failed attempts move to the next (default: after the seeds of the task already in --out, "
        "0 in a new folder: a seed is a scene, recorded again the same)",
    )
    p.add_argument("--size", type=int, default=None, help="square frame size in px (default from config: 84)")
    p.add_argument("--hz", type=float, default=20.0, help="control rate (default 20)")
    p.add_argument("--max-ticks", type=int, default=None, help="per-episode tick limit (default per task)")
    p.add_argument("--fast", action="store_true", help="lockstep instead of real time: as fast as the machine goes")
    p.add_argument(
        "--auth",
        action="store_true",
        help="every service authenticates as its own user; the router enforces deploy/zenoh/router-acl.json5",
    )
    p.add_argument("--config", default=None, help="YAML with per-service sections (e.g. deploy/sim.yaml)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SERVICE.KEY=VALUE",
        help="override a service's config field, e.g. sim.jpeg_quality=80 (repeatable)",
    )
    p.set_defaults(func=_collect)

    p = sub.add_parser(
        "eval", help="closed-loop episodes of a trained policy (or the expert) through the real services"
    )
    p.add_argument("--checkpoint", help="checkpoint folder or run directory")
    p.add_argument("--expert", action="store_true", help="the scripted expert instead, through the same path")
    p.add_argument("--task", default="lift", help="lift, can or square (default lift)")
    p.add_argument("--episodes", type=int, default=50, help="episodes to run (default 50)")
    p.add_argument("--views", help="cameras to compose, e.g. F or F,FL,FR (default: the training views)")
    p.add_argument("--gamma", help="composition weights, e.g. F=0.5,FL=0.25,FR=0.25 (default 1/V)")
    p.add_argument("--workers", type=int, default=0, help="policy worker processes (default 0: in-process)")
    p.add_argument(
        "--server",
        help="evaluate a running `viewscale serve` at HOST:PORT instead of starting one "
        "(its token: VIEWSCALE_DRIVER__TOKEN)",
    )
    p.add_argument("--tls-ca", metavar="PEM", help="--server serves TLS: the CA certificate that signed its own")
    p.add_argument("--rig", help="the sim's rig (default: the checkpoint's; five15 with --server, which names none)")
    p.add_argument("--size", type=int, help="frame size the sim renders (default: the checkpoint's)")
    p.add_argument("--realtime", action="store_true", help="run at the control rate (default lockstep)")
    p.add_argument("--seed", type=int, help="first seed (default: the task's fixed evaluation seeds)")
    p.add_argument("--max-ticks", type=int, help="per-episode tick limit (default: the task's horizon)")
    p.add_argument("--video", type=int, default=0, metavar="N", help="write MP4s of the first N episodes")
    p.add_argument("--video-camera", help="camera of the videos (default: the first view)")
    p.add_argument("--out", required=True, help="directory for the report, rollouts, logs and videos")
    p.set_defaults(func=_eval)

    p = sub.add_parser("rerender", help="replay recorded sim episodes through another camera rig (sim only)")
    p.add_argument("--raw", nargs="+", required=True, help="directory of episode .mcap files, or files")
    p.add_argument("--rig", required=True, help="rig preset or YAML to render through")
    p.add_argument("--out", required=True, help="directory for the re-rendered episodes")
    p.add_argument("--size", type=int, help="frame size (default: the recording's)")
    p.set_defaults(func=_rerender)

    p = sub.add_parser("experiment", help="run one of the paper's questions: collect, build, train, evaluate, tabulate")
    p.add_argument("question", help="q1 .. q5 (experiments/<question>.yaml)")
    p.add_argument("--task", default="lift", help="lift, can or square (default lift)")
    p.add_argument(
        "--scale", default="tiny", help="tiny (a 2-core CPU), paper (a GPU) or smoke (experiments/scales.yaml)"
    )
    p.add_argument("--root", default="runs/experiments", help="cache and results directory (default runs/experiments)")
    p.add_argument(
        "--only",
        action="append",
        default=[],
        metavar="AXIS=VALUE",
        help="run only the cells with this value: train=F, space=camera, N=10, eval_views=F,FL, seed=0 "
        "(repeatable; two values of one axis: either)",
    )
    p.add_argument(
        "--seeds",
        metavar="0,1,2",
        help="training seeds per cell, instead of the scale's (tiny: 0; paper: 0,1,2); a cell's stages "
        "with seed 0 are the same whichever list it is in",
    )
    p.add_argument(
        "--table-only",
        action="store_true",
        help="make no stage: write the table and plot from the selected cells already evaluated in the "
        "cache, and list the cells not evaluated yet",
    )
    p.set_defaults(func=_experiment)

    p = sub.add_parser("episode", help="start/stop/discard/status of the recorder's episode (hardware sessions)")
    p.add_argument("action", choices=["start", "stop", "discard", "status"])
    p.add_argument("--connect", default="tcp/127.0.0.1:7447", help="Zenoh router endpoint (default tcp/127.0.0.1:7447)")
    p.add_argument("--id", default=None, help="episode id (start: default <task>-<rig>-<UTC time>)")
    p.add_argument("--task", default="", help="task name recorded with the episode")
    p.add_argument("--rig", default="", help="rig name recorded with the episode")
    p.add_argument("--seed", type=int, default=0, help="scene seed recorded with the episode")
    p.add_argument("--hz", type=float, default=20.0, help="control rate recorded with the episode")
    p.add_argument("--success", action="store_true", help="stop: mark the episode successful")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the recorder")
    p.add_argument(
        "--user",
        default=os.environ.get("VIEWSCALE_BUS__USER"),
        help="authenticate as this Zenoh user, e.g. operator (default $VIEWSCALE_BUS__USER)",
    )
    p.add_argument(
        "--password-file",
        default=os.environ.get("VIEWSCALE_BUS__PASSWORD_FILE"),
        help="the user's password file (default $VIEWSCALE_BUS__PASSWORD_FILE)",
    )
    p.set_defaults(func=_episode)

    p = sub.add_parser("router", help="run a Zenoh router for a multi-host or compose session")
    p.add_argument("--listen", action="append", help="endpoint, repeatable (default tcp/0.0.0.0:7447)")
    p.add_argument("--users", help="user:password file (viewscale credentials); sessions not in it are refused")
    p.add_argument("--acl", help="access control per user, e.g. deploy/zenoh/router-acl.json5 (needs --users)")
    p.set_defaults(func=_router)

    p = sub.add_parser(
        "credentials", help="passwords for an authenticated session: router's users file + one per service"
    )
    p.add_argument("--out", default="deploy/zenoh/secrets", help="folder to write to (default deploy/zenoh/secrets)")
    p.add_argument("--users", help="comma-separated user names (default: the users of deploy/zenoh/router-acl.json5)")
    p.add_argument("--force", action="store_true", help="replace existing credentials (rotates every password)")
    p.set_defaults(func=_credentials)

    p = sub.add_parser(
        "check",
        help="check a rig before a session: cameras open and keep their rate, calibration matches, robot answers",
    )
    p.add_argument("--config", required=True, help="the session's YAML (e.g. deploy/real.yaml)")
    p.add_argument("--seconds", type=float, default=3.0, help="how long to measure each camera (default 3)")
    p.add_argument(
        "--only",
        help="some parts only: cameras, calibration, robot, policy (comma-separated; policy: the server "
        "a policy teleop drives with, checked by default where the session has one)",
    )
    p.add_argument(
        "--max-error-px", type=float, default=1.0, help="largest reprojection error accepted (default 1.0 px)"
    )
    p.add_argument("--max-age-days", type=float, default=30.0, help="oldest calibration accepted (default 30 days)")
    p.add_argument(
        "--set", action="append", default=[], metavar="SERVICE.KEY=VALUE", help="override, e.g. camera.fps=30"
    )
    p.set_defaults(func=_check)

    _add_optional(sub, "services.dataset.cli", "add_dataset_commands")
    _add_optional(sub, "services.trainer.cli", "add_train_command")
    _add_optional(sub, "services.policy.cli", "add_policy_commands")
    _add_optional(sub, "services.calibration.cli", "add_calibrate_command")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = None
    try:  # (from the first import on: a Ctrl-C there was a traceback from pydantic's imports)
        from services.core.runtime import LOG_FORMAT, die_with_parent, remember_interrupts, signalled_while_starting

        remember_interrupts()  # (a library that swallows a Ctrl-C while a command starts does not lose it)
        die_with_parent()  # started by a session or an experiment: do not outlive it
        args = build_parser().parse_args(argv)  # (it imports every command's module: a second or so)
        if signalled_while_starting():
            raise KeyboardInterrupt
        logging.basicConfig(level=getattr(logging, args.log_level), format=LOG_FORMAT)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:  # before a command's own handling (while torch imports): no traceback
        print(f"viewscale{f' {args.command}' if args else ''}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
