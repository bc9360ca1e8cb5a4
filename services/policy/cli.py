"""``viewscale serve`` and ``viewscale worker`` (also ``python -m services.policy serve|worker``).

    viewscale serve --checkpoint runs/lift --listen 127.0.0.1:50051 --views F,FL,FR --workers 3
    viewscale serve --checkpoint runs/lift --worker 10.0.0.5:7001 --worker 10.0.0.6:7001 --placement spread
    viewscale serve --checkpoint runs/lift --worker dns:///policy-worker:7001   # every replica, round-robin
    viewscale worker --checkpoint runs/lift --listen 0.0.0.0:7001

Settings: defaults < --config YAML (section ``policy`` / ``worker``) < VIEWSCALE_<FIELD> env < the
flags below < --set key=value. The token is best given as VIEWSCALE_TOKEN (a flag shows in ps).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import sys

from services.policy.config import PLACEMENTS, PRECISIONS  # pydantic only, as the CLI's --log-level check


def _load(model, args: argparse.Namespace, flags: list[str], section: str):
    """The config from --config, env, the flags given and --set; None (after one error line) if invalid.

    Imports stay inside the commands: `viewscale collect` must not pay for torch."""
    from services.core.config import ConfigError, load_config
    from services.core.runtime import configure_logging

    overrides = []
    for name in flags:
        value = getattr(args, name, None)
        if value is None or value is False or value == []:
            continue
        if isinstance(value, list):  # each item quoted: an address may hold commas (ipv4:A:P,B:P)
            value = json.dumps([str(v) for v in value])
        overrides.append(f"{name}={value}")
    try:
        cfg = load_config(model, args.config, [*overrides, *args.set], section=section)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    configure_logging(cfg.log_level)
    return cfg


def _empty_token(args: argparse.Namespace) -> str | None:
    """Why the token given is empty, or None. An empty value reads as no value, so an unset
    variable (VIEWSCALE_TOKEN=$TOKEN with TOKEN unset) would turn the token check off in silence."""
    import os

    if "VIEWSCALE_TOKEN" in os.environ and not os.environ["VIEWSCALE_TOKEN"].strip():
        return "VIEWSCALE_TOKEN is set but empty (an unset variable?): give the token, or unset it for none"
    for item in args.set:
        key, _, value = item.partition("=")
        if key.strip() == "token" and not value.strip():
            return f"--set {item}: the token is empty; give one, or leave it out for none"
    return None


def _run(coro_factory) -> int:
    from services.core.runtime import die_with_parent, signalled_while_starting

    die_with_parent()  # a server's workers (and a session's server) go when their parent goes
    if signalled_while_starting():  # (a Ctrl-C that torch's imports swallowed: see remember_interrupts)
        raise KeyboardInterrupt
    stop = asyncio.Event()

    async def main() -> int:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            loop.add_signal_handler(sig, stop.set)
        return await coro_factory(stop)

    return asyncio.run(main())


def _announce(line: str) -> None:
    print(line, flush=True)


def _error(exc: Exception, code: int = 2) -> int:
    print(f"error: {exc}", file=sys.stderr)
    return code


def _bad_listen(address: str) -> str | None:
    """A listen address no run could bind (a bad argument: exit 2); a port another process holds
    is ``_unbindable``'s (exit 1: the same command works once it is free)."""
    from services.policy.transport import unlistenable

    why = unlistenable(address)
    return f"cannot listen on {address}: {why}" if why else None


def _unbindable(address: str) -> str | None:
    """Why a bind to the listen address fails now (a port another process holds, an address of no
    interface here): exit 1, said before the model loads and any worker starts, not seconds later
    (the server binds again when it starts, for a port taken in between)."""
    from services.policy.transport import bind_problem

    why = bind_problem(address)
    return f"cannot listen on {address}: {why}" if why else None


def _serve(args: argparse.Namespace) -> int:
    from services.policy.config import ServerConfig

    if args.views is not None:
        args.views = [v.strip() for v in args.views.split(",") if v.strip()]
        if not args.views:
            return _error("--views names no camera (leave it out for the training views)")
    if why := _empty_token(args):
        return _error(why)
    flags = ["checkpoint", "listen", "views", "workers", "worker", "in_process", "placement", "device", "threads"]
    flags += ["precision", "rig", "task"]
    cfg = _load(ServerConfig, args, flags, "policy")
    if cfg is None:
        return 2
    if why := _bad_listen(cfg.listen):  # (found before the workers start, not after)
        return _error(why)
    if why := _unbindable(cfg.listen):
        return _error(why, 1)
    if cfg.in_process and (cfg.workers or cfg.worker):  # (a config file's workers, --in-process to debug)
        unused = [f"{cfg.workers} local workers"] if cfg.workers else []
        unused += [f"worker {a}" for a in cfg.worker]
        print(f"warning: --in-process computes every view here; not used: {', '.join(unused)}", file=sys.stderr)
    from services.policy.checkpoint import CheckpointError, check_weights, inference_device, resolve_checkpoint
    from services.policy.server import LocalWorkers, load_spec, serve_policy
    from services.policy.transport import ListenError

    try:
        # A run's latest checkpoint, resolved once: the one the server describes, computes with and
        # starts its local workers on (a run still training moves its latest on; before, a local
        # worker restarted later loaded the newer one and the server's answers went without it)
        cfg = cfg.model_copy(update={"checkpoint": str(resolve_checkpoint(cfg.checkpoint))})
        load_spec(cfg)  # a bad checkpoint, view or device is one line, before any process starts
        here = cfg.in_process or not (cfg.workers or cfg.worker)  # this process computes
        if here or cfg.workers:  # (the device is that of the in-process model and of local workers)
            # bf16 support only where this process computes: asking creates a CUDA context (local
            # workers ask for themselves, and say so in their logs)
            inference_device(cfg.device, cfg.precision if here else "fp32")
    except (CheckpointError, ValueError, OSError) as exc:
        return _error(exc)
    try:
        # weights cut short, said now (exit 1, as when they are loaded): before, local workers were
        # started, failed to load them and were restarted until worker_ready_s ran out (120 s)
        check_weights(cfg.checkpoint)
    except CheckpointError as exc:
        return _error(exc, 1)
    from services.core.runtime import OutputError, reading, writable_dir

    try:
        log_dir = writable_dir(args.log_dir, "--log-dir") if args.log_dir else None
    except OutputError as exc:
        return _error(exc)
    try:
        # held while it serves: the run's training keeps it (a worker started again loads it again)
        with (
            reading(cfg.checkpoint, "policy server"),
            LocalWorkers(cfg, cfg.workers if not cfg.in_process else 0, log_dir) as local,
        ):
            addresses = [*cfg.worker, *local.addresses]

            async def serve(stop):
                supervisor = asyncio.create_task(local.supervise(stop))  # a local worker that exits: restarted
                try:
                    rc = await serve_policy(cfg, stop, addresses, _announce)
                finally:
                    supervisor.cancel()
                if local.failed:  # (it stopped the server)
                    raise RuntimeError(local.failed)
                return rc

            return _run(serve)
    except (RuntimeError, TimeoutError, CheckpointError, ListenError, OutputError) as exc:  # (weights, port taken)
        return _error(exc, 1)


