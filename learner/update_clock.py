"""The learner's time: since it started, in updates, and the span from this start's first update to its last.

The rate (`updates_per_s`) and the duty cycle (the share of the time spent updating) go to the
stats topic and progress.csv; the span is logged at the end, where `silcr bench peer` reads it.
"""

from __future__ import annotations

import logging
import time

log = logging.getLogger("learner")


class UpdateClock:
    def __init__(self) -> None:
        self.started = time.monotonic()
        self.wall_before = 0.0
        self.update_time = 0.0
        self.first_update_at: float | None = None
        self.last_update_at = 0.0
        self.updates_this_start = 0

    def elapsed(self) -> float:
        return time.monotonic() - self.started

    def wall_time(self) -> float:
        """Seconds the run has run, every stretch added (`wall_before`: to the checkpoint this start resumed)."""
        return self.wall_before + self.elapsed()

    def counted(self, n: int, seconds: float) -> None:
        """`n` updates just took `seconds`."""
        self.update_time += seconds
        now = time.monotonic()
        if self.first_update_at is None:
            self.first_update_at = now - seconds
        self.last_update_at = now
        self.updates_this_start += n

    def rates(self, updates: int) -> dict[str, float]:
        elapsed = max(self.elapsed(), 1e-9)
        return {"updates_per_s": updates / elapsed, "duty_cycle": self.update_time / elapsed}

    def log_span(self) -> None:
        if self.first_update_at is None:
            return
        span = self.last_update_at - self.first_update_at
        log.info("training: %d updates in %.2f s from the first to the last (%.2f ms each), %.2f s of it in updates "
                 "(duty cycle %.3f)", self.updates_this_start, span, 1000 * span / self.updates_this_start,
                 self.update_time, self.update_time / max(span, 1e-9))
