"""D_E: the expert buffer of the best whole episodes by episodic return.

Admission rule (the project's, see docs/algorithm.md; the official code is
transition-level and can keep partial episodes):

1. An episode longer than M transitions is rejected.
2. If it fits (stored + its length <= M) it enters; but once D_E has been full
   (an episode has found no room), with `refill="better"` (the default) only if
   its key is strictly above the lowest stored, so the room left over by
   evicting whole episodes never takes a worse episode and the lowest stored
   key never falls, as in the official code's full heap. `refill="any"` (runs
   recorded before the option) lets any episode that fits enter.
3. Otherwise it enters only if evicting stored episodes whose key is strictly
   lower than its own, lowest first (older first among equal keys), frees
   enough room; those are evicted and it enters. If not, it is rejected and
   nothing is evicted.

The key is the episode's return (`admission="return"`, SILCR). The control
`admission="recent"` keys episodes by arrival instead, so every episode enters and
the oldest leave: D_E then holds the latest M transitions, with the same size and
the same constant rewards but no ranking (docs/algorithm.md, "The ranking at work").
So ties never displace a stored episode, and a rejection never loses data.

Admitted episodes are copied into this table's own rows (`storage.RowStorage`),
appended at the end; rows freed by evictions are reclaimed by compacting when the
end is reached. An expert episode that is also still in D_O is therefore stored
twice, at most M transitions (5% of the paper's Humanoid buffers), so that both
tables sample with one vectorised gather (docs/performance.md).
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools

import numpy as np

from silcr.common.config import EXPERT_ADMISSIONS, EXPERT_REFILLS
from silcr.common.protocol import Batch, Episode

from .storage import Drawn, EpisodeIndex, RowStorage, Watcher, detach


class AdmissionMismatch(ValueError):
    """A saved D_E kept by another rule than this one's."""


