"""Process plumbing shared by every service: logging, signals, the ready line."""

from __future__ import annotations

import logging
import signal
import sys
import threading


def configure_logging(level: str = "INFO") -> None:
    """Called once from a service's main (never at import time)."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def stop_on_signals(stop: threading.Event) -> None:
    """SIGTERM and SIGINT set ``stop`` so the service can close its files cleanly."""

    def handler(signum, _frame):
        logging.getLogger("runtime").info("received %s, stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def announce_ready(service: str, address: str) -> None:
    """Print the one line tests and compose wait on: ``ready <service> <address>``."""
    print(f"ready {service} {address}", flush=True)
    logging.getLogger(service).info("ready at %s", address)


def serve(name: str, bus_config, build, address: str) -> int:
    """The body of every service's ``main``: open the bus, build the service (a context manager
    taking the bus), print the ready line, run until SIGTERM/SIGINT, close everything."""
    from services.core.bus import Bus  # here, not at import: runtime stays free of zenoh

    stop = threading.Event()
    stop_on_signals(stop)
    with Bus(bus_config) as bus, build(bus) as service:
        announce_ready(name, address)
        service.run(stop)
    return 0
