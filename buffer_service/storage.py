"""Contiguous episode storage shared by D_O and D_E: rows of arrays plus a per-episode index.

Both tables keep their transitions in preallocated row arrays (`RowStorage`) and
describe each stored episode by one slot of `EpisodeIndex` (first row, length,
flags, policy version). Sampling a batch is then one `searchsorted` and one fancy
index per field, with no Python loop over rows: what a GPU learner asking for
thousands of batches a second needs (docs/performance.md).

An episode occupies `length + 1` consecutive rows: row t holds s_t, a_t and r_t,
and the last row holds only the final observation, so next observations are the
following row and never stored twice.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from silcr.common.protocol import Batch, Episode


class Watcher(Protocol):
    """Told of every episode that enters or leaves a table (the labeller keeps what it needs from them)."""

    def entered(self, ep: Episode) -> None: ...

    def left(self, ep: Episode) -> None: ...


class RowStorage:
    """Observation, action and reward rows, allocated at the first episode (its shapes fix the widths)."""

    def __init__(self, rows: int) -> None:
        self.rows = rows
        self.obs: np.ndarray | None = None
        self.actions: np.ndarray | None = None
        self.rewards: np.ndarray | None = None
        # Held while rows are rewritten or an episode's arrays are swapped for copies,
        # and by the checkpoint writer while it encodes one episode: a checkpoint
        # written in the background never reads rows that are being overwritten.
        self.lock = threading.Lock()

    def _allocate(self, ep: Episode) -> None:
        self.obs = np.empty((self.rows, ep.obs.shape[1]), np.float32)
        kind = np.int64 if ep.action_kind == "discrete" else np.float32  # action indices, or continuous actions
        self.actions = np.zeros((self.rows, ep.actions.shape[1]), kind)
        self.rewards = np.zeros(self.rows, np.float32)

    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.obs, self.actions, self.rewards) if a is not None)

    def write(self, row: int, ep: Episode) -> None:
        if self.obs is None:
            self._allocate(ep)
        n = ep.length
        self.obs[row : row + n + 1] = ep.obs
        self.actions[row : row + n] = ep.actions
        self.rewards[row : row + n] = ep.rewards

    def view(self, row: int, ep: Episode) -> Episode:
        """`ep` with its arrays replaced by views of its rows here (no copy)."""
        n = ep.length
        ep.obs = self.obs[row : row + n + 1]
        ep.actions = self.actions[row : row + n]
        ep.rewards = self.rewards[row : row + n]
        return ep

    def grow(self, rows: int) -> None:
        with self.lock:
            self.rows = rows
            if self.obs is not None:
                self.obs = _resized(self.obs, rows)
                self.actions = _resized(self.actions, rows)
                self.rewards = _resized(self.rewards, rows)


def _resized(a: np.ndarray, rows: int) -> np.ndarray:
    out = np.zeros((rows, *a.shape[1:]), a.dtype)
    out[: len(a)] = a
    return out


def detach(ep: Episode) -> None:
    """Give `ep` its own copies of its arrays, before the rows it views are reused."""
    ep.obs, ep.actions, ep.rewards = ep.obs.copy(), ep.actions.copy(), ep.rewards.copy()


class EpisodeIndex:
    """Per-episode columns indexed by slot (first row, length, how it ended, the policy version
    that acted, its return); sampling is uniform over all live transitions.

    Free slots have length 0, so they are never drawn. The cumulative lengths are
    recomputed (vectorised) only when the set of episodes changed since the last draw.
    """

    def __init__(self, slots: int = 64) -> None:
        self.row = np.zeros(slots, np.int64)
        self.length = np.zeros(slots, np.int64)
        self.terminated = np.zeros(slots, bool)
        self.truncated = np.zeros(slots, bool)
        self.version = np.zeros(slots, np.int64)
        self.episode_return = np.zeros(slots, np.float64)
        self._free = list(range(slots - 1, -1, -1))
        self._cum: np.ndarray | None = None
        self.transitions = 0

    def add(self, row: int, ep: Episode) -> int:
        if not self._free:
            self._grow()
        slot = self._free.pop()
        self.row[slot] = row
        self.length[slot] = ep.length
        self.terminated[slot] = ep.terminated
        self.truncated[slot] = ep.truncated
        self.version[slot] = ep.policy_version
        self.episode_return[slot] = ep.episode_return
        self.transitions += ep.length
        self._cum = None
        return slot

    def remove(self, slot: int) -> None:
        self.transitions -= int(self.length[slot])
        self.length[slot] = 0
        self._free.append(slot)
        self._cum = None

    def move(self, slot: int, row: int) -> None:
        self.row[slot] = row

    def _grow(self) -> None:
        n = len(self.row)
        for name in ("row", "length", "terminated", "truncated", "version", "episode_return"):
            setattr(self, name, np.concatenate([getattr(self, name), np.zeros_like(getattr(self, name))]))
        self._free = list(range(2 * n - 1, n - 1, -1))
        self._cum = None

    def _draw(self, n: int, rng: np.random.Generator,
              slots: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(slot, step in the episode, row) of `n` transitions drawn uniformly (with replacement)
        over the episodes in `slots` (default: every stored one)."""
        if slots is None:
            if self._cum is None:
                self._cum = np.cumsum(self.length)
            cum, high = self._cum, self.transitions
        else:
            cum = np.cumsum(self.length[slots])
            high = int(cum[-1])
        g = rng.integers(0, high, size=n)
        i = np.searchsorted(cum, g, side="right")
        slot = i if slots is None else slots[i]
        t = g - (cum[i] - self.length[slot])
        return slot, t, self.row[slot] + t

    def gather(self, storage: RowStorage, n: int, rng: np.random.Generator, out: Batch[np.ndarray],
               rows: slice | np.ndarray, rewards: bool) -> np.ndarray:
        """Draw `n` transitions uniformly (with replacement) into `out`'s `rows` (the env's rewards
        too if `rewards`); return the slot of each one's episode."""
        slot, t, r = self._draw(n, rng)
        out.obs[rows] = storage.obs[r]
        out.next_obs[rows] = storage.obs[r + 1]
        out.actions[rows] = storage.actions[r]
        if rewards:
            out.rewards[rows] = storage.rewards[r]
        last = t == self.length[slot] - 1
        terminated = self.terminated[slot]
        out.terminated[rows] = last & terminated
        # gymnasium may report both on the same step; termination wins (no bootstrap).
        out.truncated[rows] = last & self.truncated[slot] & ~terminated
        out.policy_version[rows] = self.version[slot]
        return slot

    def gather_state_actions(self, storage: RowStorage, n: int, rng: np.random.Generator,
                             slots: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`n` (state, action) pairs drawn uniformly over the transitions of `slots` (default: all)."""
        r = self._draw(n, rng, slots)[2]
        return storage.obs[r], storage.actions[r]


@dataclass
class Drawn:
    """The rows one table put into a batch, described by their episodes (what a labeller needs)."""

    index: EpisodeIndex
    slots: np.ndarray

    @property
    def episode_return(self) -> np.ndarray:
        return self.index.episode_return[self.slots]

    @property
    def episode_length(self) -> np.ndarray:
        return self.index.length[self.slots]
