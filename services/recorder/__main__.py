"""python -m services.recorder [--config deploy/sim.yaml] [--set key=value ...]"""

from __future__ import annotations

import argparse
import sys

from services.core.config import ConfigError, load_config
from services.core.runtime import configure_logging
from services.recorder.config import RecorderConfig
from services.recorder.service import main


def cli(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.recorder", description="Record episodes to MCAP.")
    parser.add_argument("--config", help="YAML file with a 'recorder' section (e.g. deploy/sim.yaml)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a setting, dotted for nested ones (repeatable)")
    args = parser.parse_args(argv)
    try:
        cfg = load_config(RecorderConfig, args.config, args.overrides, section="recorder")
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    configure_logging(cfg.log_level)
    return main(cfg)


if __name__ == "__main__":
    raise SystemExit(cli())
