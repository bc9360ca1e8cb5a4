"""python -m services.session [--config deploy/sim.yaml] [--set episodes=10 ...]"""

from services.core.cli_args import service_main
from services.session.config import SessionConfig
from services.session.session import main

if __name__ == "__main__":
    raise SystemExit(service_main("session", SessionConfig, main))
