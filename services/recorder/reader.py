"""Read a recorded episode back: its metadata and every message, decoded.

    from services.recorder.reader import read_episode
    ep = read_episode("data/raw/ep0001.mcap")
    ep.metadata["achieved_hz"], ep.metadata["frames"], ep.metadata["flags"]
    for rec in ep.messages("/camera/F/image"):   # in log_time order
        rec.publish_time, rec.log_time, rec.sequence, rec.msg   # msg: foxglove CompressedImage

Messages decode to this repository's classes (``topics.topic_for_key``) when the embedded schema
names the same type, otherwise through the embedded schema. A file that is missing, not MCAP,
cut short (``.part`` left by a killed recorder: run ``python -m services.recorder.recover``) or
without an ``episode`` record raises ``EpisodeReadError`` naming the file.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from google.protobuf.message import DecodeError, Message
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import MCAP0_MAGIC
from mcap_protobuf.decoder import DecoderFactory

from services.core.topics import topic_for_key
from services.pb.episode_pb2 import EpisodeMeta
from services.recorder.writer import EPISODE_CHANNEL, EPISODE_RECORD, PART_SUFFIX, record_to_dict


class EpisodeReadError(ValueError):
    """An episode file could not be read; the message names the file and what is wrong."""


@dataclass(frozen=True)
class Record:
    log_time: int  # receive time, Unix ns
    publish_time: int  # capture time, Unix ns
    sequence: int  # index of the message in its channel
    msg: Message


@dataclass
class Episode:
    path: Path
    metadata: dict  # the ``episode`` record, typed: seed/ticks ints, hz floats, success bool, maps, flags
    topics: dict[str, list[Record]] = field(default_factory=dict)  # mcap topic -> records by log_time
    schemas: dict[str, str] = field(default_factory=dict)  # mcap topic -> message type full name
    raw_metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # every metadata record by name

    def messages(self, topic: str) -> list[Record]:
        """Records of ``topic`` (``/robot/state`` or ``robot/state``); empty if none."""
        return self.topics.get(topic if topic.startswith("/") else "/" + topic, [])

    @property
    def meta(self) -> EpisodeMeta | None:
        """The final EpisodeMeta written on ``/recorder/episode`` at close."""
        recs = self.topics.get(EPISODE_CHANNEL)
        return recs[-1].msg if recs else None  # type: ignore[return-value]

    @property
    def cameras(self) -> list[str]:
        return sorted(t.split("/")[2] for t in self.topics if t.startswith("/camera/") and t.endswith("/image"))

    @property
    def flags(self) -> list[str]:
        return list(self.metadata.get("flags", []))


def _decoder_for(topic: str, schema, fallback: DecoderFactory):
    ours = EpisodeMeta if topic == EPISODE_CHANNEL else getattr(topic_for_key(topic[1:]), "msg_type", None)
    if ours is not None and schema is not None and schema.name == ours.DESCRIPTOR.full_name:

        def decode(data: bytes, _type=ours) -> Message:
            msg = _type()
            msg.ParseFromString(data)
            return msg

        return decode
    decode = fallback.decoder_for("protobuf", schema)
    if decode is None:
        raise EpisodeReadError(f"channel {topic} has no protobuf schema")
    return decode


def read_episode(path: str | Path, topics: Iterable[str] | None = None) -> Episode:
    """Read ``path`` (a closed episode); ``topics`` limits which channels are decoded (none: only
    its metadata is read)."""
    path = Path(path)
    if not path.is_file():
        hint = (
            f" (a partial {path.name}{PART_SUFFIX} exists: recover it first)"
            if path.with_name(path.name + PART_SUFFIX).is_file()
            else ""
        )
        raise EpisodeReadError(f"episode file {path} does not exist{hint}")
    wanted = None if topics is None else {t if t.startswith("/") else "/" + t for t in topics}
    fallback = DecoderFactory()
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP0_MAGIC))
            f.seek(max(0, path.stat().st_size - len(MCAP0_MAGIC)))
            tail = f.read(len(MCAP0_MAGIC))
            if head != MCAP0_MAGIC:
                raise EpisodeReadError(f"{path} is not an MCAP file")
            if tail != MCAP0_MAGIC or path.stat().st_size < 2 * len(MCAP0_MAGIC):
                raise EpisodeReadError(
                    f"{path} was not closed (no footer: the recorder stopped while writing "
                    f"it); recover it with `python -m services.recorder.recover {path}`"
                )
            f.seek(0)
            reader = make_reader(f)
            raw = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            if EPISODE_RECORD not in raw:
                raise EpisodeReadError(f"{path} has no '{EPISODE_RECORD}' metadata record (not a closed episode)")
            episode = Episode(path=path, metadata=record_to_dict(raw[EPISODE_RECORD]), raw_metadata=raw)
            decoders: dict[int, object] = {}
            if wanted is not None and not wanted:  # topics=(): the metadata alone, without reading the chunks
                return episode
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if wanted is not None and channel.topic not in wanted:
                    continue
                decode = decoders.get(channel.id)
                if decode is None:
                    decode = decoders[channel.id] = _decoder_for(channel.topic, schema, fallback)
                    episode.schemas[channel.topic] = schema.name if schema is not None else ""
                episode.topics.setdefault(channel.topic, []).append(
                    Record(message.log_time, message.publish_time, message.sequence, decode(message.data))
                )
    except EpisodeReadError:
        raise
    except (McapError, DecodeError, EOFError, struct.error, ValueError, OSError) as exc:
        raise EpisodeReadError(f"{path} is not a readable episode: {type(exc).__name__}: {exc}") from exc
    except Exception as exc:  # zstd and friends raise their own types on corrupt chunks
        raise EpisodeReadError(f"{path} is corrupt: {type(exc).__name__}: {exc}") from exc
    for recs in episode.topics.values():
        recs.sort(key=lambda r: (r.log_time, r.sequence))
    return episode
