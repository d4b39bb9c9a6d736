"""A bandwidth policy for the weights' fan-out to the actors."""

from __future__ import annotations

import time
from typing import Callable


class FanoutPacer:
    """Keeps the weights' fan-out (bytes x actors per second) within a budget.

    Each publication goes to every actor, so its cost is its size times the actors alive. After
    sending one, the next may go `actors x size / budget` seconds later; what the learner publishes
    before then waits, and a newer set replaces a waiting one (the actors keep only the newest anyway).
    A budget of 0 sends everything at once.
    """

    def __init__(self, budget_bytes_per_s: float, actors: Callable[[], int],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.budget = budget_bytes_per_s
        self._actors, self._clock = actors, clock
        self._next_at = float("-inf")
        self.waiting: bytes | None = None
        self.held = 0  # publications that waited for the budget
        self.replaced = 0  # waiting publications a newer one replaced before they went out

    def offer(self, payload: bytes, final: bool = False) -> bytes | None:
        """The payload to send now, or None if it must wait (`due()` hands it over later)."""
        if final or self.budget <= 0 or self._clock() >= self._next_at:
            self.waiting = None
            return self._sent(payload)
        self.held += 1
        self.replaced += self.waiting is not None
        self.waiting = payload
        return None

    def due(self) -> bytes | None:
        """The waiting payload once the budget allows it."""
        if self.waiting is None or self._clock() < self._next_at:
            return None
        payload, self.waiting = self.waiting, None
        return self._sent(payload)

    def _sent(self, payload: bytes) -> bytes:
        if self.budget > 0:
            self._next_at = self._clock() + max(1, self._actors()) * len(payload) / self.budget
        return payload
