"""Recorder files without a bus: payload checks, the MCAP layout, the reader, recovery."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from services.core.config import ConfigError, load_config
from services.core.rig import Camera, look_at
from services.core.tensors import compressed_image, decode_jpeg, encode_jpeg
from services.core.topics import COMMAND, ROBOT_STATE, camera_calibration, camera_image, camera_pose
from services.core.validation import Invalid as MalformedPayload
from services.core.validation import parse
from services.pb.control_pb2 import EefCommand
from services.pb.episode_pb2 import EpisodeMeta
from services.pb.sensors_pb2 import RobotState
from services.recorder.config import RecorderConfig
from services.recorder.reader import EpisodeReadError, read_episode
from services.recorder.recover import RECOVERED_FLAG, RecoveryError, salvage
from services.recorder.recover import main as recover_main
from services.recorder.writer import (
    EPISODE_CHANNEL,
    EPISODE_RECORD,
    START_RECORD,
    EpisodeWriter,
    check_episode_id,
    meta_to_record,
    record_to_dict,
    start_record,
)

T0 = 1_700_000_000_000_000_000
RNG = np.random.default_rng(0)
IMG = RNG.integers(0, 255, (24, 32, 3), dtype=np.uint8)


def state(i: int, stamp: int) -> RobotState:
    msg = RobotState(tick=i, eef_pos=[0.1 * i, 0.0, 0.2], eef_quat_wxyz=[1, 0, 0, 0], gripper=0.5)
    msg.header.stamp_ns = stamp
    msg.header.seq = i
    return msg


def camera() -> Camera:
    pos = np.array([1.5, 0.0, 0.6])
    return Camera("F", pos, look_at(pos, np.array([0.5, 0.0, 0.1])), 50.0)


# -- payload checks ---------------------------------------------------------------------------
def test_good_payloads_parse_as_their_topic():
    img = compressed_image(IMG, T0, "F")
    assert parse(camera_image("F"), img.SerializeToString()).data == img.data
    assert parse(ROBOT_STATE, state(3, T0).SerializeToString()).tick == 3
    calib = camera().calibration_msg(32, 24, T0)
    assert list(parse(camera_calibration("F"), calib.SerializeToString()).K) == list(calib.K)
    pose = camera().pose_msg(T0)
    assert parse(camera_pose("F"), pose.SerializeToString()).child_frame_id == "F"


def _bad_payloads() -> dict[str, tuple[object, bytes, str]]:
    good_img = compressed_image(IMG, T0, "F")
    jpeg = encode_jpeg(IMG)
    garbage = CompressedImage(
        frame_id="F", format="jpeg", data=b"\xff\xd8" + bytes(RNG.integers(0, 255, 500, dtype=np.uint8)) + b"\xff\xd9"
    )
    garbage.timestamp.FromNanoseconds(T0)
    cut = CompressedImage(frame_id="F", format="jpeg", data=jpeg[: len(jpeg) // 2])
    cut.timestamp.FromNanoseconds(T0)
    png = CompressedImage(frame_id="F", format="png", data=jpeg)
    png.timestamp.FromNanoseconds(T0)
    unstamped = RobotState(tick=1)
    return {
        "truncated state": (ROBOT_STATE, state(1, T0).SerializeToString()[:-3], "not a valid"),
        "image bytes on robot/state": (ROBOT_STATE, good_img.SerializeToString(), "viewscale.v1.RobotState"),
        "state bytes on an image topic": (camera_image("F"), state(1, T0).SerializeToString(), "CompressedImage"),
        "truncated image message": (camera_image("F"), good_img.SerializeToString()[:-10], "not a valid"),
        "undecodable jpeg": (camera_image("F"), garbage.SerializeToString(), "JPEG"),
        "jpeg cut in half": (camera_image("F"), cut.SerializeToString(), "truncated JPEG"),
        "png": (camera_image("F"), png.SerializeToString(), "not jpeg"),
        "no capture time": (ROBOT_STATE, unstamped.SerializeToString(), "no capture time"),
        "random bytes": (camera_calibration("F"), bytes(RNG.integers(0, 255, 64, dtype=np.uint8)), ""),
    }


@pytest.mark.parametrize("case", list(_bad_payloads()))
def test_malformed_payloads_are_refused_with_a_reason(case):
    topic, payload, reason = _bad_payloads()[case]
    with pytest.raises(MalformedPayload) as err:
        parse(topic, payload)
    assert reason in str(err.value)


def test_markers_only_mode_skips_the_decode_but_not_the_markers():
    garbage = b"\xff\xd8" + b"\x00\x11" * 40 + b"\xff\xd9"
    msg = CompressedImage(frame_id="F", format="jpeg", data=garbage)
    msg.timestamp.FromNanoseconds(T0)
    assert parse(camera_image("F"), msg.SerializeToString(), decode_images=False).data == garbage
    msg.data = garbage[:-2]
    with pytest.raises(MalformedPayload, match="truncated"):
        parse(camera_image("F"), msg.SerializeToString(), decode_images=False)


def test_episode_ids_cannot_escape_the_output_directory():
    check_episode_id("pick_cube-0007.a")
    for bad in ("", "../x", "a/b", ".hidden", "x" * 200, "ep.mcap.part"):
        with pytest.raises(ValueError, match="invalid episode id"):
            check_episode_id(bad)


def test_config_validates_and_takes_overrides(tmp_path):
    yaml_file = tmp_path / "sim.yaml"
    yaml_file.write_text("bus: {mode: client, connect: [tcp/127.0.0.1:7447]}\nrecorder: {queue_size: 8}\n")
    cfg = load_config(RecorderConfig, yaml_file, ["chunk_size=4096"], environ={}, section="recorder")
    assert (cfg.queue_size, cfg.chunk_size, cfg.bus.mode) == (8, 4096, "client")
    with pytest.raises(ConfigError, match="queue_size"):
        load_config(RecorderConfig, None, ["queue_size=0"], environ={}, section="recorder")
    with pytest.raises(ConfigError, match="queu_size"):
        load_config(RecorderConfig, None, ["queu_size=3"], environ={}, section="recorder")


# -- writing and reading ----------------------------------------------------------------------
def write_episode(path, n=30, chunk_size=1 << 20, close=True) -> tuple[EpisodeWriter, EpisodeMeta]:
    """n robot states at 50 Hz capture time, an image per tick, calibration first."""
    meta = EpisodeMeta(episode_id=path.stem, task="lift", seed=7, rig="five15", control_hz=50.0, start_ns=T0)
    w = EpisodeWriter(path, chunk_size=chunk_size, flush_interval_s=3600)
    w.add_metadata(START_RECORD, start_record(meta))
    w.write_message(camera_calibration("F").mcap_topic, camera().calibration_msg(32, 24, T0), T0, T0)
    w.write_message(camera_pose("F").mcap_topic, camera().pose_msg(T0), T0, T0)
    for i in range(n):
        stamp = T0 + i * 20_000_000
        w.write_message(ROBOT_STATE.mcap_topic, state(i, stamp), stamp + 1000, stamp)
        w.write_message(camera_image("F").mcap_topic, compressed_image(IMG, stamp, "F"), stamp + 2000, stamp)
        w.write_message(COMMAND.mcap_topic, EefCommand(tick=i, source="policy"), stamp + 3000, stamp)
    if close:
        meta.ticks = n
        meta.frames["F"] = n
        meta.achieved_hz = 50.0
        meta.success = True
        meta.flags.append("camera F: example flag")
        meta.end_ns = T0 + n * 20_000_000
        w.write_message(EPISODE_CHANNEL, meta, meta.end_ns, meta.end_ns)
        w.add_metadata(EPISODE_RECORD, meta_to_record(meta))
        w.close()
    return w, meta


def test_file_layout_reads_back_with_the_mcap_library(tmp_path):
    path = tmp_path / "ep1.mcap"
    write_episode(path, n=30)
    assert path.is_file() and not (tmp_path / "ep1.mcap.part").exists()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        topics = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert {t: (s.name, s.encoding) for t, s in topics.items()} == {
            "/camera/F/calibration": ("foxglove.CameraCalibration", "protobuf"),
            "/camera/F/pose": ("foxglove.FrameTransform", "protobuf"),
            "/robot/state": ("viewscale.v1.RobotState", "protobuf"),
            "/camera/F/image": ("foxglove.CompressedImage", "protobuf"),
            "/teleop/command": ("viewscale.v1.EefCommand", "protobuf"),
            "/recorder/episode": ("viewscale.v1.EpisodeMeta", "protobuf"),
        }
        assert {c.message_encoding for c in summary.channels.values()} == {"protobuf"}
        seqs: dict[str, list[int]] = {}
        # Decoded through the embedded schemas alone, as Foxglove would.
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            seqs.setdefault(channel.topic, []).append(message.sequence)
            if channel.topic == "/robot/state":
                assert message.publish_time == decoded.header.stamp_ns == T0 + decoded.tick * 20_000_000
                assert message.log_time == message.publish_time + 1000
        assert seqs["/robot/state"] == list(range(30)) and seqs["/camera/F/image"] == list(range(30))
        records = {m.name: m.metadata for m in reader.iter_metadata()}
    assert records[START_RECORD]["task"] == "lift"
    assert record_to_dict(records[EPISODE_RECORD])["frames"] == {"F": 30}


def test_read_episode_gives_typed_metadata_and_decoded_messages(tmp_path):
    path = tmp_path / "ep2.mcap"
    _, meta = write_episode(path, n=12)
    ep = read_episode(path)
    assert ep.metadata == {
        "episode_id": "ep2",
        "task": "lift",
        "seed": 7,
        "rig": "five15",
        "success": True,
        "control_hz": 50.0,
        "achieved_hz": 50.0,
        "lockstep": False,
        "ticks": 12,
        "stale_ticks": 0,
        "clipped_ticks": 0,
        "frames": {"F": 12},
        "drops": {},
        "malformed": {},
        "gaps": {},
        "malformed_reasons": {},
        "flags": ["camera F: example flag"],
        "start_ns": T0,
        "end_ns": meta.end_ns,
    }
    assert ep.meta == meta and ep.cameras == ["F"] and ep.flags == ["camera F: example flag"]
    states = ep.messages("robot/state")
    assert [r.msg.tick for r in states] == list(range(12)) and isinstance(states[0].msg, RobotState)
    assert [r.sequence for r in states] == list(range(12))
    assert [r.publish_time for r in states] == [T0 + i * 20_000_000 for i in range(12)]
    frame = ep.messages("/camera/F/image")[5]
    assert isinstance(frame.msg, CompressedImage) and decode_jpeg(frame.msg.data).shape == (24, 32, 3)
    calib, _ = Camera.from_msgs(ep.messages("/camera/F/calibration")[0].msg, ep.messages("/camera/F/pose")[0].msg)
    assert np.allclose(calib.position, camera().position)
    only = read_episode(path, topics=["/robot/state"])
    assert set(only.topics) == {"/robot/state"} and only.metadata["ticks"] == 12


def test_read_episode_names_the_file_when_it_cannot_read_it(tmp_path):
    with pytest.raises(EpisodeReadError, match="missing.mcap does not exist"):
        read_episode(tmp_path / "missing.mcap")
    (tmp_path / "text.mcap").write_text("not an mcap file at all")
    with pytest.raises(EpisodeReadError, match="text.mcap"):
        read_episode(tmp_path / "text.mcap")
    w, _ = write_episode(tmp_path / "open.mcap", n=5, close=False)
    w.flush()
    with pytest.raises(EpisodeReadError, match="recover it first"):
        read_episode(tmp_path / "open.mcap")
    with pytest.raises(EpisodeReadError, match=r"open.mcap.part .*recover"):
        read_episode(tmp_path / "open.mcap.part")


def test_metadata_record_round_trips():
    meta = EpisodeMeta(
        episode_id="e",
        seed=2**63,
        control_hz=10.0,
        achieved_hz=9.5,
        ticks=3,
        success=False,
        flags=["a", "b: c"],
        start_ns=1,
        end_ns=2,
    )
    meta.drops["camera/F/image"] = 4
    assert "command_sources" not in meta_to_record(meta)  # (none: as recordings made before it)
    meta.command_sources.extend(["policy", "spacemouse"])
    rec = meta_to_record(meta)
    assert all(isinstance(v, str) for v in rec.values())
    back = record_to_dict(rec)
    assert back["seed"] == 2**63 and back["drops"] == {"camera/F/image": 4} and back["flags"] == ["a", "b: c"]
    assert back["success"] is False and back["achieved_hz"] == 9.5
    assert back["command_sources"] == ["policy", "spacemouse"]


# -- crash bound and recovery -----------------------------------------------------------------
def test_an_open_file_loses_only_its_open_chunk(tmp_path):
    path = tmp_path / "ep3.mcap"
    w, _ = write_episode(path, n=200, chunk_size=8192, close=False)
    assert 0 < w.unflushed < w.messages
    # What a kill -9 leaves: the .part as the OS has it right now.
    snapshot = tmp_path / "killed" / "ep3.mcap.part"
    snapshot.parent.mkdir()
    shutil.copy(w.part_path, snapshot)
    result = salvage(snapshot)
    assert result.messages == w.messages - w.unflushed
    assert not result.complete and result.chunks > 10
    ep = read_episode(result.path)
    assert any(f.startswith(RECOVERED_FLAG) for f in ep.flags)
    assert (ep.metadata["task"], ep.metadata["seed"], ep.metadata["rig"]) == ("lift", 7, "five15")
    assert ep.metadata["command_sources"] == ["policy"]  # from the commands saved: a rollout stays one
    states = ep.messages("/robot/state")
    assert ep.metadata["ticks"] == len(states) and ep.metadata["frames"] == {"F": len(ep.messages("camera/F/image"))}
    assert [r.sequence for r in states] == list(range(len(states)))  # a prefix: nothing skipped
    assert ep.metadata["achieved_hz"] == pytest.approx(50.0)
    assert len(ep.messages("/camera/F/calibration")) == 1
    w.flush()  # time-based cut: now nothing is left in memory
    assert w.unflushed == 0
    shutil.copy(w.part_path, snapshot)
    assert salvage(snapshot, overwrite=True).messages == w.messages


def test_recovery_survives_a_cut_at_any_byte(tmp_path):
    full = tmp_path / "ep4.mcap"
    write_episode(full, n=40, chunk_size=4096)
    data = full.read_bytes()
    total = sum(len(v) for v in read_episode(full).topics.values())
    last = -1
    for cut in sorted(set(RNG.integers(8, len(data), 25).tolist()) | {8, 9, len(data) - 1}):
        part = tmp_path / f"cut{cut}.mcap.part"
        part.write_bytes(data[:cut])
        result = salvage(part)
        ep = read_episode(result.path)
        counts = {t: len(r) for t, r in ep.topics.items() if t != EPISODE_CHANNEL}
        for topic, recs in ep.topics.items():
            if topic != EPISODE_CHANNEL:
                assert [r.sequence for r in recs] == list(range(len(recs)))
        assert sum(counts.values()) == result.messages - result.per_topic[EPISODE_CHANNEL]
        assert result.messages <= total
        assert result.messages >= last  # more bytes never recover fewer messages
        last = result.messages


def test_recovering_a_complete_file_keeps_everything(tmp_path):
    full = tmp_path / "ep5.mcap"
    _, meta = write_episode(full, n=10)
    result = salvage(full)
    assert result.complete and result.path.name == "ep5.recovered.mcap"
    ep = read_episode(result.path)
    assert ep.meta == meta and ep.metadata["frames"] == {"F": 10} and RECOVERED_FLAG not in " ".join(ep.flags)


def test_recover_cli_reports_counts_and_refuses_non_mcap(tmp_path, capsys):
    w, _ = write_episode(tmp_path / "ep6.mcap", n=50, chunk_size=2048, close=False)
    w.flush()
    assert recover_main([str(w.part_path)]) == 0
    out = capsys.readouterr().out
    assert f"{w.messages} messages" in out and "ep6.mcap" in out
    assert recover_main([str(w.part_path)]) == 1  # output exists: not overwritten
    assert "already exists" in capsys.readouterr().err
    (tmp_path / "junk.mcap.part").write_bytes(b"junk")
    with pytest.raises(RecoveryError, match="junk.mcap.part is not an MCAP"):
        salvage(tmp_path / "junk.mcap.part")
    # a writer killed before its first flush leaves an empty file (before: 'is not an MCAP file: ')
    (tmp_path / "empty.mcap.part").write_bytes(b"")
    with pytest.raises(RecoveryError, match="empty.mcap.part holds 0 bytes, .*nothing to recover"):
        salvage(tmp_path / "empty.mcap.part")


def test_recover_cli_takes_a_folder(tmp_path, capsys):
    """A folder: every .mcap.part under it, those recovered already skipped (before: 'does not exist')."""
    w1, _ = write_episode(tmp_path / "a1.mcap", n=20, chunk_size=2048, close=False)
    (tmp_path / "eval" / "rollouts").mkdir(parents=True)
    w2, _ = write_episode(tmp_path / "eval" / "rollouts" / "a2.mcap", n=30, chunk_size=2048, close=False)
    w1.flush(), w2.flush()
    assert recover_main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert read_episode(tmp_path / "a1.mcap").metadata["ticks"] == 20 and "a1.mcap" in out
    assert read_episode(tmp_path / "eval" / "rollouts" / "a2.mcap").metadata["ticks"] == 30 and "a2.mcap" in out
    before = (tmp_path / "a1.mcap").stat().st_mtime_ns
    assert recover_main([str(tmp_path)]) == 0  # again: nothing to do, nothing overwritten
    assert "2 of 2 .mcap.part files are recovered already" in capsys.readouterr().out
    assert (tmp_path / "a1.mcap").stat().st_mtime_ns == before
    (tmp_path / "none").mkdir()
    assert recover_main([str(tmp_path / "none")]) == 1
    assert f"error: {tmp_path / 'none'} holds no .mcap.part file" in capsys.readouterr().err
