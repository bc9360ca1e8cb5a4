"""The thin ``__main__`` every service shares: parse --config/--set, configure logging, run."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import TypeVar

from services.core.config import ConfigError, load_config, log_level_name
from services.core.runtime import OutputError, configure_logging

C = TypeVar("C")


def log_level_arg(value: str) -> str:
    """argparse ``type`` of a ``--log-level`` flag: a level name in any case, or a usage error."""
    try:
        return log_level_name(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def service_overrides(items: list[str], services: tuple[str, ...]) -> dict[str, list[str]]:
    """``--set SERVICE.KEY=VALUE`` items of a command that reads several services' sections of a
    session file, by service; ValueError for an item that names none of ``services``."""
    out: dict[str, list[str]] = {}
    for item in items:
        service, _, rest = item.partition(".")
        if service not in services or not rest:
            raise ValueError(f"--set {item!r} must look like {' or '.join(f'{s}.KEY=VALUE' for s in services)}")
        out.setdefault(service, []).append(rest)
    return out


def service_main(
    name: str, model: type[C], main: Callable[[C], int], module: str | None = None, argv: list[str] | None = None
) -> int:
    """``name`` is the service and its YAML section; ``module`` what ``python -m`` runs."""
    parser = argparse.ArgumentParser(
        prog=f"python -m {module or 'services.' + name}",
        description=f"Run the {name} service. Settings: defaults < --config YAML section '{name}' "
        "< VIEWSCALE_<FIELD>=value < --set field=value.",
    )
    parser.add_argument("--config", help="YAML file with a section per service (e.g. deploy/sim.yaml)")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field, dotted for nested ones (repeatable)",
    )
    args = parser.parse_args(argv)
    try:
        cfg = load_config(model, args.config, args.overrides, section=name)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    configure_logging(getattr(cfg, "log_level", "INFO"))
    try:
        return main(cfg)
    # a driver that cannot be built, a router not there, an output folder in use or not writable
    except (ConfigError, ConnectionError, OutputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