def _worker(args: argparse.Namespace) -> int:
    from services.policy.config import WorkerConfig

    if why := _empty_token(args):
        return _error(why)
    cfg = _load(WorkerConfig, args, ["checkpoint", "listen", "device", "threads", "precision"], "worker")
    if cfg is None:
        return 2
    if why := _bad_listen(cfg.listen):
        return _error(why)
    if why := _unbindable(cfg.listen):
        return _error(why, 1)
    from services.core.runtime import OutputError, reading
    from services.policy.checkpoint import (
        CheckpointError,
        inference_device,
        model_config,
        read_info,
        resolve_checkpoint,
    )
    from services.policy.transport import ListenError
    from services.policy.worker import serve_worker

    try:
        cfg = cfg.model_copy(update={"checkpoint": str(resolve_checkpoint(cfg.checkpoint))})  # (as serve's)
        model_config(read_info(cfg.checkpoint), cfg.checkpoint)
        inference_device(cfg.device, cfg.precision)  # before it listens: a one-line error, not a traceback
    except (CheckpointError, ValueError, OSError) as exc:
        return _error(exc)
    try:
        with reading(cfg.checkpoint, "policy worker"):  # kept by its run's training while it serves
            return _run(lambda stop: serve_worker(cfg, stop, _announce))
    except (CheckpointError, ListenError, OutputError) as exc:  # its port taken; the weights, read once it listens
        return _error(exc, 1)


def add_policy_commands(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "serve",
        help="serve a trained policy over gRPC (GetAction), composing camera views",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--checkpoint", help="checkpoint folder or run directory (its latest checkpoint)")
    p.add_argument("--listen", help="host:port to serve on (default 127.0.0.1:50051; port 0: any free one)")
    p.add_argument("--views", help="cameras composed by default, e.g. F,FL,FR (default: the training views)")
    p.add_argument("--workers", type=int, help="local worker processes to start (default 0: in-process)")
    p.add_argument(
        "--worker",
        action="append",
        default=[],
        metavar="ADDR",
        help="a running worker: host:port, or dns:///name:port / ipv4:A:P,B:P for every replica (repeatable)",
    )
    p.add_argument("--in-process", action="store_true", help="compute every view in this process")
    p.add_argument(
        "--placement",
        choices=PLACEMENTS,
        help="a request's views on workers: all on one (pack), one each (spread), "
        "or auto: one per GPU and per machine (or set of cores), packed where workers share cores or a GPU (default)",
    )
    p.add_argument("--device", help="cpu, cuda or cuda:N (default cpu)")
    p.add_argument("--threads", type=int, help="intra-op threads per model (default 1)")
    p.add_argument(
        "--precision",
        choices=PRECISIONS,
        help="bf16: the model's passes under bfloat16 autocast, in-process and in local workers; "
        "remote workers must run with the same (default fp32)",
    )
    p.add_argument(
        "--rig",
        help="rig preset or YAML: cameras the checkpoint was not trained on, or recalibrated since "
        "(its cameras take the place of the checkpoint's of the same name)",
    )
    p.add_argument("--task", help="with --rig: the task whose framing a sim rig takes (default: the checkpoint's)")
    p.add_argument("--log-dir", help="write local workers' logs here")
    p.add_argument("--config", help="YAML with a `policy` section")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any setting: token=..., tls.cert=..., request_timeout_s=2 (repeatable)",
    )
    p.set_defaults(func=_serve)

    w = subparsers.add_parser(
        "worker",
        help="a denoising worker for `viewscale serve --worker ADDR`",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    w.add_argument("--checkpoint", help="checkpoint folder or run directory (the server's)")
    w.add_argument("--listen", help="host:port (default 127.0.0.1:0)")
    w.add_argument("--device", help="cpu, cuda or cuda:N (default cpu)")
    w.add_argument("--threads", type=int, help="intra-op threads (default 1)")
    w.add_argument(
        "--precision",
        choices=PRECISIONS,
        help="bf16: passes under bfloat16 autocast, as the server's --precision (default fp32)",
    )
    w.add_argument("--config", help="YAML with a `worker` section")
    w.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override any setting")
    w.set_defaults(func=_worker)
