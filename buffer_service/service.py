"""The buffer service over Zenoh: one thread stores episodes and answers sample queries.

The state (`replay.ReplayState`) is the whole service without the network. Here one
thread owns it: the clients layer's `ZenohReplayServer` hands episodes and queries
from Zenoh's callbacks to a bounded inbox (a full one back-pressures the actors, so
no episode is dropped while the service runs), and this loop takes them one at a
time, tells the actors when the rate limiter wants them to pause, checkpoints on the
shared schedule (`snapshot.PeriodicCheckpoints`) and publishes stats.
"""

from __future__ import annotations

import logging
import time

from silcr.common import protocol as P
from silcr.common import run_end
from silcr.common.config import Config
from silcr.common.control_channel import Throttle, finished_reason
from silcr.common.envs import EnvSpec
from silcr.common.inbox import Inbox
from silcr.common.lifecycle import EXIT_CANNOT_START, EXIT_STALE_CHECKPOINT, StopFlag
from silcr.common.presence import Presence
from silcr.common.replay_server import SampleQuery, ZenohReplayServer
from silcr.common.resources import release_free_memory
from silcr.common.role_session import role_session
from silcr.common.schedule import Every

from . import snapshot
from .replay import ReplayState, checkpoint_path, open_replay

log = logging.getLogger("buffer")


def run_buffer(cfg: Config, stop: StopFlag) -> int:
    spec = EnvSpec.of(cfg.env)
    try:
        replay, snap = open_replay(cfg, spec)
    except snapshot.SnapshotError as e:
        log.error("cannot start: %s", e)
        return EXIT_CANNOT_START
    inbox = Inbox()
    checkpoints = snapshot.PeriodicCheckpoints(checkpoint_path(cfg), cfg.buffer_checkpoint_interval, inbox=inbox)
    checkpoints.restore_parts(snap, replay)
    restored = {} if snap is None else {"restored_transitions": snap.transitions,
                                        "restored_checkpoint_age_s": time.time() - snap.header["written_at"]}
    log.info("buffer for run %s: %s, algo %s, D_O %d, D_E %s, learning starts after %d transitions", cfg.run, cfg.env,
             cfg.algo, cfg.online_capacity, replay.heap.capacity if replay.heap is not None else "-", cfg.learning_starts)
    with role_session(cfg, stop, "buffer", spec=spec) as role:
        server = ZenohReplayServer(role.session, role.keys, inbox, cfg.max_episode_bytes)
        actors = Presence.actors(role.session, role.keys)
        learners = Presence.learners(role.session, role.keys)
        throttle = Throttle(role.session, role.keys)
        paused = False
        while not stop.is_set():
            item = server.next(timeout=min(0.5, role.stats_due.remaining()))
            if isinstance(item, SampleQuery):
                _serve(replay, item, learners)
            elif isinstance(item, P.ProtocolError):  # judged by its size alone, in the receiving thread
                replay.reject(item)
                log.warning("rejected episode (%s): %s", item.reason, item)
                release_free_memory()
            elif item is not None:
                try:
                    replay.ingest(item)
                except P.ProtocolError as e:
                    log.warning("rejected episode (%s): %s", e.reason, e)
            now = time.monotonic()
            stats_due = role.stats_due.due(now)
            now_paused = replay.limiter.inserts_paused()
            if now_paused != paused or stats_due:
                throttle.send(now_paused)
                paused = now_paused
            checkpoints.maybe(replay, now)
            if stats_due:
                waiting_episodes, waiting_queries = inbox.depth()
                role.stats.put(replay.stats() | {
                    "actors_alive": len(actors), "actors_paused": paused, "inbox_episodes": waiting_episodes,
                    "inbox_queries": waiting_queries, "inbox_blocked_puts": inbox.blocked_puts,
                    "episodes_dropped": inbox.dropped_at_close, "episode_bytes_received": server.episode_bytes_received,
                } | checkpoints.stats() | restored)
        server.close()
    written = checkpoints.final(replay)
    if written and stop.reason == finished_reason() and run_end.read(cfg.run_dir) is None:
        # The learner's run directory is not always this one (a claim of its own on Kubernetes): the buffer's
        # records that the run finished too, so a buffer started again on it changes nothing (run_end.py).
        run_end.mark(cfg.run_dir, run_end.Finished(cfg.run, replay.transitions_received,
                                                   replay.sampler.batches_served, cfg.total_steps))
    log.info("buffer stopping (%s): %d episodes, %d transitions received, %d rejected, %d missing, %d batches served, "
             "%d of them after the last episode arrived", stop.reason, replay.intake.episodes_received,
             replay.transitions_received, sum(replay.intake.rejections.values()), replay.intake.episodes_missing,
             replay.sampler.batches_served, replay.stats()["updates_since_last_episode"])
    return 0 if written else EXIT_STALE_CHECKPOINT


_REFUSAL_LOGS: dict[str, Every] = {}  # one line per reason every 10 s: an outside client's flood must not flood the log


def _serve(replay: ReplayState, query: SampleQuery, learners: Presence) -> None:
    try:
        reply = replay.answer(query.payload, learners)
    except P.ProtocolError as e:
        if _REFUSAL_LOGS.setdefault(e.reason, Every(10.0)).due():
            log.warning("rejected sample request (%s): %s (%d refused so far)", e.reason, e,
                        replay.sampler.request_rejections[e.reason])
        query.refuse(f"{e.reason}: {e}")
        return
    query.answer(reply)
