"""python -m services.recorder [--config deploy/sim.yaml] [--set key=value ...]"""

from services.core.cli_args import service_main
from services.recorder.config import RecorderConfig
from services.recorder.service import main

if __name__ == "__main__":
    raise SystemExit(service_main("recorder", RecorderConfig, main))
