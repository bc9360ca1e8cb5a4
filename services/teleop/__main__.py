"""python -m services.teleop [--config deploy/sim.yaml] [--set key=value ...]"""

from services.core.cli_args import service_main
from services.teleop.config import TeleopConfig
from services.teleop.service import main

if __name__ == "__main__":
    raise SystemExit(service_main("teleop", TeleopConfig, main))
