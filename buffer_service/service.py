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
from silcr.common.episode_channel import EpisodeAcks
from silcr.common.inbox import Inbox
from silcr.common.lifecycle import EXIT_CANNOT_START, EXIT_STALE_CHECKPOINT, StopFlag
from silcr.common.presence import Presence
from silcr.common.replay_server import SampleQuery, ZenohReplayServer
from silcr.common.resources import release_free_memory
from silcr.common.role_session import role_session
from silcr.common.schedule import Every

from . import snapshot
from .episode_log import EpisodeLog, log_dir
from .episode_log import read as read_log
from .episode_log import segments as log_segments
from .replay import ReplayState, checkpoint_path, open_replay

log = logging.getLogger("buffer")
#: The longest a stored episode waits for its ack while more episodes keep arriving.
ACK_INTERVAL_S = 0.05


def run_buffer(cfg: Config, stop: StopFlag) -> int:
    spec = EnvSpec.of(cfg.env)
    try:
        replay, snap = open_replay(cfg, spec)
    except snapshot.SnapshotError as e:
        log.error("cannot start: %s", e)
        return EXIT_CANNOT_START
    episode_log = _open_episode_log(cfg, replay)
    inbox = Inbox()
    checkpoints = snapshot.PeriodicCheckpoints(checkpoint_path(cfg), cfg.buffer_checkpoint_interval, episode_log,
                                               inbox=inbox)
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
        acks = EpisodeAcks(role.session, role.keys)
        paused = False
        acks_due = Every(ACK_INTERVAL_S)
        while not stop.is_set():
            item = server.next(timeout=min(0.5, role.stats_due.remaining()))
            if isinstance(item, SampleQuery):
                _serve(replay, item, learners)
            elif isinstance(item, P.ProtocolError):  # judged by its size alone, in the receiving thread
                replay.intake.reject(item)
                log.warning("rejected episode (%s): %s", item.reason, item)
                release_free_memory()
            elif item is not None:
                _store(replay, item, episode_log, acks)
            # Acks go out in bursts, once the log has handed what they confirm to the operating system.
            if acks.pending and (inbox.depth()[0] == 0 or acks_due.due()) and (
                    episode_log is None or episode_log.flush()):
                acks.send(lambda sender: replay.intake.last_seq.get(sender, -1))
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
                    "acks_sent": acks.sent, "acks_waiting": len(acks.pending),
                } | checkpoints.stats() | (episode_log.stats() if episode_log else {}) | restored)
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


def _open_episode_log(cfg: Config, replay: ReplayState) -> EpisodeLog | None:
    """The episode log (none without periodic checkpoints, which are what compact it), after replaying
    what an earlier buffer of this run logged since its last checkpoint (with --resume; without, a
    fresh start, the old segments are removed with the state they belonged to)."""
    if cfg.no_episode_log or cfg.buffer_checkpoint_interval <= 0:
        return None
    folder = log_dir(cfg.run_dir)
    replayed = 0
    if cfg.resume:
        t0 = time.monotonic()
        replayed = sum(replay.intake.replay(ep) for ep in read_log(folder, replay.limits))
        if replayed:
            log.info("replayed %d episodes from the episode log %s in %.1fs (%d transitions received now)", replayed,
                     folder, time.monotonic() - t0, replay.transitions_received)
    else:
        for path in log_segments(folder):
            path.unlink()
    return EpisodeLog(folder, replayed)


def _store(replay: ReplayState, payload: bytes, episode_log: EpisodeLog | None, acks: EpisodeAcks) -> None:
    """Store one episode message, log it, and note the ack its sender is owed (also for one already held,
    whose ack went missing, and for one after a gap, whose sender is asked again from the gap)."""
    try:
        ep = replay.intake.decode(payload)
    except P.ProtocolError as e:
        log.warning("rejected episode (%s): %s", e.reason, e)
        return
    try:
        replay.intake.store(ep)
    except P.ProtocolError as e:
        acks.note(ep, replay.intake.expected(ep) if e.reason == "out_of_order" else None)
        if e.reason not in ("duplicate", "out_of_order"):  # those two are an actor sending again: expected
            log.warning("rejected episode (%s): %s", e.reason, e)
        return
    if episode_log is not None:
        episode_log.append(payload)
    acks.note(ep)


_REFUSAL_LOGS: dict[str, Every] = {}  # one line per reason every 10 s: an outside client's flood must not flood the log


def _serve(replay: ReplayState, query: SampleQuery, learners: Presence) -> None:
    try:
        reply = replay.sampler.answer(query.payload, learners)
    except P.ProtocolError as e:
        if _REFUSAL_LOGS.setdefault(e.reason, Every(10.0)).due():
            log.warning("rejected sample request (%s): %s (%d refused so far)", e.reason, e,
                        replay.sampler.request_rejections[e.reason])
        query.refuse(f"{e.reason}: {e}")
        return
    query.answer(reply)
