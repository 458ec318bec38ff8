"""Waiting, across threads or processes, for a condition the test can observe: the condition
is what proves that something happened; the interval only says how often it is looked at, and
the deadline only bounds how long a broken build makes the test wait."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(
    condition: Callable[[], bool], timeout_s: float = 60.0, interval_s: float = 0.05
) -> bool:
    """Whether ``condition()`` became true before ``timeout_s`` passed (looked at every
    ``interval_s`` seconds, and once more at the deadline)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            return condition()
        time.sleep(interval_s)
    return True