class ExpertHeap:
    """D_E: at most `capacity` transitions of whole episodes, admitted by the rule above. `watcher`
    is told of every episode that enters or leaves."""

    def __init__(self, capacity: int, admission: str = "return", watcher: Watcher | None = None,
                 refill: str = "better") -> None:
        if capacity <= 0:
            raise ValueError(f"expert capacity must be positive, got {capacity}")
        if admission not in EXPERT_ADMISSIONS:
            raise ValueError(f"admission must be one of {EXPERT_ADMISSIONS}, got {admission!r}")
        if refill not in EXPERT_REFILLS:
            raise ValueError(f"refill must be one of {EXPERT_REFILLS}, got {refill!r}")
        self.capacity = capacity
        self.admission = admission
        self.refill = refill
        self.filled = False  # an episode has found no room: from then on rule 2 asks `refill`
        # Min-heap of (key, insertion order, episode): the root is the first to go.
        self._heap: list[tuple[float, int, Episode]] = []
        self._order = itertools.count()
        self._transitions = 0
        self.storage = RowStorage(capacity + capacity // 8 + 2)
        self.index = EpisodeIndex()
        self._where: dict[int, tuple[int, Episode]] = {}  # id(stored episode) -> (slot in the index, it)
        self._end = 0  # rows [0, _end) are in use or freed by evictions
        self.admitted = 0
        self.rejected = 0
        self.evicted = 0
        self._return_range: tuple[float, float] | None = None  # (min, max) of stored returns, cached
        self._watcher = watcher

    def __len__(self) -> int:
        return self._transitions

    @property
    def num_episodes(self) -> int:
        return len(self._heap)

    def _returns(self) -> tuple[float, float] | None:
        if self._return_range is None and self._heap:
            returns = [e[2].episode_return for e in self._heap]
            self._return_range = (min(returns), max(returns))
        return self._return_range

    @property
    def min_return(self) -> float | None:
        r = self._returns()
        return r[0] if r else None

    @property
    def max_return(self) -> float | None:
        r = self._returns()
        return r[1] if r else None

    def key(self, ep: Episode, order: int) -> float:
        """What D_E ranks `ep` by: its return, or (the recency control) its arrival."""
        return ep.episode_return if self.admission == "return" else float(order)

    def offer(self, ep: Episode) -> bool:
        """Apply the admission rule; return whether `ep` entered."""
        need = self._transitions + ep.length - self.capacity
        if ep.length > self.capacity:
            self.rejected += 1
            return False
        order = next(self._order)
        key = self.key(ep, order)
        if need <= 0 and self.filled and self.refill == "better" and self._heap and key <= self._heap[0][0]:
            # Room left over by whole-episode evictions: not for an episode the full D_E would refuse.
            self.rejected += 1
            return False
        if need > 0:
            self.filled = True
            # Pop strictly-worse episodes in eviction order until `ep` fits; undo if it never does.
            popped: list[tuple[float, int, Episode]] = []
            freed = 0
            while freed < need and self._heap and self._heap[0][0] < key:
                popped.append(heapq.heappop(self._heap))
                freed += popped[-1][2].length
            if freed < need:
                for entry in popped:
                    heapq.heappush(self._heap, entry)
                self.rejected += 1
                return False
            self._transitions -= freed
            self.evicted += len(popped)
            for _, _, old in popped:
                self._release(old)
        stored = self._store(ep)
        heapq.heappush(self._heap, (key, order, stored))
        self._transitions += ep.length
        self.admitted += 1
        self._return_range = None
        return True

    def _store(self, ep: Episode) -> Episode:
        """A copy of `ep` in this table's rows (the caller's episode is left as it is)."""
        rows = ep.length + 1
        if self._end + rows > self.storage.rows:
            self._compact()
            if self._end + rows > self.storage.rows:
                self.storage.grow(self._end + rows + self.capacity // 8)
                with self.storage.lock:  # the stored episodes still view the old arrays
                    for slot, stored in self._where.values():
                        self.storage.view(int(self.index.row[slot]), stored)
        stored = dataclasses.replace(ep)
        with self.storage.lock:
            self.storage.write(self._end, stored)
            self.storage.view(self._end, stored)
        self._where[id(stored)] = (self.index.add(self._end, stored), stored)
        self._end += rows
        if self._watcher is not None:
            self._watcher.entered(stored)
        return stored

    def _release(self, ep: Episode) -> None:
        slot, _ = self._where.pop(id(ep))
        self.index.remove(slot)
        with self.storage.lock:
            detach(ep)  # its rows will be reused by the next compaction
        if self._watcher is not None:
            self._watcher.left(ep)

    def _compact(self) -> None:
        """Move the stored episodes to the front, in row order, so the free rows are at the end."""
        end = 0
        with self.storage.lock:
            for slot, ep in sorted(self._where.values(), key=lambda v: self.index.row[v[0]]):
                n, row = ep.length + 1, int(self.index.row[slot])
                if row != end:  # moving down in row order: numpy copies overlapping slices safely
                    st = self.storage
                    st.obs[end : end + n] = st.obs[row : row + n]
                    st.actions[end : end + n] = st.actions[row : row + n]
                    st.rewards[end : end + n] = st.rewards[row : row + n]
                    st.view(end, ep)
                    self.index.move(slot, end)
                end += n
        self._end = end

    def episodes(self) -> list[Episode]:
        return [e[2] for e in self._heap]

    def state(self) -> dict:
        """What a checkpoint keeps: every entry with its key and admission order (the eviction order), and the counters."""
        return {"admission": self.admission, "entries": [[ep, key, order] for key, order, ep in self._heap],
                "admitted": self.admitted, "rejected": self.rejected, "evicted": self.evicted, "filled": self.filled}

    def restore(self, state: dict) -> None:
        """Refill an empty D_E from `state()`, keeping the eviction order."""
        if self._heap:
            raise RuntimeError("restore needs an empty expert buffer")
        if state["admission"] != self.admission:
            raise AdmissionMismatch(f"the checkpointed D_E ranks episodes by {state['admission']}, this run by "
                                    f"{self.admission} (--expert-admission)")
        entries = [(float(key), int(order), ep) for ep, key, order in state["entries"]]
        total = sum(e[2].length for e in entries)
        if total > self.capacity:
            raise ValueError(f"checkpointed D_E holds {total} transitions, more than M = {self.capacity}")
        self._heap = [(key, order, self._store(ep)) for key, order, ep in entries]
        heapq.heapify(self._heap)
        self._order = itertools.count(max((e[1] for e in entries), default=-1) + 1)
        self._transitions = total
        self._return_range = None
        self.admitted, self.rejected, self.evicted = int(state["admitted"]), int(state["rejected"]), int(state["evicted"])
        # Checkpoints before `filled` was kept: an eviction shows D_E was full (a rejection may have been for length).
        self.filled = bool(state.get("filled", self.evicted > 0))

    def gather(self, n: int, rng: np.random.Generator, out: Batch[np.ndarray], rows: slice | np.ndarray,
               rewards: bool) -> Drawn:
        """Draw `n` transitions uniformly over all stored transitions (with replacement) into `out`'s `rows`."""
        if not self._heap:
            raise LookupError("expert buffer is empty")
        return Drawn(self.index, self.index.gather(self.storage, n, rng, out, rows, rewards))

    def gather_state_actions(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """`n` (state, action) pairs drawn uniformly over all stored transitions."""
        if not self._heap:
            raise LookupError("expert buffer is empty")
        return self.index.gather_state_actions(self.storage, n, rng)
