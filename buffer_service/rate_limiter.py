"""Samples-per-insert rate limiting, after Reverb's `SampleToInsertRatio`.

Inserts are environment transitions; samples are gradient updates (one batch =
one sample). The error `inserts * spi - samples` is kept inside a window of
`+-tolerance` around `min_size_to_sample * spi`, so after the warm-up the
learner does `spi` updates per environment step, whether 1 actor or 16 feed it:

* the learner may take a batch only while that keeps the error >= the window's
  lower edge (it is ahead otherwise and must wait);
* actors are paused once the error passes the upper edge (they are ahead) and
  resumed when it is back at the centre (hysteresis, so the pause signal does not
  flap on every batch).

The window is at least one update wide and, because the learner can always be
served part of a request, a paused actor always implies a learner that can
sample: the two sides can never both wait (tests/test_rate_limiter.py).

A budget spent during the warm-up (a run no longer than `min_size_to_sample`) pauses the actors
at the budget: no update will ever need those transitions, and the actors otherwise ran
unthrottled until the learner joined (5-9 s, twice the budget of a short run on a fast env).

The run's end (`final_inserts`, the run's step budget): with the hysteresis alone, actors
that outpace the learner sit at the window's top and are paused until the learner is back
at the centre, so the last `tolerance` updates of a run trained on tables that no longer
changed (in one MiniGrid run that turned a policy that reached the goal at every
evaluation into one that never did at the closing one). Over the last `2 * tolerance /
spi` inserts of the budget the actors keep pace instead: paused whenever they are ahead
of the ratio at all, resumed as soon as they are not. Data keeps arriving until the
learner's last update (the actors go on stepping past the budget if the learner still
has updates to make; those episodes are stored like any other), and the updates made
after the last episode are at most about one episode's worth (docs/algorithm.md, "Rate
control").
"""

from __future__ import annotations

import math


class SamplesPerInsertLimiter:
    def __init__(
        self,
        samples_per_insert: float = 1.0,
        min_size_to_sample: int = 10_240,
        tolerance: float = 2_000.0,
        throttle_inserts: bool = True,
        final_inserts: int | None = None,
    ) -> None:
        if not samples_per_insert > 0:
            raise ValueError(f"samples_per_insert must be > 0, got {samples_per_insert}")
        if min_size_to_sample < 0:
            raise ValueError(f"min_size_to_sample must be >= 0, got {min_size_to_sample}")
        if not tolerance >= 1.0:
            raise ValueError(
                f"tolerance must be >= 1 update, got {tolerance}: a narrower window could block both sides"
            )
        self.samples_per_insert = float(samples_per_insert)
        self.min_size_to_sample = int(min_size_to_sample)
        self.tolerance = float(tolerance)
        self.throttle_inserts = throttle_inserts
        self.final_inserts = final_inserts
        self.inserts = 0
        self.samples = 0
        self._paused = False

    @property
    def centre(self) -> float:
        return self.min_size_to_sample * self.samples_per_insert

    @property
    def error(self) -> float:
        return self.inserts * self.samples_per_insert - self.samples

    def record_insert(self, transitions: int) -> None:
        self.inserts += transitions

    def warming_up(self) -> bool:
        # The official code trains once D_O holds *more than* 10,240 transitions.
        return self.inserts <= self.min_size_to_sample

    def available(self) -> int:
        """How many samples (updates) the learner may take now without leaving the window."""
        if self.warming_up():
            return 0
        return max(0, math.floor(self.error - (self.centre - self.tolerance)))

    def due(self) -> int:
        """How many samples bring the error back to the window's centre: the updates the inserts so far
        are due at exactly `samples_per_insert`, never ahead (the single-process loop takes these)."""
        if self.warming_up():
            return 0
        return max(0, math.floor(self.error - self.centre))

    def record_sample(self, n: int) -> None:
        self.samples += n

    def at_the_end(self) -> bool:
        """Within the last 2 * tolerance / spi inserts of the run's budget (or past it): actors keep pace."""
        return (self.final_inserts is not None
                and self.inserts >= self.final_inserts - 2 * self.tolerance / self.samples_per_insert)

    def inserts_paused(self) -> bool:
        """Whether actors should pause now (updates the hysteresis state)."""
        if not self.throttle_inserts:
            self._paused = False
        elif self.warming_up():
            # No update can need more data than the budget: a budget spent before the learner may start (a run
            # shorter than --learning-starts, a learner that has not joined yet) pauses the actors there.
            self._paused = self.final_inserts is not None and self.inserts >= self.final_inserts
        elif self.at_the_end():
            self._paused = self.error > self.centre
        elif self._paused:
            self._paused = self.error > self.centre
        else:
            self._paused = self.error > self.centre + self.tolerance
        return self._paused

    def state(self) -> dict:
        return {"inserts": self.inserts, "samples": self.samples, "paused": self._paused}

    def restore(self, state: dict) -> None:
        self.inserts, self.samples, self._paused = int(state["inserts"]), int(state["samples"]), bool(state["paused"])

    def observed_samples_per_insert(self) -> float:
        after_warmup = self.inserts - self.min_size_to_sample
        return self.samples / after_warmup if after_warmup > 0 else 0.0
