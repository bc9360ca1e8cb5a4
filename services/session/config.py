from __future__ import annotations

from pydantic import Field

from services.core.bus import BusConfig
from services.core.config import Frozen, LogLevel

DEFAULT_MAX_TICKS = {"lift": 150, "can": 300, "square": 400}  # the sim tasks' horizons
# Evaluation seeds: fixed per task, so every row of a table starts from the same scenes, and
# disjoint from every training seed (collection refuses seeds from EVAL_SEED_FLOOR on).
EVAL_SEED_FLOOR = 100_000
EVAL_SEEDS = {"lift": 100_000, "can": 200_000, "square": 300_000}


class SessionConfig(Frozen):
    bus: BusConfig = BusConfig()  # how to reach the session's Zenoh network
    task: str = "lift"  # task of every episode
    rig: str = "five15"  # rig name recorded with each episode (the sim's rig)
    episodes: int = Field(10, ge=1)  # successful episodes to record (evaluation: episodes to run)
    seed: int = Field(0, ge=0)  # first seed; each attempt takes the next one
    evaluation: bool = False  # record every attempt, successful or not, never retry; ids without a clock
    max_attempts: int | None = Field(None, ge=1)  # give up after this many attempts (default 3 x episodes)
    max_ticks: int | None = Field(None, ge=1)  # per-episode tick limit (default per task)
    settle_ticks: int = Field(3, ge=0)  # ticks still recorded after success, so demos end at rest
    warmup_ticks: int = Field(10, ge=0)  # unrecorded ticks before the first episode (first renders, routes)
    control_hz: float = Field(20.0, gt=0)  # the sim's control rate (recorded; used for time limits)
    services: list[str] = Field(default_factory=lambda: ["sim", "teleop", "recorder"])  # must be alive
    wait_services_s: float = Field(120.0, gt=0)  # how long to wait for them at start-up
    log_level: LogLevel = "INFO"  # logging level of the process

    def tick_limit(self) -> int:
        return self.max_ticks or DEFAULT_MAX_TICKS.get(self.task, 400)
