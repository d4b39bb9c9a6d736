"""D_E: the expert buffer of the best whole episodes by episodic return.

Admission rule (the project's, see docs/algorithm.md; the official code is
transition-level and can keep partial episodes):

1. An episode longer than M transitions is rejected.
2. If it fits (stored + its length <= M) it enters.
3. Otherwise it enters only if evicting stored episodes whose return is strictly
   lower than its own, lowest first (older first among equal returns), frees
   enough room; those are evicted and it enters. If not, it is rejected and
   nothing is evicted.

So ties never displace a stored episode, and a rejection never loses data.
"""

from __future__ import annotations

import heapq
import itertools

import numpy as np

from common.protocol import Episode


class ExpertHeap:
    def __init__(self, capacity: int) -> None:
        if capacity <= 0:
            raise ValueError(f"expert capacity must be positive, got {capacity}")
        self.capacity = capacity
        # Min-heap of (return, insertion order, episode): the root is the first to go.
        self._heap: list[tuple[float, int, Episode]] = []
        self._order = itertools.count()
        self._transitions = 0
        self._cum: np.ndarray | None = None
        self.admitted = 0
        self.rejected = 0
        self.evicted = 0

    def __len__(self) -> int:
        return self._transitions

    @property
    def num_episodes(self) -> int:
        return len(self._heap)

    @property
    def min_return(self) -> float | None:
        return self._heap[0][0] if self._heap else None

    @property
    def max_return(self) -> float | None:
        return max(e[0] for e in self._heap) if self._heap else None

    def offer(self, ep: Episode) -> bool:
        """Apply the admission rule; return whether `ep` entered."""
        need = self._transitions + ep.length - self.capacity
        if ep.length > self.capacity:
            self.rejected += 1
            return False
        if need > 0:
            # Pop strictly-worse episodes in eviction order until `ep` fits; undo if it never does.
            popped: list[tuple[float, int, Episode]] = []
            freed = 0
            while freed < need and self._heap and self._heap[0][0] < ep.episode_return:
                popped.append(heapq.heappop(self._heap))
                freed += popped[-1][2].length
            if freed < need:
                for entry in popped:
                    heapq.heappush(self._heap, entry)
                self.rejected += 1
                return False
            self._transitions -= freed
            self.evicted += len(popped)
        heapq.heappush(self._heap, (ep.episode_return, next(self._order), ep))
        self._transitions += ep.length
        self._cum = None
        self.admitted += 1
        return True

    def episodes(self) -> list[Episode]:
        return [e[2] for e in self._heap]

    def entries(self) -> list[tuple[float, int, Episode]]:
        """(return, admission order, episode) of every stored episode, for checkpoints."""
        return list(self._heap)

    def restore(self, entries: list[tuple[float, int, Episode]], admitted: int, rejected: int, evicted: int) -> None:
        """Refill an empty heap from `entries()` of a checkpoint, keeping the eviction order."""
        if self._heap:
            raise RuntimeError("restore needs an empty expert buffer")
        total = sum(e[2].length for e in entries)
        if total > self.capacity:
            raise ValueError(f"checkpointed D_E holds {total} transitions, more than M = {self.capacity}")
        self._heap = list(entries)
        heapq.heapify(self._heap)
        self._order = itertools.count(max((e[1] for e in entries), default=-1) + 1)
        self._transitions = total
        self._cum = None
        self.admitted, self.rejected, self.evicted = admitted, rejected, evicted

    def returns(self) -> list[float]:
        return [e[0] for e in self._heap]

    def sample_locations(self, n: int, rng: np.random.Generator) -> tuple[list[Episode], np.ndarray]:
        """Pick `n` transitions uniformly over all stored transitions (with replacement)."""
        if not self._heap:
            raise LookupError("expert buffer is empty")
        if self._cum is None:
            self._cum = np.cumsum([e[2].length for e in self._heap])
        g = rng.integers(0, self._transitions, size=n)
        idx = np.searchsorted(self._cum, g, side="right")
        t = g - np.where(idx > 0, self._cum[idx - 1], 0)
        return [self._heap[i][2] for i in idx], t
