"""Time: wall-clock capture stamps and a fixed-rate loop that reports overruns."""

from __future__ import annotations

import time


def now_ns() -> int:
    """Capture/receive time as Unix nanoseconds (what every Header.stamp_ns holds)."""
    return time.time_ns()


class Rate:
    """Sleep to keep a loop at ``hz``; counts ticks that started late (overruns).

    Unlike a naive ``sleep(period)``, the schedule is absolute, so jitter does not accumulate;
    after an overrun the schedule restarts from now instead of bursting to catch up.
    """

    def __init__(self, hz: float):
        if hz <= 0:
            raise ValueError(f"rate must be positive, got {hz}")
        self.period = 1.0 / hz
        self._next = time.monotonic() + self.period
        self.overruns = 0

    def sleep(self) -> None:
        now = time.monotonic()
        delay = self._next - now
        if delay > 0:
            time.sleep(delay)
            self._next += self.period
        else:
            self.overruns += 1
            self._next = now + self.period

    def reset(self) -> None:
        self._next = time.monotonic() + self.period
