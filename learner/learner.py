"""The learner without the network: the update (`update.py`) and its bookkeeping (`bookkeeping.py`).

`Learner.step(reply)` is what a learner does with one buffer reply: check it, train
on its batches, count. Tests drive it directly; `silcr train --single-process`
drives it with in-process clients, and `service.run_learner` over Zenoh.
"""

from __future__ import annotations

import time
from typing import Any

from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.weights_channel import WeightsServer

from .bookkeeping import Bookkeeping
from .update import Update


class Learner:
    def __init__(self, cfg: Config, spec: EnvSpec, weights: WeightsServer) -> None:
        self.update = Update(cfg, spec)
        self.books = Bookkeeping(cfg, spec, self.update, weights)

    def step(self, reply: P.BatchReply) -> None:
        """Train on one `ok` reply (one update per batch), then publish weights and checkpoint when due."""
        reply.header.check(self.books.algo, self.update.spec.env_id, self.update.spec.action_kind)
        self.books.see(reply.meta)
        self.books.note_rows(reply)
        t0 = time.monotonic()
        n = self.update.train(reply, self.books.updates)
        self.books.counted(n, time.monotonic() - t0)

    # The rest is the bookkeeping's, named here for the loops that drive a learner.
    def start(self) -> None:
        self.books.start()

    def see(self, meta: dict[str, Any]) -> None:
        self.books.see(meta)

    def poll(self) -> None:
        self.books.poll()

    def done(self, starved: bool) -> bool:
        return self.books.done(starved)

    def finish(self, finished: bool) -> bool:
        return self.books.finish(finished)

    def settle(self, finished: bool) -> bool:
        return self.books.settle(finished)

    def stats(self) -> dict[str, Any]:
        return self.books.stats()

    def record_scalars(self, stats: dict[str, Any]) -> None:
        self.books.record_scalars(stats)

    def sample_request(self) -> P.SampleRequest:
        return self.update.sample_request()

    def checkpoint(self) -> None:
        self.books.checkpoint()
