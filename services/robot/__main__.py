"""python -m services.robot [--config deploy/real.yaml] [--set key=value ...]"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # the sim driver loads MuJoCo headless

from services.core.cli_args import service_main  # noqa: E402
from services.robot.config import RobotConfig  # noqa: E402
from services.robot.service import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(service_main("robot", RobotConfig, main))
