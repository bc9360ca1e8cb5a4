"""The recorder's episode rules, pure: what an episode counts while it is written, and why it
is flagged when it closes. No files, threads or clocks in here; the recorder feeds it.

Counted per topic key: messages written, malformed payloads, sequence gaps (a forward jump
counts the messages skipped; a jump back is a publisher restart), plus the robot-state
capture times (for the achieved rate), stale ticks (the robot held still for want of a command),
clipped ticks (the safety layer changed the command) and fault ticks (the arm could not move: a
protective stop, a lost connection; ``AppliedAction.fault``).

Flags, in this order: events (liveliness losses and restarts, write errors) as they happened;
``empty`` when no robot state was recorded at all, else ``low rate`` when the robot state arrived
below ``min_rate_fraction`` of the control rate (real time only: a lockstep session runs as fast
as the machine goes, so its rate says nothing);
recorder queue drops; malformed payloads; publisher restarts; sequence gaps not explained by
our own drops; robot faults; stale ticks; clipped ticks; fewer robot states than the ticks the
source says it published; a camera whose frame count differs from the tick count; a publisher
whose capture stamps disagree with the recorder's clock.

Clocks. Every message carries its capture time from its publisher's clock, and the dataset pairs
frames with states by those times: a camera host whose clock is 300 ms off the robot's pairs every
state with a frame from six ticks away, and nothing else shows it. The recorder receives each
message after its capture, so per topic the smallest ``receive - capture`` of an episode is the
quickest delivery plus the publisher's clock offset. Below ``-CLOCK_AHEAD_NS`` (captured after it
was received) the publisher's clock is ahead of the recorder's. Above ``CLOCK_BEHIND_NS`` on a
topic stamped when it is published (robot state, applied actions, commands, task state), even the
quickest message took that long, and the clock is behind (or every message was held up). A
camera's frames are stamped at capture, which comes a latency before they are sent (an RTSP
stream's can be a second or more), so they are checked for a clock ahead only. Calibration and
pose messages are republished copies and not checked.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from services.core.topics import APPLIED_ACTION, COMMAND, ROBOT_STATE
from services.core.validation import counts_by_reason
from services.pb.common_pb2 import Header
from services.pb.episode_pb2 import EpisodeMeta, EpisodeRequest


def camera_of(key: str) -> str:
    return key.split("/")[1]


def is_calibration(key: str) -> bool:
    return key.startswith("camera/") and (key.endswith("/calibration") or key.endswith("/pose"))


CLOCK_AHEAD_NS = 20_000_000  # 20 ms: beyond what synchronised clocks (NTP, chrony, PTP) differ by
CLOCK_BEHIND_NS = 500_000_000  # 500 ms: far longer than a message stamped as it is sent takes on a lab network


def fmt_counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))


@dataclass
class EpisodeCounts:
    """Counters of one open episode."""

    meta: EpisodeMeta  # what START said: id, task, seed, rig, control rate, lockstep, start, path
    written: Counter = field(default_factory=Counter)  # key -> messages written
    malformed: Counter = field(default_factory=Counter)  # key -> payloads refused
    malformed_reasons: Counter = field(default_factory=Counter)  # (key, reason) -> payloads refused
    gaps: Counter = field(default_factory=Counter)  # key -> sequence discontinuities
    resets: Counter = field(default_factory=Counter)  # key -> times the sequence went back (publisher restart)
    missing: Counter = field(default_factory=Counter)  # key -> messages skipped by forward sequence jumps
    last_seq: dict[str, int] = field(default_factory=dict)
    cameras: set[str] = field(default_factory=set)
    stale: int = 0  # applied actions that were a hold for want of a command
    clipped: int = 0  # applied actions the safety layer changed
    faults: Counter = field(default_factory=Counter)  # robot fault -> ticks it lasted (the arm stopped)
    state_n: int = 0
    state_first: int = 0
    state_last: int = 0
    events: list[str] = field(default_factory=list)  # flags from liveliness and errors, in order
    left: set[str] = field(default_factory=set)  # services that lost liveliness during the episode
    sources: set[str] = field(default_factory=set)  # EefCommand.source of the commands written
    quickest: dict[str, int] = field(default_factory=dict)  # key -> smallest receive - capture (ns)

    @classmethod
    def start(cls, req: EpisodeRequest, path: str, start_ns: int) -> EpisodeCounts:
        return cls(
            EpisodeMeta(
                episode_id=req.episode_id,
                task=req.task,
                seed=req.seed,
                rig=req.rig,
                control_hz=req.control_hz,
                lockstep=req.lockstep,
                start_ns=start_ns,
                path=path,
            )
        )

    @property
    def start_ns(self) -> int:
        return int(self.meta.start_ns)

    def note(self, flag: str) -> None:
        if flag not in self.events:
            self.events.append(flag)

    def service_left(self, service: str) -> None:
        self.left.add(service)
        self.note(f"service {service} lost liveliness mid-episode")

    def service_back(self, service: str) -> bool:
        """Note a service's return; False if it had not left during the episode."""
        if service not in self.left:
            return False
        self.note(f"service {service} restarted mid-episode")
        return True

    @property
    def achieved_hz(self) -> float:
        if self.state_n < 2 or self.state_last <= self.state_first:
            return 0.0
        return (self.state_n - 1) * 1e9 / (self.state_last - self.state_first)

    def count(self, key: str, msg, stamp_ns: int, receive_ns: int | None = None) -> int | None:
        """Count one written message of ``key`` (captured at ``stamp_ns`` by its publisher's clock,
        received at ``receive_ns`` by the recorder's); returns the previous sequence if this one went back."""
        self.written[key] += 1
        if receive_ns is not None and stamp_ns and not is_calibration(key):
            delay = receive_ns - stamp_ns
            if delay < self.quickest.get(key, delay + 1):
                self.quickest[key] = delay
        if key.endswith("/image") or is_calibration(key):
            self.cameras.add(camera_of(key))
        went_back = None
        header = getattr(msg, "header", None)
        if isinstance(header, Header):
            last = self.last_seq.get(key)
            if last is not None and header.seq != last + 1:
                self.gaps[key] += 1
                if header.seq <= last:
                    self.resets[key] += 1
                    went_back = last
                else:
                    self.missing[key] += header.seq - last - 1
            self.last_seq[key] = header.seq
        if key == COMMAND.key and msg.source:
            self.sources.add(msg.source)
        if key == APPLIED_ACTION.key:
            self.stale += bool(msg.stale)
            self.clipped += bool(len(msg.limits))
            if msg.fault:
                self.faults[msg.fault] += 1
        if key == ROBOT_STATE.key:
            if self.state_n == 0:
                self.state_first = stamp_ns
            self.state_n += 1
            self.state_last = stamp_ns
        return went_back

    def frames(self, camera: str) -> int:
        return self.written[f"camera/{camera}/image"]


