"""Recover the readable part of an episode file a killed recorder left behind.

    python -m services.recorder.recover data/raw/ep0001.mcap.part [...]
    python -m services.recorder.recover data/raw      # every .mcap.part under it

A ``.part`` file has a header, the ``episode_start`` record and whole chunks up to the one the
recorder was filling when it died; that last chunk and the summary/footer are missing. This
reads records one by one, keeps every record that is complete (chunks must also decompress and
pass their CRC) and stops at the first that is not. The kept schemas, channels, messages and
metadata are rewritten into a valid, indexed MCAP next to it (``ep0001.mcap``). Unless the
source already held the final ``episode`` record, an EpisodeMeta is rebuilt from
``episode_start`` and the recovered messages (robot states, frames per camera, achieved rate)
and flagged ``recovered``. The source file is left in place.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import struct
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from google.protobuf.message import DecodeError
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import MAGIC_SIZE, breakup_chunk, read_magic
from mcap.writer import MCAP0_MAGIC, CompressionType
from mcap.writer import Writer as McapWriter

from services.core.text import first_few
from services.core.topics import COMMAND, ROBOT_STATE
from services.pb.control_pb2 import EefCommand
from services.pb.episode_pb2 import EpisodeMeta
from services.recorder.writer import (
    EPISODE_CHANNEL,
    EPISODE_RECORD,
    LIBRARY,
    PART_SUFFIX,
    START_RECORD,
    meta_from_start_record,
    meta_to_record,
)

log = logging.getLogger(__name__)

RECOVERED_FLAG = "recovered"


class RecoveryError(ValueError):
    """Nothing could be recovered (not an MCAP file, or unreadable); names the file."""


@dataclass
class Recovered:
    source: Path
    path: Path
    messages: int = 0
    chunks: int = 0
    per_topic: Counter = field(default_factory=Counter)
    complete: bool = False  # the source had its footer: nothing was missing
    lost_bytes: int = 0  # unreadable bytes at the end of the source
    stop_reason: str = ""  # why reading stopped before the end, if it did
    command_sources: set[str] = field(default_factory=set)  # EefCommand.source of the commands saved

    def summary(self) -> str:
        tail = (
            "file was complete"
            if self.complete
            else (
                f"{self.lost_bytes} trailing bytes unreadable ({self.stop_reason})"
                if self.lost_bytes
                else "no data lost past the last complete record"
            )
        )
        return (
            f"recovered {self.source} -> {self.path}: {self.messages} messages on {len(self.per_topic)} "
            f"channels from {self.chunks} chunks; {tail}"
        )


def default_output(src: Path) -> Path:
    if src.name.endswith(PART_SUFFIX):
        return src.with_name(src.name[: -len(PART_SUFFIX)])
    return src.with_name(src.stem + ".recovered.mcap")


def _records(f, size: int):
    """Yield (offset, opcode, body) for every complete top-level record; stop at the first cut one."""
    offset = MAGIC_SIZE
    while offset + 9 <= size:
        f.seek(offset)
        opcode, length = struct.unpack("<BQ", f.read(9))
        if offset + 9 + length > size:
            return
        yield offset, opcode, f.read(length)
        offset += 9 + length


def salvage(src: str | Path, out: str | Path | None = None, overwrite: bool = False) -> Recovered:
    """Rewrite the readable records of ``src`` into ``out`` (default: ``src`` without ``.part``)."""
    src = Path(src)
    dst = Path(out) if out is not None else default_output(src)
    if not src.exists():
        raise RecoveryError(f"{src} does not exist")
    if not src.is_file():
        raise RecoveryError(f"{src} is not a file")
    if dst.exists() and not overwrite:
        raise RecoveryError(f"{dst} already exists; remove it or pass another output")
    size = src.stat().st_size
    if size < MAGIC_SIZE:
        with open(src, "rb") as f:
            head = f.read()
        if not MCAP0_MAGIC.startswith(head):
            raise RecoveryError(f"{src} is not an MCAP file: it holds {size} bytes, and not the MCAP magic")
        raise RecoveryError(
            f"{src} holds {size} bytes, less than an MCAP file's magic: its writer stopped before it wrote "
            "anything; nothing to recover"
        )
    result = Recovered(source=src, path=dst)
    tmp = dst.with_name(dst.name + ".recovering")
    with open(src, "rb") as f:
        try:
            read_magic(ReadDataStream(f))
        except Exception as exc:
            raise RecoveryError(f"{src} is not an MCAP file: {exc}") from exc
        with open(tmp, "wb") as out_f:
            writer = McapWriter(out_f, compression=CompressionType.ZSTD)
            writer.start(profile="", library=LIBRARY)
            schema_ids: dict[int, int] = {}  # source id -> output id
            channel_ids: dict[int, int] = {}
            topics: dict[int, str] = {}  # source channel id -> topic
            pending: list[Channel] = []  # channels whose schema has not been seen yet
            metadata: dict[str, dict[str, str]] = {}
            robot_stamps: list[int] = []
            last_log = 0
            end = MAGIC_SIZE

            def add_schema(rec: Schema) -> None:
                if rec.id not in schema_ids:
                    schema_ids[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)

            def add_channel(rec: Channel) -> None:
                if rec.id in channel_ids:
                    return
                if rec.schema_id and rec.schema_id not in schema_ids:
                    pending.append(rec)
                    return
                channel_ids[rec.id] = writer.register_channel(
                    rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), dict(rec.metadata)
                )
                topics[rec.id] = rec.topic

            def add_message(rec: Message) -> None:
                nonlocal last_log
                if rec.channel_id not in channel_ids:
                    return
                writer.add_message(channel_ids[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence)
                topic = topics[rec.channel_id]
                result.messages += 1
                result.per_topic[topic] += 1
                last_log = max(last_log, rec.log_time)
                if topic == ROBOT_STATE.mcap_topic:
                    robot_stamps.append(rec.publish_time)
                elif topic == COMMAND.mcap_topic:
                    with contextlib.suppress(DecodeError):  # (a torn command: the recorder had checked it)
                        if source := EefCommand.FromString(rec.data).source:
                            result.command_sources.add(source)

            def add(rec) -> None:
                if isinstance(rec, Schema):
                    add_schema(rec)
                    for ch in [c for c in pending if c.schema_id == rec.id]:
                        pending.remove(ch)
                        add_channel(ch)
                elif isinstance(rec, Channel):
                    add_channel(rec)
                elif isinstance(rec, Message):
                    add_message(rec)

            for offset, opcode, body in _records(f, size):
                stream = ReadDataStream(io.BytesIO(body))
                try:
                    if opcode == Opcode.CHUNK:
                        inner = breakup_chunk(Chunk.read(stream), validate_crc=True)
                        result.chunks += 1
                        for rec in inner:
                            add(rec)
                    elif opcode == Opcode.SCHEMA:
                        add(Schema.read(stream))
                    elif opcode == Opcode.CHANNEL:
                        add(Channel.read(stream))
                    elif opcode == Opcode.MESSAGE:
                        add(Message.read(stream, len(body)))
                    elif opcode == Opcode.METADATA:
                        rec = Metadata.read(stream)
                        metadata[rec.name] = dict(rec.metadata)
                    elif opcode == Opcode.ATTACHMENT:
                        att = Attachment.read(stream)
                        writer.add_attachment(att.create_time, att.log_time, att.name, att.media_type, att.data)
                    elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                        result.complete = True
                        end = size
                        break
                except Exception as exc:  # a corrupt record: keep what came before it
                    result.stop_reason = f"record at byte {offset} unreadable: {type(exc).__name__}: {exc}"
                    break
                end = offset + 9 + len(body)
            if not result.complete and not result.stop_reason and end < size:
                result.stop_reason = f"record at byte {end} cut short"
            result.lost_bytes = 0 if result.complete else size - end

            for name, data in metadata.items():
                if name != EPISODE_RECORD:
                    writer.add_metadata(name, data)
            if EPISODE_RECORD in metadata:
                writer.add_metadata(EPISODE_RECORD, metadata[EPISODE_RECORD])
            else:
                meta = _rebuild_meta(src, metadata.get(START_RECORD), result, robot_stamps, last_log)
                _write_meta(writer, meta)
            writer.finish()
            out_f.flush()
            os.fsync(out_f.fileno())
    os.replace(tmp, dst)
    return result


def _rebuild_meta(
    src: Path, start: dict[str, str] | None, result: Recovered, robot_stamps: list[int], last_log: int
) -> EpisodeMeta:
    meta = meta_from_start_record(start or {})
    if not meta.episode_id:
        meta.episode_id = default_output(src).stem
    meta.ticks = len(robot_stamps)
    if len(robot_stamps) >= 2 and robot_stamps[-1] > robot_stamps[0]:
        meta.achieved_hz = (len(robot_stamps) - 1) * 1e9 / (robot_stamps[-1] - robot_stamps[0])
    for topic, n in result.per_topic.items():
        parts = topic.split("/")
        if len(parts) == 4 and parts[1] == "camera" and parts[3] == "image":
            meta.frames[parts[2]] = n
    meta.end_ns = last_log
    meta.path = str(result.path)
    meta.command_sources.extend(sorted(result.command_sources))
    meta.flags.append(
        f"{RECOVERED_FLAG}: {src.name} was not closed by the recorder (killed?); "
        f"{result.messages} messages saved"
        + (f", {result.lost_bytes} trailing bytes lost" if result.lost_bytes else "")
    )
    if start is None:
        meta.flags.append("episode_start record missing: task, seed and rig unknown")
    return meta


def _write_meta(writer: McapWriter, meta: EpisodeMeta) -> None:
    from mcap.well_known import MessageEncoding
    from mcap_protobuf.schema import build_file_descriptor_set

    schema_id = writer.register_schema(
        EpisodeMeta.DESCRIPTOR.full_name, "protobuf", build_file_descriptor_set(EpisodeMeta).SerializeToString()
    )
    channel_id = writer.register_channel(EPISODE_CHANNEL, MessageEncoding.Protobuf, schema_id)
    stamp = meta.end_ns or meta.start_ns
    writer.add_message(channel_id, stamp, meta.SerializeToString(), stamp, 0)
    writer.add_metadata(EPISODE_RECORD, meta_to_record(meta))


def recover(path_part: str | Path, out: str | Path | None = None) -> Path:
    """Recover ``path_part`` into a valid MCAP; returns the new file's path."""
    result = salvage(path_part, out)
    log.info("%s", result.summary())
    return result.path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.recorder.recover", description=__doc__.split("\n")[0])
    parser.add_argument(
        "files",
        nargs="+",
        type=Path,
        help="partial episode files (<episode_id>.mcap.part), or folders: every .mcap.part under them, "
        "skipping those already recovered",
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing output file")
    args = parser.parse_args(argv)
    failed = 0
    for arg in args.files:
        if not arg.is_dir():
            sources = [arg]
        else:
            sources = sorted(arg.rglob("*.mcap" + PART_SUFFIX))
            if not sources:
                print(f"error: {arg} holds no .mcap{PART_SUFFIX} file, at any depth", file=sys.stderr, flush=True)
                failed += 1
            done = [] if args.force else [p for p in sources if default_output(p).exists()]
            if done:
                print(
                    f"{arg}: {len(done)} of {len(sources)} .mcap{PART_SUFFIX} files are recovered already "
                    f"({first_few([p.name for p in done])}): skipped; "
                    "--force recovers them again",
                    flush=True,
                )
            sources = [p for p in sources if p not in done]
        for src in sources:
            try:
                print(salvage(src, overwrite=args.force).summary(), flush=True)
            except (RecoveryError, OSError) as exc:
                print(f"error: {exc}", file=sys.stderr, flush=True)
                failed += 1
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
