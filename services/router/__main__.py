"""A Zenoh router: the hub every service of a session connects to.

python -m services.router --listen tcp/0.0.0.0:7447
python -m services.router --listen tcp/0.0.0.0:7447 \\
    --users deploy/zenoh/secrets/users.txt --acl deploy/zenoh/router-acl.json5

With ``--users`` the router refuses every session that does not authenticate with a user and
password from that file; with ``--acl`` as well, each user may send and receive only what the
file's rules allow (deploy/README.md: generating the credentials, running a session with them).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from pathlib import Path

from services.core.bus import read_users, router
from services.core.cli_args import log_level_arg
from services.core.config import ConfigError
from services.core.runtime import announce_ready, configure_logging, die_with_parent, stop_on_signals, wait_for_stop


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m services.router",
        description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n".join(__doc__.splitlines()[2:]),
    )
    parser.add_argument(
        "--listen", action="append", default=None, help="endpoint (repeatable), default tcp/0.0.0.0:7447"
    )
    parser.add_argument("--users", type=Path, help="user:password file; sessions not in it are refused")
    parser.add_argument("--acl", type=Path, help="zenoh JSON5 access control, per user (needs --users)")
    parser.add_argument(
        "--log-level", default="INFO", type=log_level_arg, help="DEBUG, INFO, WARNING, ERROR or CRITICAL"
    )
    args = parser.parse_args(argv)
    if args.acl is not None and args.users is None:
        parser.error("--acl needs --users: its rules name users that must authenticate")
    die_with_parent()
    configure_logging(args.log_level)
    log = logging.getLogger("router")
    listen = args.listen or ["tcp/0.0.0.0:7447"]
    try:
        hub = router(listen, acl_file=args.acl, users_file=args.users)
    except (ConfigError, ConnectionError) as exc:  # a missing or bad users/ACL file, a port in use
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    stop_on_signals(stop)
    with hub:
        if args.users is not None:
            users = read_users(args.users)
            log.info("authentication on: %d users (%s)", len(users), ", ".join(users))
            log.info("access control: %s", args.acl or "none (every authenticated user may do anything)")
        announce_ready("router", ",".join(listen))
        wait_for_stop(stop)
    log.info("stopped")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
