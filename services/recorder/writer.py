"""One episode's MCAP file: protobuf schemas embedded, zstd chunks, handed to the OS chunk by chunk.

Layout of ``<episode_id>.mcap`` (written as ``<episode_id>.mcap.part``, renamed on close):
- a metadata record ``episode_start`` right after the header (episode_id, task, seed, rig,
  control_hz, start_ns), so even a file cut short says what it was;
- one channel per topic, ``/`` + key, message encoding ``protobuf`` with the schema's
  FileDescriptorSet embedded; ``publish_time`` = capture time, ``log_time`` = receive time,
  ``sequence`` = index of the message in its channel (0, 1, 2, ...);
- at close, the final ``EpisodeMeta`` on ``/recorder/episode`` and the same facts as a metadata
  record ``episode`` (string map; maps and lists as JSON).

Crash bound: messages collect in the open chunk until it holds ``chunk_size`` uncompressed bytes
or ``flush_interval_s`` has passed; then the chunk is compressed and written through to the OS
(no fsync: a killed process loses nothing the kernel has). A kill -9 therefore loses at most the
open chunk, i.e. min(chunk_size bytes, flush_interval_s) of messages, plus what was still queued
in memory; ``recover`` reads back everything before it.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO

from google.protobuf.message import Message
from mcap.well_known import MessageEncoding
from mcap.writer import LIBRARY_IDENTIFIER as MCAP_LIBRARY
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

from services.core.topics import EPISODE
from services.pb.episode_pb2 import EpisodeMeta

PART_SUFFIX = ".part"
EPISODE_CHANNEL = EPISODE.mcap_topic  # "/recorder/episode"
START_RECORD = "episode_start"
EPISODE_RECORD = "episode"
LIBRARY = f"viewscale-recorder {MCAP_LIBRARY}"

_EPISODE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def check_episode_id(episode_id: str) -> None:
    """Episode ids become file names: letters, digits, ``._-``, no path separators."""
    if not _EPISODE_ID.match(episode_id) or episode_id.endswith(PART_SUFFIX):
        raise ValueError(f"invalid episode id {episode_id!r}: use 1-128 of [A-Za-z0-9._-], starting alphanumeric")


def episode_path(out_dir: Path, episode_id: str) -> Path:
    check_episode_id(episode_id)
    return Path(out_dir) / f"{episode_id}.mcap"


# -- metadata records -------------------------------------------------------------------------
_MAP_FIELDS = ("frames", "drops", "malformed", "gaps", "malformed_reasons")


def meta_to_record(meta: EpisodeMeta) -> dict[str, str]:
    """EpisodeMeta -> the string map of the ``episode`` metadata record."""
    record = {
        "episode_id": meta.episode_id,
        "task": meta.task,
        "seed": str(meta.seed),
        "rig": meta.rig,
        "success": "true" if meta.success else "false",
        "control_hz": repr(float(meta.control_hz)),
        "lockstep": "true" if meta.lockstep else "false",
        "achieved_hz": repr(float(meta.achieved_hz)),
        "ticks": str(meta.ticks),
        "stale_ticks": str(meta.stale_ticks),
        "clipped_ticks": str(meta.clipped_ticks),
        "flags": json.dumps(list(meta.flags)),
        "start_ns": str(meta.start_ns),
        "end_ns": str(meta.end_ns),
    }
    for name in _MAP_FIELDS:
        record[name] = json.dumps(dict(sorted(getattr(meta, name).items())))
    if meta.rerendered_from:  # only re-rendered episodes carry it
        record["rerendered_from"] = meta.rerendered_from
    if meta.command_sources:  # (recordings before 2026-12-05 have none)
        record["command_sources"] = json.dumps(list(meta.command_sources))
    return record


def record_to_dict(record: Mapping[str, str]) -> dict:
    """The ``episode`` string map with typed values (ints, floats, bool, dicts, list)."""
    out: dict = dict(record)
    for key in ("seed", "ticks", "stale_ticks", "clipped_ticks", "start_ns", "end_ns"):
        if key in out:
            out[key] = int(out[key])
    for key in ("control_hz", "achieved_hz"):
        if key in out:
            out[key] = float(out[key])
    for key in ("success", "lockstep"):
        if key in out:
            out[key] = out[key] == "true"
    for key in (*_MAP_FIELDS, "flags", "command_sources"):
        if key in out:
            out[key] = json.loads(out[key])
    return out


def start_record(meta: EpisodeMeta) -> dict[str, str]:
    return {
        "episode_id": meta.episode_id,
        "task": meta.task,
        "seed": str(meta.seed),
        "rig": meta.rig,
        "control_hz": repr(float(meta.control_hz)),
        "lockstep": "true" if meta.lockstep else "false",
        "start_ns": str(meta.start_ns),
    }


def meta_from_start_record(record: Mapping[str, str]) -> EpisodeMeta:
    return EpisodeMeta(
        episode_id=record.get("episode_id", ""),
        task=record.get("task", ""),
        seed=int(record.get("seed", "0")),
        rig=record.get("rig", ""),
        control_hz=float(record.get("control_hz", "0")),
        lockstep=record.get("lockstep") == "true",
        start_ns=int(record.get("start_ns", "0")),
    )


# -- the file ---------------------------------------------------------------------------------
class EpisodeWriter:
    """Appends protobuf messages to ``<path>.part``; ``close`` renames it to ``path``."""

    def __init__(self, path: Path, chunk_size: int = 1 << 20, flush_interval_s: float = 1.0):
        self.path = Path(path)
        self.part_path = self.path.with_name(self.path.name + PART_SUFFIX)
        self.flush_interval_s = flush_interval_s
        self._file: IO[bytes] = open(self.part_path, "xb")  # never clobber another episode's file
        # Chunks are cut here, not by the mcap writer: its own limit sits far above ours.
        self._mcap = McapWriter(self._file, chunk_size=1 << 62, compression=CompressionType.ZSTD)
        self.chunk_size = chunk_size
        self._mcap.start(profile="", library=LIBRARY)
        self._file.flush()
        self._schemas: dict[str, int] = {}  # message full name -> schema id
        self._channels: dict[str, int] = {}  # mcap topic -> channel id
        self._types: dict[str, str] = {}  # mcap topic -> message full name
        self._seq: dict[str, int] = {}  # mcap topic -> next sequence
        self._on_disk = self._file.tell()
        self._last_flush = time.monotonic()
        self._open: list[tuple[int, int, int, bytes, int, int]] = []  # the open chunk: (log, order, channel, ...)
        self._open_bytes = 0
        self.messages = 0
        self.closed = False

    # Channels and schemas are registered on first use, so the file holds only what it carries.
    def _channel(self, topic: str, msg_type: type[Message]) -> int:
        channel_id = self._channels.get(topic)
        name = msg_type.DESCRIPTOR.full_name
        if channel_id is not None:
            if self._types[topic] != name:
                raise ValueError(f"channel {topic} holds {self._types[topic]}, not {name}")
            return channel_id
        schema_id = self._schemas.get(name)
        if schema_id is None:
            fds = build_file_descriptor_set(msg_type)
            schema_id = self._mcap.register_schema(name=name, encoding="protobuf", data=fds.SerializeToString())
            self._schemas[name] = schema_id
        channel_id = self._mcap.register_channel(
            topic=topic, message_encoding=MessageEncoding.Protobuf, schema_id=schema_id
        )
        self._channels[topic] = channel_id
        self._types[topic] = name
        return channel_id

    def write(self, topic: str, msg_type: type[Message], data: bytes, log_time: int, publish_time: int) -> int:
        """Append serialized ``data`` of ``msg_type`` on ``topic``; returns its sequence."""
        channel_id = self._channel(topic, msg_type)
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        self._open.append((int(log_time), self.messages, channel_id, data, int(publish_time), seq))
        self._open_bytes += len(data)
        self.messages += 1
        if self._open_bytes >= self.chunk_size:
            self.flush()
        return seq

    def write_message(self, topic: str, msg: Message, log_time: int, publish_time: int) -> int:
        return self.write(topic, type(msg), msg.SerializeToString(), log_time, publish_time)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self._mcap.add_metadata(name, dict(data))
        self._file.flush()
        self._on_disk = self._file.tell()

    @property
    def unflushed(self) -> int:
        """Messages in the open chunk: what a kill -9 right now would lose."""
        return len(self._open)

    def count(self, topic: str) -> int:
        return self._seq.get(topic, 0)

    def flush(self) -> None:
        """Cut the open chunk now, its messages in log-time order (queues of several topics drain in
        turns, so they arrive out of order by a little), and hand it to the OS."""
        self._open.sort(key=lambda m: (m[0], m[1]))
        for log_time, _, channel_id, data, publish_time, seq in self._open:
            self._mcap.add_message(
                channel_id=channel_id, log_time=log_time, data=data, publish_time=publish_time, sequence=seq
            )
        self._open.clear()
        self._open_bytes = 0
        self._mcap.flush()
        self._file.flush()
        self._on_disk = self._file.tell()
        self._last_flush = time.monotonic()

    def maybe_flush(self) -> None:
        if self._open and time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def close(self) -> Path:
        """Write the summary and footer, fsync, and rename ``.part`` to the final name."""
        self.flush()
        self._mcap.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        self.closed = True
        os.replace(self.part_path, self.path)
        _fsync_dir(self.path.parent)
        return self.path

    def abandon(self) -> None:
        """Stop writing and keep the partial file as it is (for ``recover``)."""
        if not self.closed:
            try:
                self._file.close()
            except OSError:
                pass
            self.closed = True

    def abort(self) -> None:
        """Stop writing and delete the partial file (a discarded episode)."""
        if not self.closed:
            self._file.close()
            self.closed = True
        self.part_path.unlink(missing_ok=True)


def _fsync_dir(path: Path) -> None:
    # The rename is durable only once the directory entry is.
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
