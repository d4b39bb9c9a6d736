"""D_O: the online FIFO of whole episodes, sampled uniformly by transition.

Episodes are stored as the `Episode` objects the codec decoded (each array once;
next observations are row t+1 of `obs`), so an episode that is also in the
expert heap costs no extra memory: both tables hold a reference.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from common.protocol import Episode


class OnlineFifo:
    """First-in first-out store of at most `capacity` transitions.

    Oldest whole episodes are evicted to make room, so no partial episode is
    ever kept (the official code's deque of transitions can hold partial ones;
    the difference is at most one episode out of 1e6 transitions).
    """

    def __init__(self, capacity: int) -> None:
        if capacity <= 0:
            raise ValueError(f"online capacity must be positive, got {capacity}")
        self.capacity = capacity
        self._episodes: deque[Episode] = deque()
        # Global index of each stored episode's first transition; transitions are
        # numbered by insertion, so the live range is [starts[0], _end).
        self._starts: deque[int] = deque()
        self._end = 0
        self._starts_array: np.ndarray | None = None
        self.evicted_episodes = 0

    def __len__(self) -> int:
        return self._end - self._starts[0] if self._starts else 0

    @property
    def num_episodes(self) -> int:
        return len(self._episodes)

    def add(self, ep: Episode) -> None:
        if ep.length > self.capacity:
            raise ValueError(f"episode of {ep.length} steps does not fit an online buffer of {self.capacity}")
        while self._episodes and len(self) + ep.length > self.capacity:
            self._episodes.popleft()
            self._starts.popleft()
            self.evicted_episodes += 1
        self._episodes.append(ep)
        self._starts.append(self._end)
        self._end += ep.length
        self._starts_array = None

    def episodes(self) -> list[Episode]:
        return list(self._episodes)

    def sample_locations(self, n: int, rng: np.random.Generator) -> tuple[list[Episode], np.ndarray]:
        """Pick `n` transitions uniformly (with replacement): their episodes and time steps."""
        if not self._episodes:
            raise LookupError("online buffer is empty")
        if self._starts_array is None:
            self._starts_array = np.fromiter(self._starts, dtype=np.int64, count=len(self._starts))
        starts = self._starts_array
        g = rng.integers(starts[0], self._end, size=n)
        idx = np.searchsorted(starts, g, side="right") - 1
        eps = [self._episodes[i] for i in idx]
        return eps, g - starts[idx]
