"""D_O and D_E as one run keeps them: which tables its algorithm has, what D_E starts with, their locks.

`Tables` builds the online FIFO (`online_fifo.OnlineFifo`) and, for the algorithms that keep one,
D_E (`expert_heap.ExpertHeap`): the agent's best episodes by return, or SQIL's demonstrations,
loaded again at every start and never changed (reference.md). Both report episodes to the
run's labeller. It saves and restores the tables (`state`, `restore`) and describes D_E the way
every reply and the stats topic do (`expert_meta`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from silcr.common import protocol as P
from silcr.common.algorithms import algorithm
from silcr.common.config import Config
from silcr.common.demos import is_demonstration, load_demos
from silcr.common.envs import EnvSpec

from .expert_heap import ExpertHeap
from .labels import labeller_for
from .online_fifo import OnlineFifo

log = logging.getLogger("buffer")


class Tables:
    """D_O (`fifo`), D_E (`heap`, None for plain SAC) and the labeller they both report to."""

    def __init__(self, cfg: Config, spec: EnvSpec) -> None:
        self.algo = algorithm(cfg.algo)
        self.labeller = labeller_for(self.algo)
        self.fifo = OnlineFifo(cfg.online_capacity, spec.max_episode_steps, self.labeller)
        self.heap: ExpertHeap | None = None
        if self.algo.ranks_own_episodes:
            self.heap = ExpertHeap(cfg.expert_capacity, cfg.expert_admission, self.labeller, cfg.expert_refill)
        elif self.algo.needs_demos:
            demos = load_demos(Path(cfg.demos), spec)
            self.heap = ExpertHeap(sum(d.length for d in demos), watcher=self.labeller)
            for d in demos:
                self.heap.offer(d)
            log.info("D_E holds %d demonstration episodes (%d transitions, mean return %.1f) from %s",
                     self.heap.num_episodes, len(self.heap), np.mean([d.episode_return for d in demos]), cfg.demos)

    def add(self, ep: P.Episode) -> None:
        """A new episode of the agent's: into D_O, and offered to D_E when D_E ranks the agent's own."""
        self.fifo.add(ep)
        if self.algo.ranks_own_episodes:
            self.heap.offer(ep)

    def warm_start(self, demos: list[P.Episode]) -> None:
        """`--expert-init`: offer demonstrations to D_E, best first, before any episode of the agent's own.

        From then on they are ranked and evicted like any episode: better own
        episodes push them out, worse ones do not (`expert_init_transitions` counts what is left).
        """
        assert self.heap is not None and self.algo.ranks_own_episodes
        for d in sorted(demos, key=lambda e: e.episode_return, reverse=True):
            self.heap.offer(d)
        log.info("D_E starts with %d of %d demonstration episodes (%d transitions, returns %.1f to %.1f)",
                 self.heap.num_episodes, len(demos), len(self.heap), self.heap.min_return or 0.0,
                 self.heap.max_return or 0.0)

    def expert_init_transitions(self) -> int:
        """Demonstration transitions still in D_E (with --expert-init)."""
        if not self.algo.ranks_own_episodes:
            return 0
        return sum(e.length for e in self.heap.episodes() if is_demonstration(e))

    def expert_meta(self) -> dict[str, Any]:
        """D_E as every reply describes it (the learner's progress.csv columns)."""
        heap = self.heap
        return {
            "expert_transitions": len(heap) if heap is not None else 0,
            "expert_episodes": heap.num_episodes if heap is not None else 0,
            "expert_min_return": P.finite_or_none(heap.min_return) if heap is not None else None,
            "expert_max_return": P.finite_or_none(heap.max_return) if heap is not None else None,
            # D_E has turned an episode away for want of room: from then on its lowest return is a bar the agent set
            # (SQIL's demonstrations fill it exactly and are all it ever holds)
            "expert_full": heap is not None and (heap.filled or self.algo.needs_demos),
        }

    def locks(self) -> tuple:
        """The row storages' locks, in a fixed order: held while a checkpoint encodes an episode they hold."""
        return (self.fifo.storage.lock,) + ((self.heap.storage.lock,) if self.heap is not None else ())

    def state(self) -> dict[str, Any]:
        # SQIL's D_E is the demonstrations, loaded again from --demos at every start.
        return {"fifo": self.fifo.state(), "heap": self.heap.state() if self.algo.ranks_own_episodes else None}

    def restore(self, state: dict[str, Any]) -> None:
        self.fifo.restore(state["fifo"])
        if state["heap"] is not None and self.algo.ranks_own_episodes:
            self.heap.restore(state["heap"])

    def stats(self) -> dict[str, Any]:
        heap = self.heap
        return {
            "online_transitions": len(self.fifo),
            "online_episodes": self.fifo.num_episodes,
            "online_capacity": self.fifo.capacity,
            "online_evicted": self.fifo.evicted_episodes,
            "online_evicted_for_rows": self.fifo.evicted_for_rows,
            **self.expert_meta(),
            "expert_capacity": heap.capacity if heap is not None else 0,
            "expert_admitted": heap.admitted if heap is not None else 0,
            "expert_rejected": heap.rejected if heap is not None else 0,
            "expert_evicted": heap.evicted if heap is not None else 0,
            "expert_init_transitions": self.expert_init_transitions(),
        }
