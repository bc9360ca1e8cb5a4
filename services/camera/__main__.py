"""python -m services.camera [--config deploy/sim.yaml] [--set key=value ...]"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # the sim driver renders headless

from services.camera.config import CameraConfig  # noqa: E402
from services.camera.service import main  # noqa: E402
from services.core.cli_args import service_main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(service_main("camera", CameraConfig, main))
