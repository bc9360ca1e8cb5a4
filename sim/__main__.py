"""python -m sim [--config deploy/sim.yaml] [--set key=value ...]"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: headless rendering

from services.core.cli_args import service_main  # noqa: E402
from sim.config import SimConfig  # noqa: E402
from sim.service import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(service_main("sim", SimConfig, main, module="sim"))
