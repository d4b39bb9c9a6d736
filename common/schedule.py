"""Wall-clock schedules: "every N seconds" for stats messages and buffer checkpoints."""

from __future__ import annotations

import time


class Every:
    """Due every `seconds` (never when `seconds` <= 0 and `never_if_zero`), first at start or after one interval."""

    def __init__(self, seconds: float, first_now: bool = True, never_if_zero: bool = False) -> None:
        self.seconds = seconds
        self.off = never_if_zero and seconds <= 0
        self.next = time.monotonic() + (0.0 if first_now else seconds)

    def due(self, now: float | None = None) -> bool:
        """Whether it is due at `now`; if so, the next time is one interval later."""
        if self.off:
            return False
        now = time.monotonic() if now is None else now
        if now < self.next:
            return False
        self.next = now + self.seconds
        return True

    def remaining(self, now: float | None = None) -> float:
        if self.off:
            return float("inf")
        return max(0.0, self.next - (time.monotonic() if now is None else now))
