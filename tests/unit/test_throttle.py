"""A failure that repeats every tick is logged once, then once a while with how many it stands for."""

from __future__ import annotations

import logging

from services.core.throttle import Throttle


def test_a_repeated_reason_is_logged_once_a_while_with_its_count(caplog, monkeypatch):
    now = [100.0]
    monkeypatch.setattr("services.core.throttle.time.monotonic", lambda: now[0])
    say = Throttle(logging.getLogger("throttle-test"), every_s=5.0)
    with caplog.at_level("WARNING", logger="throttle-test"):
        said = [say(logging.WARNING, f"rejected command for tick {t}: step 1.{t} m") for t in range(20)]
        assert said == [True] + [False] * 19  # numbers aside, the same reason
        assert say(logging.WARNING, "malformed payload (12 bytes)")  # another reason: at once
        now[0] += 5.0
        assert say(logging.WARNING, "rejected command for tick 20: step 1.2 m")
        assert not say(logging.WARNING, "rejected command for tick 21: step 1.2 m")
    assert [r.getMessage() for r in caplog.records] == [
        "rejected command for tick 0: step 1.0 m",
        "malformed payload (12 bytes)",
        "rejected command for tick 20: step 1.2 m (19 more like it since the last line)",
    ]
