"""Sample requests answered: batches composed from D_O and D_E as the rate limiter allows, and counted.

`Sampler.answer(payload)` decodes a learner's request, refuses one that is malformed, too large
for one reply, or (over Zenoh) not from the run's learner, and `sample` composes up to the
requested batches (`batches.compose_batches`; GASIL's discriminator rows beside them). On a
learner's first request the limiter takes its count of updates (`take_learner_count`). Every
request, refusal and not-ready reply is counted and published; the counts save and restore.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Container
from typing import Any

import numpy as np

from silcr.common import protocol as P
from silcr.common.envs import EnvSpec

from .batches import compose_batches, discriminator_rows
from .intake import Intake
from .rate_limiter import SamplesPerInsertLimiter
from .tables import Tables

log = logging.getLogger("buffer")


class Sampler:
    COUNTERS = ("batches_served", "sample_requests", "sample_requests_rejected", "not_ready_replies")

    def __init__(self, tables: Tables, intake: Intake, limiter: SamplesPerInsertLimiter, spec: EnvSpec,
                 rng: np.random.Generator) -> None:
        """`intake`: read only, for what every reply says of the episodes received (`describe`)."""
        self.tables, self.intake, self.limiter, self.spec, self.rng = tables, intake, limiter, spec, rng
        self.batches_served = 0
        self.sample_requests = 0
        self.sample_requests_rejected = 0
        self.not_ready_replies = 0
        self.request_rejections: collections.Counter[str] = collections.Counter()  # by reason
        # The learner whose update count the limiter last took (not checkpointed: a restarted buffer
        # takes the count again from the learner's first request) and how often that changed it.
        self.counted_learner: int | None = None
        self.limiter_realigned = 0

    def answer(self, payload: bytes | None, learners: Container[int] | None = None) -> P.BatchReply:
        """Answer one sample query; raise `ProtocolError` for a malformed request.

        With `learners` (over Zenoh: the incarnations of the learners alive now), a
        request that names none of them is refused: only the run's learner spends the
        samples-per-insert budget, so an outside client's sampling cannot starve it.
        """
        try:
            if payload is None:
                raise P.ProtocolError("bad_request", "sample query carries no payload")
            req = P.SampleRequest.decode(payload)
            if learners is not None and req.learner not in learners:
                raise P.ProtocolError("not_the_learner", "only the run's learner samples: the request names "
                                      + (f"learner {req.learner}, which is not alive" if req.learner else "no learner")
                                      + " (docs/protocol.md, 'Sample request')")
        except P.ProtocolError as e:
            self.sample_requests += 1
            self._refused(e)
            raise
        if req.learner and req.updates is not None:
            self.take_learner_count(req.learner, req.updates)
        return self.sample(req)

    def take_learner_count(self, learner: int, updates: int) -> None:
        """On a learner's first request, make the limiter's count of updates served its count of updates made.

        Every batch served is one update, so the two counts agree until a component
        restarts from a checkpoint: a learner restarted from its last checkpoint (every
        `--checkpoint-interval` updates) lost the updates since, which the limiter still
        counts as served (a distributed run made them up with as many env steps past its
        budget, a single-process one ended that many updates short); a buffer restarted
        from its last checkpoint counts fewer than the learner made. The
        learner's count is the one its weights have seen, so the limiter takes it: lost
        updates are served again, and the actors re-collect what the buffer lost before
        the learner trains further. Later requests of the same learner change nothing
        (their counts lag the batches in flight).
        """
        if learner == self.counted_learner:
            return
        self.counted_learner = learner
        served = self.limiter.samples
        if served != updates:
            self.limiter_realigned += 1
            log.info("learner %d has made %d updates, the limiter counted %d served; it takes the learner's count, "
                     "so %d updates are %s", learner, updates, served, abs(served - updates),
                     "served again" if served > updates else "not served twice")
            self.limiter.samples = updates

    def describe(self) -> dict[str, Any]:
        """What every reply says of the buffer: its algorithm (the learner checks it runs the same), the
        transitions received, D_E, and the actors' recent returns."""
        return {"algo": self.tables.algo.name, "env_steps": self.intake.transitions_received,
                "episodes_received": self.intake.episodes_received,
                "online_transitions": len(self.tables.fifo)} | self.tables.expert_meta() | self.intake.rollout_meta()

    def _refused(self, e: P.ProtocolError) -> None:
        self.sample_requests_rejected += 1
        self.request_rejections[e.reason] += 1

    def sample(self, req: P.SampleRequest, keep_ratio: bool = False) -> P.BatchReply:
        """Up to `req.batches` batches, as many as the rate limiter allows now.

        Over the network the learner may run up to the limiter's tolerance ahead of
        the ratio (so it never waits on a round trip); `keep_ratio` serves only the
        updates the inserted transitions are due, as the single-process loop wants.
        """
        self.sample_requests += 1
        heap, algo = self.tables.heap, self.tables.algo
        rows = req.batches * (req.batch_size + 2 * req.disc_batch_size)
        row_bytes = 4 * (2 * self.spec.obs_dim + 1) + self.spec.action_bytes + 2 + 8  # obs, next_obs, reward, action, flags, version
        if rows * row_bytes > P.MAX_REPLY_BYTES:
            e = P.ProtocolError("bad_request", f"a reply of {rows} rows would be {rows * row_bytes / 2**20:.0f} MiB, more "
                                               f"than {P.MAX_REPLY_BYTES >> 20} MiB: at most "
                                               f"{P.MAX_REPLY_BYTES // row_bytes} rows per request on {self.spec.env_id}")
            self._refused(e)
            raise e
        if req.disc_batch_size and heap is None:
            e = P.ProtocolError("bad_request", f"disc_batch_size: this buffer keeps no D_E (--algo {algo.name})")
            self._refused(e)
            raise e
        if self.limiter.warming_up() or (heap is not None and heap.num_episodes == 0):
            self.not_ready_replies += 1
            return P.BatchReply("not_ready", self.describe(), reason="warmup", retry_after_ms=200)
        k = min(req.batches, self.limiter.due() if keep_ratio else self.limiter.available())
        if k == 0:
            self.not_ready_replies += 1
            return P.BatchReply("not_ready", self.describe(), reason="rate_limited", retry_after_ms=20)
        mixed_heap = heap if algo.mixes_expert else None
        batch = compose_batches(self.tables.fifo, mixed_heap, k, req.batch_size, self.rng, self.tables.labeller,
                                self.spec.obs_dim, self.spec.act_dim, self.spec.action_dtype)
        disc = None
        if req.disc_batch_size:
            assert heap is not None
            disc = discriminator_rows(self.tables.fifo, heap, k * req.disc_batch_size, req.recent_window, self.rng)
        self.limiter.record_sample(k)
        self.batches_served += k
        layout = P.BatchHeader(algo.name, batches=k, batch_size=req.batch_size,
                               online_rows=P.BatchHeader.online_rows_for(req.batch_size, mixed_heap is not None),
                               disc_batch_size=req.disc_batch_size).layout()
        return P.BatchReply("ok", self.describe() | layout, batch, disc)

    def state(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.COUNTERS} | {"request_rejections": dict(self.request_rejections)}

    def restore(self, state: dict[str, Any]) -> None:
        for name in self.COUNTERS:
            setattr(self, name, int(state[name]))
        self.request_rejections = collections.Counter(state["request_rejections"])

    def stats(self) -> dict[str, Any]:
        return {
            "batches_served": self.batches_served,
            "sample_requests": self.sample_requests,
            "sample_requests_rejected": self.sample_requests_rejected,
            "request_rejections": dict(self.request_rejections),
            "not_ready_replies": self.not_ready_replies,
            "limiter_realigned": self.limiter_realigned,
        }
