"""Recorder settings (YAML section ``recorder``; the top-level ``bus`` section is shared)."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from services.core.bus import BusConfig
from services.core.config import Frozen, LogLevel


class RecorderConfig(Frozen):
    bus: BusConfig = BusConfig()  # zenoh session the recorder subscribes on
    out_dir: Path = Path("data/raw")  # one <episode_id>.mcap per episode goes here
    queue_size: int = Field(256, ge=1)  # per-channel bound; samples beyond it are dropped and counted
    chunk_size: int = Field(1 << 20, ge=1024)  # uncompressed bytes per MCAP chunk: the most a kill -9 loses
    flush_interval_s: float = Field(1.0, gt=0)  # also cut a chunk after this long, bounding loss on slow topics
    min_rate_fraction: float = Field(0.9, ge=0, le=1)  # flag episodes whose robot-state rate < this x control_hz
    stop_grace_s: float = Field(2.0, ge=0)  # STOP waits up to this long for the ticks the source published
    max_episode_ticks: int = Field(360_000, ge=1)  # a STOP claiming more ticks is refused (5 h at 20 Hz)
    decode_images: bool = True  # fully decode every JPEG to validate it (else check its markers only)
    log_level: LogLevel = "INFO"  # logging level of the process
