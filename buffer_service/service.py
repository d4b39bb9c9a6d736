"""The buffer service: D_O, D_E and the rate limiter behind Zenoh.

`ReplayState` is the whole service without the network (used directly by unit
tests); `run_buffer` wires it to Zenoh. One thread owns the state: Zenoh
callbacks only hand raw payloads and queries to a bounded `Inbox`, and the main
loop decodes, stores and answers. A full inbox blocks the callback, which
back-pressures the publishing actor through Zenoh (BLOCK), so no episode is
dropped while the service runs.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

from pathlib import Path

import numpy as np
import zenoh

from silcr.common import protocol as P
from silcr.common.clients import StatsPublisher, Throttle, stop_on_shutdown
from silcr.common.config import RANKED_ALGOS, Config
from silcr.common.demos import is_demonstration, load_demos
from silcr.common.envs import EnvSpec
from silcr.common.lifecycle import StopFlag
from silcr.common.zenoh_session import open_session, session_config

from .batches import compose_batches, discriminator_rows, online_rows
from .expert_heap import ExpertHeap
from .online_fifo import OnlineFifo
from . import snapshot
from .rate_limiter import SamplesPerInsertLimiter

log = logging.getLogger("buffer")


class ReplayState:
    """D_O, D_E (SILCR, GASIL and SQIL), the limiter and every counter the stats topic reports."""

    def __init__(self, cfg: Config, spec: EnvSpec) -> None:
        self.cfg = cfg
        self.spec = spec
        self.constant_rewards = cfg.constant_rewards
        self.fifo = OnlineFifo(cfg.online_capacity, spec.max_episode_steps)
        self.heap: ExpertHeap | None = None
        # D_E ranks the agent's own episodes (SILCR, GASIL); only SILCR and SQIL mix it into batches.
        self.ranked = cfg.algo in RANKED_ALGOS
        if self.ranked:
            self.heap = ExpertHeap(cfg.expert_capacity, cfg.expert_admission)
        elif cfg.algo == "sqil":
            # SQIL: D_E is the demonstrations, loaded once and never changed (reference.md).
            demos = load_demos(Path(cfg.demos), spec)
            self.heap = ExpertHeap(sum(d.length for d in demos))
            for d in demos:
                self.heap.offer(d)
            log.info("D_E holds %d demonstration episodes (%d transitions, mean return %.1f) from %s",
                     self.heap.num_episodes, len(self.heap), np.mean([d.episode_return for d in demos]), cfg.demos)
        self.limiter = SamplesPerInsertLimiter(
            cfg.samples_per_insert, cfg.learning_starts, cfg.spi_tolerance, throttle_inserts=not cfg.no_throttle
        )
        self.codec = P.EpisodeCodec(spec.obs_dim, spec.act_dim, spec.max_episode_steps, cfg.max_episode_bytes)
        self.rng = np.random.default_rng(cfg.seed + 1_000_003)
        self.episodes_received = 0
        self.transitions_received = 0
        self.rejections: collections.Counter[str] = collections.Counter()
        self.batches_served = 0
        self.sample_requests = 0
        self.sample_requests_rejected = 0
        self.not_ready_replies = 0
        self.last_episode_version = -1
        # Last sequence number per (actor id, incarnation): an episode is never stored twice.
        self.last_seq: dict[tuple[int, int], int] = {}
        self.started = time.time()

    def warm_start(self, demos: list[P.Episode]) -> None:
        """`--expert-init`: offer demonstrations to D_E, best first, before any episode of the agent's own.

        From then on they are ranked and evicted like any episode: better own
        episodes push them out, worse ones do not (`expert_init_transitions` counts what is left).
        """
        assert self.heap is not None and self.cfg.algo == "silcr"
        for d in sorted(demos, key=lambda e: e.episode_return, reverse=True):
            self.heap.offer(d)
        log.info("D_E starts with %d of %d demonstration episodes (%d transitions, returns %.1f to %.1f)",
                 self.heap.num_episodes, len(demos), len(self.heap), self.heap.min_return or 0.0,
                 self.heap.max_return or 0.0)

    def expert_init_transitions(self) -> int:
        """Demonstration transitions still in D_E (SILCR with --expert-init)."""
        if not self.ranked:
            return 0
        return sum(e.length for e in self.heap.episodes() if is_demonstration(e))

    # -- episodes ---------------------------------------------------------------
    def ingest(self, payload: bytes) -> P.Episode:
        """Store one episode message; raise `ProtocolError` (and count it) if it is rejected."""
        try:
            ep = self.codec.decode(payload)
        except P.ProtocolError as e:
            self.rejections[e.reason] += 1
            raise
        self.store(ep)
        return ep

    def store(self, ep: P.Episode) -> None:
        """Store a decoded episode (an in-process actor's, or a message's); a repeated one is rejected and counted."""
        sender = (ep.actor_id, ep.incarnation)
        if ep.seq <= self.last_seq.get(sender, -1):
            self.rejections["duplicate"] += 1
            raise P.ProtocolError(
                "duplicate", f"actor {ep.actor_id} (incarnation {ep.incarnation}) sent seq {ep.seq} again"
            )
        if len(self.last_seq) >= 65_536:  # bound the table: forget the oldest senders
            del self.last_seq[next(iter(self.last_seq))]
        self.last_seq[sender] = ep.seq
        self.fifo.add(ep)
        if self.ranked:
            self.heap.offer(ep)
        self.limiter.record_insert(ep.length)
        self.episodes_received += 1
        self.transitions_received += ep.length
        self.last_episode_version = max(self.last_episode_version, ep.policy_version)

    # -- batches ----------------------------------------------------------------
    def meta(self) -> dict[str, Any]:
        heap = self.heap
        return {
            "env_steps": self.transitions_received,
            "episodes_received": self.episodes_received,
            "online_transitions": len(self.fifo),
            "expert_transitions": len(heap) if heap is not None else 0,
            "expert_episodes": heap.num_episodes if heap is not None else 0,
            "expert_min_return": P.finite_or_none(heap.min_return) if heap is not None else None,
            "expert_max_return": P.finite_or_none(heap.max_return) if heap is not None else None,
        }

    def answer(self, payload: bytes | None) -> P.BatchReply:
        """Answer one sample query; raise `ProtocolError` for a malformed request."""
        try:
            if payload is None:
                raise P.ProtocolError("bad_request", "sample query carries no payload")
            req = P.SampleRequest.decode(payload)
        except P.ProtocolError:
            self.sample_requests += 1
            self.sample_requests_rejected += 1
            raise
        return self.sample(req)

    def sample(self, req: P.SampleRequest, keep_ratio: bool = False) -> P.BatchReply:
        """Up to `req.batches` mixed batches, as many as the rate limiter allows now.

        Over the network the learner may run up to the limiter's tolerance ahead of
        the ratio (so it never waits on a round trip); `keep_ratio` serves only the
        updates the inserted transitions are due, as the single-process loop wants.
        """
        self.sample_requests += 1
        if req.disc_batch_size and self.heap is None:
            self.sample_requests_rejected += 1
            raise P.ProtocolError("bad_request", f"disc_batch_size: this buffer keeps no D_E (--algo {self.cfg.algo})")
        if self.limiter.warming_up() or (self.heap is not None and self.heap.num_episodes == 0):
            self.not_ready_replies += 1
            return P.BatchReply("not_ready", self.meta(), reason="warmup", retry_after_ms=200)
        k = min(req.batches, self.limiter.due() if keep_ratio else self.limiter.available())
        if k == 0:
            self.not_ready_replies += 1
            return P.BatchReply("not_ready", self.meta(), reason="rate_limited", retry_after_ms=20)
        mixed_heap = self.heap if self.constant_rewards else None
        arrays = compose_batches(
            self.fifo, mixed_heap, k, req.batch_size, self.rng, self.constant_rewards, self.spec.obs_dim, self.spec.act_dim
        )
        if req.disc_batch_size:
            assert self.heap is not None
            arrays |= discriminator_rows(self.fifo, self.heap, k * req.disc_batch_size, req.recent_window, self.rng)
        self.limiter.record_sample(k)
        self.batches_served += k
        meta = self.meta() | {"batches": k, "batch_size": req.batch_size,
                              "online_rows": online_rows(req.batch_size, mixed_heap is not None)}
        if req.disc_batch_size:
            meta["disc_batch_size"] = req.disc_batch_size
        return P.BatchReply("ok", meta, arrays)

    # -- checkpoints ------------------------------------------------------------
    COUNTERS = ("episodes_received", "transitions_received", "batches_served", "sample_requests",
                "sample_requests_rejected", "not_ready_replies", "last_episode_version")

    def state(self) -> dict[str, Any]:
        """Everything a restart needs, each table and the limiter providing its own part (`snapshot` writes it)."""
        return {
            "counters": {name: getattr(self, name) for name in self.COUNTERS} | {"rejections": dict(self.rejections)},
            "last_seq": [[a, inc, seq] for (a, inc), seq in self.last_seq.items()],
            "fifo": self.fifo.state(),
            # SQIL's D_E is the demonstrations, loaded again from --demos at every start.
            "heap": self.heap.state() if self.ranked else None,
            "limiter": self.limiter.state(),
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Fill this fresh state from `state()`."""
        c = state["counters"]
        for name in self.COUNTERS:
            setattr(self, name, int(c[name]))
        self.rejections.update(c["rejections"])
        self.last_seq = {(int(a), int(inc)): int(seq) for a, inc, seq in state["last_seq"]}
        self.fifo.restore(state["fifo"])
        if state["heap"] is not None and self.ranked:
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
            "algo": self.cfg.algo,
            "online_transitions": len(self.fifo),
            "online_episodes": self.fifo.num_episodes,
            "online_capacity": self.fifo.capacity,
            "online_evicted": self.fifo.evicted_episodes,
            "online_evicted_for_rows": self.fifo.evicted_for_rows,
            "expert_transitions": len(heap) if heap is not None else 0,
            "expert_capacity": heap.capacity if heap is not None else 0,
            "expert_episodes": heap.num_episodes if heap is not None else 0,
            "expert_min_return": P.finite_or_none(heap.min_return) if heap is not None else None,
            "expert_max_return": P.finite_or_none(heap.max_return) if heap is not None else None,
            "expert_admitted": heap.admitted if heap is not None else 0,
            "expert_rejected": heap.rejected if heap is not None else 0,
            "expert_evicted": heap.evicted if heap is not None else 0,
            "expert_init_transitions": self.expert_init_transitions(),
            "episodes_received": self.episodes_received,
            "transitions_received": self.transitions_received,
            "episodes_rejected": sum(self.rejections.values()),
            "rejections": dict(self.rejections),
            "batches_served": self.batches_served,
            "sample_requests": self.sample_requests,
            "sample_requests_rejected": self.sample_requests_rejected,
            "not_ready_replies": self.not_ready_replies,
            "samples_per_insert": self.limiter.observed_samples_per_insert(),
            "samples_per_insert_target": self.limiter.samples_per_insert,
            "rate_limiter_error": self.limiter.error - self.limiter.centre,
            "warming_up": self.limiter.warming_up(),
            "latest_episode_policy_version": self.last_episode_version,
        }


