"""The buffer service's state without the network: D_O, D_E, the labeller, the rate limiter and the counters.

`ReplayState` stores episodes (`ingest` a message, `store` a decoded one), answers
sample requests (`answer` a message, `sample` a decoded one) and reports its stats.
What it keeps and how it labels follows the run's algorithm (`silcr.common.algorithms`):
D_E holds the agent's best episodes, or demonstrations, or nothing; batches mix D_E
or not; the labeller writes the rewards. Unit tests and `silcr train --single-process`
use it directly; `service.run_buffer` serves it over Zenoh.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Container
import time
from pathlib import Path
from typing import Any

import numpy as np

from silcr.common import protocol as P
from silcr.common import seeds
from silcr.common.algorithms import algorithm
from silcr.common.config import Config
from silcr.common.demos import is_demonstration, load_demos
from silcr.common.envs import EnvSpec

from . import snapshot
from .batches import compose_batches, discriminator_rows, online_rows
from .expert_heap import ExpertHeap
from .labels import labeller_for
from .online_fifo import OnlineFifo
from .rate_limiter import SamplesPerInsertLimiter

log = logging.getLogger("buffer")


def reserved_bytes(cfg: Config, spec: EnvSpec) -> int:
    """The bytes D_O's and D_E's row storage reserves for `cfg`'s capacities and `spec`'s shapes.

    Mirrors `OnlineFifo` and `ExpertHeap`: observation and reward rows of float32, action rows
    (float32, or int64 indices), with their slack for whole episodes. Checked against the
    machine's memory before a run starts.
    """
    row = 4 * (spec.obs_dim + 1) + spec.action_bytes
    longest = min(spec.max_episode_steps or cfg.online_capacity, cfg.online_capacity)
    rows = cfg.online_capacity + cfg.online_capacity // 32 + 2 * (longest + 1)
    if algorithm(cfg.algo).ranks_own_episodes:
        rows += cfg.expert_capacity + cfg.expert_capacity // 8 + 2
    return rows * row


class ReplayState:
    """D_O, D_E, the limiter and every counter the stats topic reports."""

    def __init__(self, cfg: Config, spec: EnvSpec) -> None:
        self.cfg = cfg
        self.spec = spec
        self.algo = algorithm(cfg.algo)
        self.labeller = labeller_for(self.algo)
        self.fifo = OnlineFifo(cfg.online_capacity, spec.max_episode_steps, self.labeller)
        self.heap: ExpertHeap | None = None
        if self.algo.ranks_own_episodes:
            self.heap = ExpertHeap(cfg.expert_capacity, cfg.expert_admission, self.labeller)
        elif self.algo.needs_demos:
            # D_E is the demonstrations, loaded at every start and never changed (reference.md).
            demos = load_demos(Path(cfg.demos), spec)
            self.heap = ExpertHeap(sum(d.length for d in demos), watcher=self.labeller)
            for d in demos:
                self.heap.offer(d)
            log.info("D_E holds %d demonstration episodes (%d transitions, mean return %.1f) from %s",
                     self.heap.num_episodes, len(self.heap), np.mean([d.episode_return for d in demos]), cfg.demos)
        self.limiter = SamplesPerInsertLimiter(
            cfg.samples_per_insert, cfg.learning_starts, cfg.spi_tolerance, throttle_inserts=not cfg.no_throttle
        )
        self.limits = spec.episode_limits(cfg.max_episode_bytes)
        self.rng = np.random.default_rng(seeds.buffer_sampling(cfg.seed))
        self.episodes_received = 0
        self.transitions_received = 0
        self.rejections: collections.Counter[str] = collections.Counter()
        self.batches_served = 0
        self.sample_requests = 0
        self.sample_requests_rejected = 0
        self.request_rejections: collections.Counter[str] = collections.Counter()  # by reason
        self.not_ready_replies = 0
        self.last_episode_version = -1
        self.episodes_missing = 0
        # Last sequence number per (actor id, incarnation): an episode is never stored twice.
        self.last_seq: dict[tuple[int, int], int] = {}
        self.started = time.time()
        # The learner whose update count the limiter last took (not checkpointed: a restarted buffer
        # takes the count again from the learner's first request) and how often that changed it.
        self.counted_learner: int | None = None
        self.limiter_realigned = 0

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

    # -- episodes ---------------------------------------------------------------
    def ingest(self, payload: bytes) -> P.Episode:
        """Store one episode message; raise `ProtocolError` (and count it) if it is rejected."""
        try:
            ep = P.Episode.decode(payload, self.limits)
        except P.ProtocolError as e:
            self.reject(e)
            raise
        self.store(ep)
        return ep

    def reject(self, e: P.ProtocolError) -> None:
        """Count an episode message rejected before it was decoded (an oversized one, by its size alone)."""
        self.rejections[e.reason] += 1

    def store(self, ep: P.Episode) -> None:
        """Store a decoded episode (an in-process actor's, or a message's); a repeated one is rejected and counted."""
        sender = (ep.actor_id, ep.incarnation)
        if ep.seq <= self.last_seq.get(sender, -1):
            self.rejections["duplicate"] += 1
            raise P.ProtocolError(
                "duplicate", f"actor {ep.actor_id} (incarnation {ep.incarnation}) sent seq {ep.seq} again"
            )
        last = self.last_seq.get(sender)
        if last is not None and ep.seq > last + 1:
            # Sequence numbers count every episode an actor publishes: a gap is episodes that were
            # sent and are not here (lost on the way, rejected, or received before a buffer restart).
            self.episodes_missing += ep.seq - last - 1
        if len(self.last_seq) >= 65_536:  # bound the table: forget the oldest senders
            del self.last_seq[next(iter(self.last_seq))]
        self.last_seq[sender] = ep.seq
        self.fifo.add(ep)
        if self.algo.ranks_own_episodes:
            self.heap.offer(ep)
        self.limiter.record_insert(ep.length)
        self.episodes_received += 1
        self.transitions_received += ep.length
        self.last_episode_version = max(self.last_episode_version, ep.policy_version)

    # -- batches ----------------------------------------------------------------
    def _expert(self) -> dict[str, Any]:
        heap = self.heap
        return {
            "expert_transitions": len(heap) if heap is not None else 0,
            "expert_episodes": heap.num_episodes if heap is not None else 0,
            "expert_min_return": P.finite_or_none(heap.min_return) if heap is not None else None,
            "expert_max_return": P.finite_or_none(heap.max_return) if heap is not None else None,
        }

    def meta(self) -> dict[str, Any]:
        """What every reply says of the buffer: its algorithm (the learner checks it runs the same), the
        transitions received, and D_E."""
        return {"algo": self.algo.name, "env_steps": self.transitions_received,
                "episodes_received": self.episodes_received, "online_transitions": len(self.fifo)} | self._expert()

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
        rows = req.batches * (req.batch_size + 2 * req.disc_batch_size)
        row_bytes = 4 * (2 * self.spec.obs_dim + 1) + self.spec.action_bytes + 2 + 8  # obs, next_obs, reward, action, flags, version
        if rows * row_bytes > P.MAX_REPLY_BYTES:
            e = P.ProtocolError("bad_request", f"a reply of {rows} rows would be {rows * row_bytes / 2**20:.0f} MiB, more "
                                               f"than {P.MAX_REPLY_BYTES >> 20} MiB: at most "
                                               f"{P.MAX_REPLY_BYTES // row_bytes} rows per request on {self.spec.env_id}")
            self._refused(e)
            raise e
        if req.disc_batch_size and self.heap is None:
            e = P.ProtocolError("bad_request", f"disc_batch_size: this buffer keeps no D_E (--algo {self.algo.name})")
            self._refused(e)
            raise e
        if self.limiter.warming_up() or (self.heap is not None and self.heap.num_episodes == 0):
            self.not_ready_replies += 1
            return P.BatchReply("not_ready", self.meta(), reason="warmup", retry_after_ms=200)
        k = min(req.batches, self.limiter.due() if keep_ratio else self.limiter.available())
        if k == 0:
            self.not_ready_replies += 1
            return P.BatchReply("not_ready", self.meta(), reason="rate_limited", retry_after_ms=20)
        mixed_heap = self.heap if self.algo.mixes_expert else None
        batch = compose_batches(self.fifo, mixed_heap, k, req.batch_size, self.rng, self.labeller, self.spec.obs_dim,
                                self.spec.act_dim, self.spec.action_dtype)
        disc = None
        if req.disc_batch_size:
            assert self.heap is not None
            disc = discriminator_rows(self.fifo, self.heap, k * req.disc_batch_size, req.recent_window, self.rng)
        self.limiter.record_sample(k)
        self.batches_served += k
        meta = self.meta() | {"batches": k, "batch_size": req.batch_size,
                              "online_rows": online_rows(req.batch_size, mixed_heap is not None)}
        if req.disc_batch_size:
            meta["disc_batch_size"] = req.disc_batch_size
        return P.BatchReply("ok", meta, batch, disc)

    # -- checkpoints ------------------------------------------------------------
    COUNTERS = ("episodes_received", "transitions_received", "batches_served", "sample_requests",
                "sample_requests_rejected", "not_ready_replies", "last_episode_version")

    def identity(self) -> dict[str, str]:
        """What a checkpoint must match to be restored here."""
        return {"env": self.spec.env_id, "algo": self.algo.name}

    def locks(self) -> tuple:
        """The row storages' locks, in a fixed order: held while a checkpoint encodes an episode they hold."""
        return (self.fifo.storage.lock,) + ((self.heap.storage.lock,) if self.heap is not None else ())

    def state(self) -> dict[str, Any]:
        """Everything a restart needs, each table and the limiter providing its own part (`snapshot` writes it)."""
        return {
            "counters": {name: getattr(self, name) for name in self.COUNTERS} | {"rejections": dict(self.rejections),
                                                                                 "request_rejections": dict(self.request_rejections),
                                                                                 "episodes_missing": self.episodes_missing},
            "last_seq": [[a, inc, seq] for (a, inc), seq in self.last_seq.items()],
            "fifo": self.fifo.state(),
            # SQIL's D_E is the demonstrations, loaded again from --demos at every start.
            "heap": self.heap.state() if self.algo.ranks_own_episodes else None,
            "limiter": self.limiter.state(),
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Fill this fresh state from `state()`."""
        c = state["counters"]
        for name in self.COUNTERS:
            setattr(self, name, int(c[name]))
        self.rejections.update(c["rejections"])
        self.request_rejections.update(c.get("request_rejections", {}))  # absent from checkpoints before 0.4
        self.episodes_missing = int(c.get("episodes_missing", 0))  # the same
        self.last_seq = {(int(a), int(inc)): int(seq) for a, inc, seq in state["last_seq"]}
        self.fifo.restore(state["fifo"])
        if state["heap"] is not None and self.algo.ranks_own_episodes:
            self.heap.restore(state["heap"])
        self.limiter.restore(state["limiter"])

    # -- stats ------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        heap = self.heap
        return {
            "time": time.time(),
            "uptime_s": time.time() - self.started,
            "run": self.cfg.run,
            "env": self.cfg.env,
            "algo": self.algo.name,
            "online_transitions": len(self.fifo),
            "online_episodes": self.fifo.num_episodes,
            "online_capacity": self.fifo.capacity,
            "online_evicted": self.fifo.evicted_episodes,
            "online_evicted_for_rows": self.fifo.evicted_for_rows,
            **self._expert(),
            "expert_capacity": heap.capacity if heap is not None else 0,
            "expert_admitted": heap.admitted if heap is not None else 0,
            "expert_rejected": heap.rejected if heap is not None else 0,
            "expert_evicted": heap.evicted if heap is not None else 0,
            "expert_init_transitions": self.expert_init_transitions(),
            "episodes_received": self.episodes_received,
            "transitions_received": self.transitions_received,
            "episodes_rejected": sum(self.rejections.values()),
            "episodes_missing": self.episodes_missing,
            "rejections": dict(self.rejections),
            "batches_served": self.batches_served,
            "sample_requests": self.sample_requests,
            "sample_requests_rejected": self.sample_requests_rejected,
            "request_rejections": dict(self.request_rejections),
            "not_ready_replies": self.not_ready_replies,
            "limiter_realigned": self.limiter_realigned,
            "samples_per_insert": self.limiter.observed_samples_per_insert(),
            "samples_per_insert_target": self.limiter.samples_per_insert,
            "rate_limiter_error": self.limiter.error - self.limiter.centre,
            "warming_up": self.limiter.warming_up(),
            "latest_episode_policy_version": self.last_episode_version,
        }


def checkpoint_path(cfg: Config) -> Path:
    return cfg.run_dir / "checkpoints" / "buffer.ckpt"


def open_replay(cfg: Config, spec: EnvSpec) -> tuple[ReplayState, snapshot.Snapshot | None]:
    """The buffer's state, restored from its checkpoint with --resume when there is one (and that snapshot).

    Raises `snapshot.SnapshotError` for a checkpoint that cannot be used: a run
    refuses to start rather than silently begin empty (the file is kept for inspection).
    """
    state = ReplayState(cfg, spec)
    path = checkpoint_path(cfg)
    if not (cfg.resume and path.exists()):
        if cfg.resume:
            log.info("--resume: no buffer checkpoint at %s yet; starting empty", path)
        if cfg.expert_init:  # a restored D_E already holds what is left of them
            state.warm_start(load_demos(Path(cfg.expert_init), spec))
        return state, None
    t0 = time.monotonic()
    snap = snapshot.restore(path, state)
    log.info("restored D_O (%d transitions) and D_E (%d) from %s in %.1fs; it was written %.0fs ago at %d "
             "transitions received; anything received after that was lost", len(state.fifo),
             len(state.heap) if state.heap is not None else 0, path, time.monotonic() - t0,
             time.time() - snap.header["written_at"], snap.transitions)
    return state, snap
