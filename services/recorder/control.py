"""The client side of the recorder's control queryable (``recorder/control``).

``viewscale episode start|stop|discard|status`` and the teleop devices' episode keys
(``services/teleop/device.py``) send their requests through these functions, so a key on the
SpaceMouse and the command line drive the recorder the same way. The recorder (``service.py``)
answers them; a STOP or DISCARD without an episode id acts on the episode being recorded.
"""

from __future__ import annotations

from datetime import datetime, timezone

from services.core import topics
from services.core.bus import Bus
from services.pb.episode_pb2 import EpisodeCommand, EpisodeReply, EpisodeRequest

COMMANDS = {
    "start": EpisodeCommand.EPISODE_COMMAND_START,
    "stop": EpisodeCommand.EPISODE_COMMAND_STOP,
    "discard": EpisodeCommand.EPISODE_COMMAND_DISCARD,
    "status": EpisodeCommand.EPISODE_COMMAND_STATUS,
}


def new_episode_id(task: str, rig: str) -> str:
    """``<task>-<rig>-<UTC time to the millisecond>`` (``lift-five15-20261206T020304.567``): the id
    of an episode started by hand; a task or rig not given is left out (neither: ``episode-<time>``).
    To the millisecond: two starts within one second (a start pressed by mistake, stopped at once,
    and the real one) would name the same file, and the recorder refuses an id it has; an operator
    at the SpaceMouse sees no reply, only the teleop's log does."""
    head = "-".join(part for part in (task, rig) if part) or "episode"
    return f"{head}-{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%S.%f')[:-3]}"


def episode_request(
    action: str,
    *,
    episode_id: str | None = None,
    task: str = "",
    rig: str = "",
    seed: int = 0,
    control_hz: float = 20.0,
    success: bool = False,
) -> EpisodeRequest:
    """The request for ``action`` (start, stop, discard, status); a start without an id gets one."""
    if action not in COMMANDS:
        raise ValueError(f"unknown episode action {action!r}: choose one of {', '.join(COMMANDS)}")
    if action == "start" and not episode_id:
        episode_id = new_episode_id(task, rig)
    return EpisodeRequest(
        command=COMMANDS[action],
        episode_id=episode_id or "",
        task=task,
        rig=rig,
        seed=seed,
        control_hz=control_hz,
        success=success,
    )


def episode_control(bus: Bus, req: EpisodeRequest, timeout: float) -> EpisodeReply:
    """Send ``req`` to the recorder and return its reply (``reply.ok`` False: ``reply.error`` says why).

    Raises TimeoutError when no recorder answers within ``timeout`` seconds."""
    return EpisodeReply.FromString(bus.query(topics.EPISODE_CONTROL, req.SerializeToString(), timeout))


def describe_reply(action: str, reply: EpisodeReply) -> str:
    """What an operator reads after a successful ``action``: the state, and the file once closed."""
    m = reply.meta
    state = "recording" if reply.recording else "idle"
    text = f"{action}: ok ({state})" + (f" episode {m.episode_id}" if m.episode_id else "")
    if reply.recording:  # open: where it goes, what it holds so far, and what is wrong already
        if m.path:
            text += f"\n  -> {m.path}" + (f": {m.ticks} ticks so far, frames {dict(m.frames)}" if m.ticks else "")
        text += "".join(f"\n  warning: {flag}" for flag in m.flags)
    elif m.path:
        text += (
            f"\n  {m.path}: {m.ticks} ticks, {m.achieved_hz:.1f} Hz, frames {dict(m.frames)}, "
            f"drops {sum(m.drops.values())}" + (f", flags: {'; '.join(m.flags)}" if m.flags else "")
        )
    return text