class Inbox:
    """Bounded hand-over from Zenoh callback threads to the service's main loop.

    Queries are served before episodes so a burst of episodes never makes the
    learner wait. `put_*` blocks while full (back-pressure); once `close()` is
    called it gives up and counts the item as dropped.
    """

    def __init__(self, max_episodes: int = 64, max_queries: int = 256) -> None:
        self._cond = threading.Condition()
        self._episodes: collections.deque[bytes] = collections.deque()
        self._queries: collections.deque[zenoh.Query] = collections.deque()
        self.max_episodes = max_episodes
        self.max_queries = max_queries
        self.closed = False
        self.dropped_at_close = 0
        self.blocked_puts = 0

    def _put(self, q: collections.deque, item: Any, limit: int) -> None:
        with self._cond:
            if len(q) >= limit:
                self.blocked_puts += 1
            while len(q) >= limit and not self.closed:
                self._cond.wait(0.1)
            if self.closed:
                self.dropped_at_close += 1
                return
            q.append(item)
            self._cond.notify_all()

    def put_episode(self, payload: bytes) -> None:
        self._put(self._episodes, payload, self.max_episodes)

    def put_query(self, query: zenoh.Query) -> None:
        self._put(self._queries, query, self.max_queries)

    def get(self, timeout: float) -> tuple[str, Any] | None:
        with self._cond:
            if not (self._queries or self._episodes):
                self._cond.wait(timeout)
            if self._queries:
                item: tuple[str, Any] = ("query", self._queries.popleft())
            elif self._episodes:
                item = ("episode", self._episodes.popleft())
            else:
                return None
            self._cond.notify_all()
            return item

    def depth(self) -> tuple[int, int]:
        with self._cond:
            return len(self._episodes), len(self._queries)

    def state(self) -> dict[str, int]:
        return {"blocked_puts": self.blocked_puts, "dropped_at_close": self.dropped_at_close}

    def restore(self, state: dict[str, int]) -> None:
        self.blocked_puts, self.dropped_at_close = int(state["blocked_puts"]), int(state["dropped_at_close"])

    def close(self) -> list[Any]:
        """Stop accepting; return the queries still waiting so they can be finalized."""
        with self._cond:
            self.closed = True
            pending = list(self._queries)
            self._queries.clear()
            self._cond.notify_all()
            return pending


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


