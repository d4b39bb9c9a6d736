"""The learner without the network: its parts wired once, and what it does with one buffer reply.

`Learner(cfg, spec, weights)` is the one place that builds a learner's parts (Acme's builder in
spirit) and restores them from the run's checkpoint: the update (`update.py`: networks, optimisers,
the gradient steps) and its bookkeeping (`bookkeeping.py`: counters, schedules, evaluations,
checkpoints, stats). `step(reply)` checks a reply, trains on its batches and counts. The loops that
drive a learner (`service.run_learner` over Zenoh, `deploy.single_process` in one process, tests)
talk to the parts themselves: `learner.books.poll()`, `learner.update.sample_request()`.
"""

from __future__ import annotations

import logging
import time

from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.weights_channel import WeightsServer

from .bookkeeping import Bookkeeping
from .checkpoint import CheckpointError, LearnerCheckpoints
from .update import Update

log = logging.getLogger("learner")


class Learner:
    def __init__(self, cfg: Config, spec: EnvSpec, weights: WeightsServer) -> None:
        """The parts, restored from the run's checkpoint with --resume; CheckpointError (no file touched) when it
        does not fit this run."""
        self.update = Update(cfg, spec)
        checkpoints = LearnerCheckpoints(cfg.run_dir, cfg.resume)
        payload = checkpoints.load()
        if payload is not None:  # the networks first: a checkpoint that does not fit stops here, no file touched
            try:
                self.update.restore(payload, checkpoints.path)
            except (ValueError, KeyError, RuntimeError) as e:  # other networks, another --algo, missing tensors
                raise CheckpointError(f"{checkpoints.path} does not fit this run: {e}") from None
        self.books = Bookkeeping(cfg, spec, self.update, weights, checkpoints)
        if payload is not None:
            self.books.restore(payload["counters"])
            log.info("resumed from %s: %d updates, policy version %d", checkpoints.path, self.books.updates,
                     self.books.policy_version)
        elif cfg.resume:
            log.info("--resume: no checkpoint at %s yet; starting fresh", checkpoints.path)

    def step(self, reply: P.BatchReply) -> None:
        """Train on one `ok` reply (one update per batch), then publish weights and checkpoint when due."""
        reply.header.check(self.books.algo, self.update.spec.env_id, self.update.spec.action_kind)
        self.books.see(reply)
        self.books.note_rows(reply)
        t0 = time.monotonic()
        n = self.update.train(reply, self.books.updates)
        self.books.counted(n, time.monotonic() - t0)
