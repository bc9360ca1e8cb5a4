"""When an episode counts as a success: one rule for the session that judges it and the sim that
stops on it (``SimControlRequest.settle_ticks``), so a demo ends at the same tick whoever looks."""

from __future__ import annotations


class SuccessWatch:
    """An episode's success as the session judges it, from the task state of every tick.

    Success is the task's condition holding for ``settle_ticks`` consecutive ticks (so demos end
    at rest); once reached it stays reached, as in robomimic's rollouts, which stop at the first
    success. A lift whose cube slips a tick after that is a success, not a failure judged by the
    state at the moment the pause lands.
    """

    def __init__(self, settle_ticks: int):
        self.settle_ticks = settle_ticks
        self.tick = -1  # the last tick seen
        self.since: int | None = None  # first tick of the current run of successful ticks
        self.held = False

    def update(self, tick: int, success: bool) -> None:
        self.tick = tick
        if not success:
            self.since = None
            return
        if self.since is None:
            self.since = tick
        if tick - self.since >= self.settle_ticks:
            self.held = True
