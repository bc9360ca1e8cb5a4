"""python -m services.trainer [--config deploy/sim.yaml] [--set jobs_dir=jobs] [--set key=value ...]

Runs the training service (see services/trainer/service.py). To train once from a shell, use
``viewscale train`` instead.
"""

from services.core.cli_args import service_main
from services.trainer.config import TrainerServiceConfig
from services.trainer.service import main

if __name__ == "__main__":
    raise SystemExit(service_main("trainer", TrainerServiceConfig, main, module="services.trainer"))
