"""Logging a failure that repeats every tick without a line per tick."""

from __future__ import annotations

import logging
import re
import threading
import time


class Throttle:
    """Log each reason at once, then the same reason again once every ``every_s`` at the earliest,
    with how many times it happened since the last line. A reason is the message with its numbers
    blanked out (a tick or a sequence number that changes every time is the same reason)."""

    def __init__(self, logger: logging.Logger, every_s: float = 5.0):
        self.log = logger
        self.every_s = every_s
        self._last: dict[str, float] = {}  # reason -> when it was last logged (monotonic)
        self._unsaid: dict[str, int] = {}  # reason -> times it happened since
        self._lock = threading.Lock()  # (called from zenoh's threads)

    def __call__(self, level: int, message: str) -> bool:
        """Log ``message`` at ``level`` unless its reason was logged less than ``every_s`` ago;
        True when it was logged."""
        reason = re.sub(r"\d+(\.\d+)?", "#", message)
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(reason, -self.every_s) < self.every_s:
                self._unsaid[reason] = self._unsaid.get(reason, 0) + 1
                return False
            more = self._unsaid.pop(reason, 0)
            self._last[reason] = now
            if len(self._last) > 256:  # (reasons that vary in words, not numbers: keep the newest)
                oldest = min(self._last, key=self._last.__getitem__)
                del self._last[oldest]
                self._unsaid.pop(oldest, None)
        self.log.log(level, "%s%s", message, f" ({more} more like it since the last line)" if more else "")
        return True