def episode_meta(
    ep: EpisodeCounts, *, drops: dict[str, int], ticks: int, success: bool, end_ns: int, min_rate_fraction: float
) -> EpisodeMeta:
    """The episode's facts so far, with every reason it is suspect in ``flags``.

    ``ticks``: the ticks the source says it published (0 while the episode is open);
    ``drops``: samples the recorder's queues dropped, per key.
    """
    meta = EpisodeMeta()
    meta.CopyFrom(ep.meta)
    meta.success = success
    states = ep.written[ROBOT_STATE.key]
    meta.ticks = ticks or states
    meta.achieved_hz = ep.achieved_hz
    for cam in sorted(ep.cameras):
        meta.frames[cam] = ep.frames(cam)
    drops = {k: v for k, v in drops.items() if v}
    meta.drops.update(drops)
    meta.malformed.update({k: v for k, v in ep.malformed.items() if v})
    meta.malformed_reasons.update(counts_by_reason(ep.malformed_reasons))
    meta.gaps.update({k: v for k, v in ep.gaps.items() if v})
    meta.stale_ticks = ep.stale
    meta.clipped_ticks = ep.clipped
    meta.command_sources.extend(sorted(ep.sources))
    meta.end_ns = end_ns

    flags = list(ep.events)
    hz = ep.meta.control_hz
    floor = min_rate_fraction * hz
    if states == 0:  # (before: "low rate: robot state at 0.00 Hz", for an arm that never published)
        flags.append(f"empty: no {ROBOT_STATE.key} recorded (no robot service or sim publishing it on this bus?)")
    elif hz > 0 and not ep.meta.lockstep and meta.achieved_hz < floor:
        flags.append(f"low rate: robot state at {meta.achieved_hz:.2f} Hz < {min_rate_fraction:g} x {hz:g} Hz")
    if drops:
        flags.append(f"drops: recorder queues overflowed ({fmt_counts(drops)})")
    if meta.malformed:
        flags.append(f"malformed payloads ({fmt_counts(dict(meta.malformed))})")
    for key, n in sorted(ep.resets.items()):
        flags.append(f"publisher restart on {key}: sequence went back {n}x")
    unexplained = {k: m for k, m in ep.missing.items() if m > drops.get(k, 0)}
    if unexplained:
        flags.append(f"sequence gaps: messages lost upstream ({fmt_counts(unexplained)})")
    if ep.faults:
        faults = list(ep.faults.items())
        what = "; ".join(f"{fault} ({n} ticks)" for fault, n in faults[:3])
        what += f"; {len(faults) - 3} other faults" if len(faults) > 3 else ""
        flags.append(f"robot fault: {sum(ep.faults.values())} ticks the arm was stopped: {what}")
    if ep.stale:
        flags.append(f"stale: {ep.stale} ticks held still without a fresh command (teleop late or missing)")
    if ep.clipped:
        flags.append(f"clipped: {ep.clipped} ticks limited by the safety layer (speed, workspace or gripper range)")
    if ticks and states != ticks:
        flags.append(f"robot/state: {states} states for {ticks} ticks")
    applied = ep.written[APPLIED_ACTION.key]
    if ticks and applied and applied != ticks:  # a source without applied actions is not flagged
        flags.append(f"robot/applied: {applied} applied actions for {ticks} ticks")
    for cam, n in sorted(meta.frames.items()):
        if n != meta.ticks:
            flags.append(f"camera {cam}: {n} frames for {meta.ticks} ticks")
    flags += clock_flags(ep.quickest)
    meta.flags.extend(flags)
    return meta


def clock_flags(quickest: dict[str, int]) -> list[str]:
    """One flag per topic whose capture stamps disagree with the recorder's clock (module docstring)."""
    flags = []
    for key, delay in sorted(quickest.items()):
        if delay < -CLOCK_AHEAD_NS:
            flags.append(
                f"clock: {key} stamped up to {-delay / 1e6:.0f} ms after the recorder received it: its "
                "publisher's clock is ahead of the recorder's, and frames pair with the wrong states "
                "(synchronise the hosts' clocks: chrony or PTP)"
            )
        elif delay > CLOCK_BEHIND_NS and not key.startswith("camera/"):
            flags.append(
                f"clock: {key} reached the recorder {delay / 1e6:.0f} ms after its capture stamp at the quickest: "
                "its publisher's clock is behind the recorder's (or every message was held up), and frames "
                "may pair with the wrong states (synchronise the hosts' clocks: chrony or PTP)"
            )
    return flags
