"""D_O: the online FIFO of whole episodes, sampled uniformly by transition.

Episodes are copied into one ring of rows (`storage.RowStorage`) as they arrive,
so a batch is gathered with one fancy index per field. The `Episode` objects this
table keeps (for checkpoints and `episodes()`) view their rows; when an episode is
evicted its rows are about to be reused, so it first gets its own copy
(`storage.detach`): whoever still holds it, a checkpoint being written for
instance, keeps valid data.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from silcr.common.protocol import Batch, Episode

from .storage import Drawn, EpisodeIndex, RowStorage, Watcher, detach


class OnlineFifo:
    """First-in first-out store of at most `capacity` transitions.

    Oldest whole episodes are evicted to make room, so no partial episode is
    ever kept (the official code's deque of transitions can hold partial ones;
    the difference is at most one episode out of 1e6 transitions).

    The ring has `capacity + capacity // 32 + 2 * (max_episode_steps + 1)` rows:
    each episode needs one row more than its transitions, and an episode that would
    cross the ring's end starts again at row 0. If episodes average fewer than
    about 32 steps the rows run out first, and the oldest episodes are evicted
    before `capacity` transitions are stored (counted in `evicted_for_rows`).
    `max_episode_steps` is the longest episode to expect; the service passes the
    env's limit. Without it the ring reserves room for episodes as long as
    `capacity`, which can triple its rows. `watcher` is told of every episode that
    enters or leaves.
    """

    def __init__(self, capacity: int, max_episode_steps: int | None = None, watcher: Watcher | None = None) -> None:
        if capacity <= 0:
            raise ValueError(f"online capacity must be positive, got {capacity}")
        self.capacity = capacity
        longest = min(max_episode_steps or capacity, capacity)
        self.storage = RowStorage(capacity + capacity // 32 + 2 * (longest + 1))
        self.index = EpisodeIndex()
        self._episodes: deque[tuple[int, Episode]] = deque()  # (slot in the index, episode), oldest first
        self._head = 0  # next free row
        self.evicted_episodes = 0
        self.evicted_for_rows = 0
        self._watcher = watcher

    def __len__(self) -> int:
        return self.index.transitions

    @property
    def num_episodes(self) -> int:
        return len(self._episodes)

    def _place(self, rows: int) -> int | None:
        """First row of `rows` free consecutive rows at the head, or None if the oldest episode is in the way."""
        if not self._episodes:
            return 0
        tail = int(self.index.row[self._episodes[0][0]])
        if self._head > tail:  # live rows are [tail, head): free are [head, end) and [0, tail)
            if self._head + rows <= self.storage.rows:
                return self._head
            return 0 if rows <= tail else None
        return self._head if self._head + rows <= tail else None  # wrapped: free are [head, tail)

    def _evict_oldest(self) -> None:
        slot, old = self._episodes.popleft()
        self.index.remove(slot)
        with self.storage.lock:
            detach(old)
        self.evicted_episodes += 1
        if self._watcher is not None:
            self._watcher.left(old)

    def add(self, ep: Episode) -> None:
        """Store `ep`; its arrays become views of the ring (no other copy is kept)."""
        if ep.length > self.capacity:
            raise ValueError(f"episode of {ep.length} steps does not fit an online buffer of {self.capacity}")
        while self._episodes and len(self) + ep.length > self.capacity:
            self._evict_oldest()
        while (row := self._place(ep.length + 1)) is None:
            self._evict_oldest()
            self.evicted_for_rows += 1
        with self.storage.lock:
            self.storage.write(row, ep)
            self.storage.view(row, ep)
        self._episodes.append((self.index.add(row, ep), ep))
        self._head = row + ep.length + 1
        if self._watcher is not None:
            self._watcher.entered(ep)

    def episodes(self) -> list[Episode]:
        return [e[1] for e in self._episodes]

    def state(self) -> dict:
        """What a checkpoint keeps: the episodes, oldest first, and the counters."""
        return {"episodes": self.episodes(), "evicted_episodes": self.evicted_episodes,
                "evicted_for_rows": self.evicted_for_rows}

    def restore(self, state: dict) -> None:
        """Refill an empty FIFO from `state()`."""
        if self._episodes:
            raise RuntimeError("restore needs an empty online buffer")
        for ep in state["episodes"]:
            self.add(ep)
        self.evicted_episodes = int(state["evicted_episodes"])
        self.evicted_for_rows = int(state["evicted_for_rows"])

    def gather(self, n: int, rng: np.random.Generator, out: Batch[np.ndarray], rows: slice | np.ndarray,
               rewards: bool) -> Drawn:
        """Draw `n` transitions uniformly (with replacement) into `out`'s `rows`."""
        if not self._episodes:
            raise LookupError("online buffer is empty")
        return Drawn(self.index, self.index.gather(self.storage, n, rng, out, rows, rewards))

    def gather_recent(self, n: int, window: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """`n` (state, action) pairs drawn uniformly from the newest whole episodes that hold
        at least `window` transitions together (all of D_O if it holds fewer)."""
        if not self._episodes:
            raise LookupError("online buffer is empty")
        slots, held = [], 0
        for slot, ep in reversed(self._episodes):
            slots.append(slot)
            held += ep.length
            if held >= window:
                break
        return self.index.gather_state_actions(self.storage, n, rng, np.asarray(slots, np.int64))
