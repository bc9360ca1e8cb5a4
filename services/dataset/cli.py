"""``viewscale dataset build`` and ``viewscale dataset info``.

    viewscale dataset build --raw data/raw --views F,FL,FR,FU,FD --space camera --out data/ds
    viewscale dataset info data/ds

Progress goes to stderr, one line per episode; the summary to stdout. A user's mistake (a
missing or corrupt file, an unknown view, an empty selection) is one ``error:`` line, exit 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from services.core.action_spaces import SPACES, STATE_FRAMES
from services.core.rig import CALIBRATION_MAX_AGE_DAYS
from services.core.runtime import OutputError, exclusive, interrupt_on_signals, output_dir
from services.dataset.build import BuildParams, build_dataset, find_episodes
from services.dataset.episodes import EpisodeError
from services.dataset.store import CONTACT_SHEET, DatasetError, DatasetStore
from services.dataset.summary import format_summary


def _size(text: str) -> tuple[int, int]:
    try:
        if "x" in text.lower():
            w, h = text.lower().split("x")
            return int(w), int(h)
        return int(text), int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"image size must look like 84 or 128x96, not {text!r}") from None


def _views(text: str) -> tuple[str, ...]:
    return tuple(v.strip() for v in text.split(",") if v.strip())


def _err(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return 2


def _build(args: argparse.Namespace) -> int:
    def progress(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    try:
        params = BuildParams(
            views=_views(args.views),
            space=args.space,
            state_frame=args.state_frame,
            image_size=args.image_size,
            max_frame_age_ms=args.max_frame_age_ms,
            drop_stale_actions=args.drop_stale_actions,
            To=args.To,
            Tp=args.Tp,
            Ta=args.Ta,
            pad_actions=args.pad_actions,
            val_fraction=args.val_fraction,
            split_seed=args.split_seed,
            rig=args.rig,
            max_calibration_age_days=args.max_calibration_age_days,
        )
        if args.jobs < 1:
            raise DatasetError(f"--jobs must be at least 1, got {args.jobs}")
        if args.contact_episodes < 0:
            raise DatasetError(f"--contact-episodes must be 0 or more, got {args.contact_episodes}")
        # a wrong --raw: no empty --out left behind (the same episode ids in two evaluations' rollouts,
        # which the build leaves out, are no clash)
        episodes = find_episodes([Path(p) for p in args.raw], unique=False)
        # SIGTERM and SIGHUP (a scheduler, a closed terminal) stop it as Ctrl-C does: the episodes
        # built so far stay, and the same command builds the rest (before: killed with no word)
        interrupt_on_signals()
        # made before an hour of decoding, not after; taken back if the build fails before writing
        with output_dir(args.out, "--out"), exclusive(args.out, "dataset build"):
            result = build_dataset(
                episodes,  # (the files found: the folders are not walked again)
                Path(args.out),
                params,
                progress=progress,
                skip_bad=args.skip_bad,
                force=args.force,
                contact_episodes=args.contact_episodes,
                jobs=args.jobs,
                include_failed=args.include_failed,
                include_rollouts=args.include_rollouts,
            )
    except KeyboardInterrupt as exc:
        print(
            f"interrupted ({exc or 'SIGINT'}): the episodes built so far are kept in {args.out}; run the same command "
            "to build the rest",
            file=sys.stderr,
        )
        return 130
    except EpisodeError as exc:  # one episode that cannot be built stops the build: say how to go on
        many = len(episodes) > 1 and not args.skip_bad
        return _err(str(exc) + ("; --skip-bad builds the other episodes and lists this one" if many else ""))
    except (DatasetError, OutputError) as exc:
        return _err(str(exc))
    except OSError as exc:  # an unwritable output, a full disk
        if exc.errno is None:  # numpy's short write ('677376 requested and 655232 written'): say what it means
            return _err(f"cannot write {args.out}: {exc} (is the disk full?)")
        return _err(f"{exc.strerror or exc}: {exc.filename or args.out}")
    s = result.summary
    if args.json:
        print(json.dumps(s))
        return 0
    print(format_summary(s, result.out))
    if result.up_to_date:
        print("  (up to date: nothing rebuilt)")
    else:
        print(
            f"  built {result.built} episodes, reused {result.reused}, {result.frames} frames decoded "
            f"in {result.seconds:.1f} s"
        )
    if args.contact_episodes > 0:
        print(f"  contact sheet {result.out / CONTACT_SHEET}")
    return 0


def _info(args: argparse.Namespace) -> int:
    try:
        store = DatasetStore(args.path)
    except DatasetError as exc:
        return _err(str(exc))
    if args.json:
        print(json.dumps(store.summary))
        return 0
    print(format_summary(store.summary, store.path))
    print(f"  built at      {store.manifest.get('built_at', '?')} from {len(store.manifest['sources'])} files")
    sheet = store.path / CONTACT_SHEET
    if sheet.is_file():
        print(f"  contact sheet {sheet}")
    return 0


def add_dataset_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register ``dataset build`` and ``dataset info`` on the top-level ``viewscale`` parser."""
    p = subparsers.add_parser("dataset", help="build and inspect pseudo-demonstration datasets")
    sub = p.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")

    b = sub.add_parser("build", help="recorded episodes -> one pseudo-demo per camera view, as a training cache")
    b.add_argument("--raw", nargs="+", default=["data/raw"], help="directory of episode .mcap files, or files")
    b.add_argument("--views", required=True, help="comma-separated camera names, e.g. F,FL,FR,FU,FD")
    b.add_argument("--space", default="camera", choices=SPACES, help="action space (default camera)")
    b.add_argument(
        "--state-frame",
        default="auto",
        choices=STATE_FRAMES,
        help="frame of the robot state input; auto follows the action space (default)",
    )
    b.add_argument("--out", default="data/ds", help="dataset directory (default data/ds)")
    b.add_argument(
        "--image-size", type=_size, default=(84, 84), metavar="WxH", help="cached frame size, 84 or WxH (default 84x84)"
    )
    b.add_argument(
        "--max-frame-age-ms",
        type=float,
        default=None,
        help="a frame older than this at its tick is stale (default per camera: its median age at a "
        "tick plus half its frame interval; half a period in sim)",
    )
    b.add_argument(
        "--drop-stale-actions",
        action="store_true",
        help="also drop ticks where the robot held still for want of a command (kept by default)",
    )
    b.add_argument("--To", type=int, default=2, help="observation horizon (default 2)")
    b.add_argument("--Tp", type=int, default=16, help="prediction horizon (default 16)")
    b.add_argument("--Ta", type=int, default=8, help="executed action steps, sets end padding (default 8)")
    b.add_argument(
        "--pad-actions",
        default="edge",
        choices=("edge", "hold"),
        help="edge: repeat the edge action (diffusion_policy, default); hold: zero motion",
    )
    b.add_argument(
        "--val-fraction",
        type=float,
        default=0.1,
        help="share of episodes held out for validation; the normaliser never sees them (default 0.1)",
    )
    b.add_argument("--split-seed", type=int, default=0, help="seeds which episodes are held out (default 0)")
    b.add_argument(
        "--rig",
        default=None,
        help="calibrated rig file to check camera-space episodes against (default: the rig each episode names); "
        "an episode whose recorded calibration differs from it, or is older than --max-calibration-age-days, "
        "is refused",
    )
    b.add_argument(
        "--max-calibration-age-days",
        type=float,
        default=CALIBRATION_MAX_AGE_DAYS,
        help=f"a calibration made longer than this before an episode is stale (default {CALIBRATION_MAX_AGE_DAYS:g})",
    )
    b.add_argument(
        "--include-failed",
        action="store_true",
        help="also build the episodes not marked successful (stopped as a failure, an evaluation's failed "
        "rollouts, recovered after a crash); left out by default, and listed",
    )
    b.add_argument(
        "--include-rollouts",
        action="store_true",
        help="also build the episodes a policy drove (its commands' source is 'policy': evaluation and "
        "deployment rollouts, successful ones too); left out by default, and listed",
    )
    b.add_argument("--skip-bad", action="store_true", help="skip unreadable episodes instead of stopping")
    b.add_argument("--force", action="store_true", help="rebuild every episode even if nothing changed")
    b.add_argument(
        "--jobs",
        type=int,
        default=min(8, os.cpu_count() or 1),
        help="episodes decoded at once (default: CPU cores, at most 8)",
    )
    b.add_argument("--contact-episodes", type=int, default=3, help="episodes on the contact sheet (0: none)")
    b.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    b.set_defaults(func=_build)

    i = sub.add_parser("info", help="print a dataset's summary")
    i.add_argument("path", help="dataset directory")
    i.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    i.set_defaults(func=_info)
