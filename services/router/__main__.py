"""A Zenoh router: the hub every service of a session connects to.

python -m services.router --listen tcp/0.0.0.0:7447
"""

from __future__ import annotations

import argparse
import logging
import threading

from services.core.bus import router
from services.core.runtime import announce_ready, configure_logging, die_with_parent, stop_on_signals


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.router", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--listen", action="append", default=None, help="endpoint (repeatable), default tcp/0.0.0.0:7447"
    )
    parser.add_argument("--log-level", default="INFO")
    args = parser.parse_args(argv)
    die_with_parent()
    configure_logging(args.log_level)
    listen = args.listen or ["tcp/0.0.0.0:7447"]
    stop = threading.Event()
    stop_on_signals(stop)
    with router(listen):
        announce_ready("router", ",".join(listen))
        stop.wait()
    logging.getLogger("router").info("stopped")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