def write_final_checkpoint(state: ReplayState, writer: snapshot.BackgroundWriter, **parts: snapshot.Part) -> None:
    """A last checkpoint on the way out, so a clean stop (Ctrl-C, end of run) loses nothing."""
    writer.join()
    t0 = time.monotonic()
    try:
        snapshot.write(writer.path, snapshot.take(state, writer=writer, **parts))
        log.info("checkpoint of %d transitions written to %s in %.1fs", state.transitions_received, writer.path,
                 time.monotonic() - t0)
    except OSError as e:
        log.error("final checkpoint failed: %s", e)
    if writer.failed:
        log.error("%d periodic checkpoints failed; last error: %s", writer.failed, writer.last_error)


def run_buffer(cfg: Config, stop: StopFlag) -> int:
    spec = EnvSpec.of(cfg.env)
    try:
        state, snap = open_replay(cfg, spec)
    except snapshot.SnapshotError as e:
        log.error("cannot resume: %s", e)
        return 1
    keys = P.Keys(cfg.run)
    inbox = Inbox()
    writer = snapshot.BackgroundWriter(checkpoint_path(cfg))
    restored: dict[str, Any] = {}
    if snap is not None:
        for name, part in (("inbox", inbox), ("writer", writer)):
            if name in snap.parts:
                part.restore(snap.parts[name])
        restored = {"restored_transitions": snap.transitions,
                    "restored_checkpoint_age_s": time.time() - snap.header["written_at"]}
    log.info(
        "buffer for run %s: %s, algo %s, D_O %d, D_E %s, learning starts after %d transitions",
        cfg.run, cfg.env, cfg.algo, cfg.online_capacity, state.heap.capacity if state.heap is not None else "-", cfg.learning_starts,
    )
    conf = session_config(cfg.connect, cfg.listen, cfg.zenoh_mode, cfg.zenoh_config)
    with open_session(conf) as session:
        session.declare_subscriber(keys.episodes, lambda s: inbox.put_episode(s.payload.to_bytes()))
        session.declare_queryable(keys.sample, inbox.put_query)
        stop_on_shutdown(session, keys, stop)
        actors_alive: set[str] = set()

        def on_alive(sample: zenoh.Sample) -> None:
            who = str(sample.key_expr).rsplit("/", 1)[-1]
            if sample.kind == zenoh.SampleKind.PUT:
                actors_alive.add(who)
                log.info("actor %s joined", who)
            else:
                actors_alive.discard(who)
                log.info("actor %s left", who)

        session.liveliness().declare_subscriber(keys.alive_actors, on_alive, history=True)
        token = session.liveliness().declare_token(keys.alive("buffer"))
        stats_pub = StatsPublisher(session, keys.stats_buffer)
        throttle = Throttle(session, keys)
        paused = False
        next_stats = time.monotonic()
        interval = cfg.buffer_checkpoint_interval
        next_checkpoint = time.monotonic() + interval if interval > 0 else float("inf")
        while not stop.is_set():
            item = inbox.get(timeout=max(0.0, min(0.5, next_stats - time.monotonic())))
            if item is not None:
                kind, obj = item
                if kind == "query":
                    _serve(state, obj, keys)
                else:
                    try:
                        state.ingest(obj)
                    except P.ProtocolError as e:
                        log.warning("rejected episode (%s): %s", e.reason, e)
            now_paused = state.limiter.inserts_paused()
            now = time.monotonic()
            if now_paused != paused or now >= next_stats:
                throttle.send(now_paused)
                paused = now_paused
            if now >= next_checkpoint:
                writer.submit(snapshot.take(state, inbox=inbox, writer=writer))
                next_checkpoint = now + interval
            if now >= next_stats:
                stats = state.stats()
                ep_depth, q_depth = inbox.depth()
                stats |= {
                    "actors_alive": len(actors_alive),
                    "actors_paused": paused,
                    "inbox_episodes": ep_depth,
                    "inbox_queries": q_depth,
                    "inbox_blocked_puts": inbox.blocked_puts,
                    "episodes_dropped": inbox.dropped_at_close,
                    "checkpoints_written": writer.written,
                    "checkpoints_skipped": writer.skipped,
                    "checkpoints_failed": writer.failed,
                    "checkpoint_transitions": writer.last_transitions,
                    "checkpoint_age_s": time.time() - writer.last_written_at if writer.last_written_at else None,
                } | restored
                stats_pub.put(stats)
                next_stats = now + cfg.stats_interval
        for q in inbox.close():
            with q:
                q.reply_err(b"buffer service is shutting down")
        token.undeclare()
        write_final_checkpoint(state, writer, inbox=inbox)
        log.info(
            "buffer stopping (%s): %d episodes, %d transitions received, %d rejected, %d batches served",
            stop.reason, state.episodes_received, state.transitions_received,
            sum(state.rejections.values()), state.batches_served,
        )
    return 0


def _serve(state: ReplayState, query: zenoh.Query, keys: P.Keys) -> None:
    with query:  # leaving the block finalizes the query, so the learner's get() ends at once
        payload = query.payload.to_bytes() if query.payload is not None else None
        try:
            reply = state.answer(payload)
        except P.ProtocolError as e:
            log.warning("rejected sample request (%s): %s", e.reason, e)
            query.reply_err(f"{e.reason}: {e}".encode())
            return
        query.reply(keys.sample, reply.encode())
