"""Episodes coming in: decoded and checked, never stored twice, counted, then into the tables.

`Intake.ingest(payload)` decodes an episode message against the run's limits (the same codec
guards the network and the checkpoints), rejects a repeated one (a sender's `seq` at or below its
last), counts the episodes a gap in a sender's sequence numbers says are missing, stores the
episode in D_O and D_E (`tables.Tables.add`) and tells the rate limiter. Every rejection is
counted by reason and published (`stats`); the counts save and restore with the part. The last
`ROLLOUT_WINDOW` episodes' returns and lengths give the actors' own returns (`rollout_meta`),
what the policy's sampled actions achieve, beside the learner's evaluations.
"""

from __future__ import annotations

import collections
from typing import Any

from silcr.common import protocol as P

from .rate_limiter import SamplesPerInsertLimiter
from .tables import Tables

#: A sender is an (actor id, incarnation); the table of their last sequence numbers forgets the
#: oldest beyond this many, so it stays bounded however many actors come and go.
MAX_SENDERS = 65_536
#: Episodes in the rollout return's mean (Stable-Baselines3's `rollout/ep_rew_mean` takes 100 too).
ROLLOUT_WINDOW = 100


class Intake:
    COUNTERS = ("episodes_received", "transitions_received", "last_episode_version", "episodes_missing")

    def __init__(self, tables: Tables, limiter: SamplesPerInsertLimiter, limits: P.EpisodeLimits) -> None:
        self.tables, self.limiter, self.limits = tables, limiter, limits
        self.episodes_received = 0
        self.transitions_received = 0
        self.last_episode_version = -1
        self.episodes_missing = 0
        self.rejections: collections.Counter[str] = collections.Counter()
        # Last sequence number per (actor id, incarnation): an episode is never stored twice.
        self.last_seq: dict[tuple[int, int], int] = {}
        # The updates served when the latest episode arrived (not checkpointed: counted from each start),
        # so that how many the learner made on tables that no longer changed is known at the end.
        self.samples_at_last_episode = 0
        self.rollouts: collections.deque[tuple[float, int]] = collections.deque(maxlen=ROLLOUT_WINDOW)
        self._rollout_means = self._means()

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
        if len(self.last_seq) >= MAX_SENDERS:
            del self.last_seq[next(iter(self.last_seq))]
        self.last_seq[sender] = ep.seq
        self.tables.add(ep)
        self.limiter.record_insert(ep.length)
        self.samples_at_last_episode = self.limiter.samples
        self.episodes_received += 1
        self.transitions_received += ep.length
        self.last_episode_version = max(self.last_episode_version, ep.policy_version)
        self.rollouts.append((ep.episode_return, ep.length))
        self._rollout_means = self._means()

    def rollout_meta(self) -> dict[str, Any]:
        """The mean return and length of the last `ROLLOUT_WINDOW` episodes received (None before the first)."""
        return dict(self._rollout_means)

    def _means(self) -> dict[str, float | None]:
        # Taken when an episode arrives, not in `rollout_meta`: every batch reply carries them, and replies
        # come far more often than episodes.
        n = len(self.rollouts)
        return {"rollout_return": sum(r for r, _ in self.rollouts) / n if n else None,
                "rollout_length": sum(length for _, length in self.rollouts) / n if n else None}

    def state(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.COUNTERS} | {
            "rejections": dict(self.rejections), "last_seq": [[a, inc, seq] for (a, inc), seq in self.last_seq.items()],
            "rollouts": [list(r) for r in self.rollouts]}

    def restore(self, state: dict[str, Any]) -> None:
        for name in self.COUNTERS:
            setattr(self, name, int(state[name]))
        self.rejections = collections.Counter(state["rejections"])
        self.last_seq = {(int(a), int(inc)): int(seq) for a, inc, seq in state["last_seq"]}
        # Checkpoints older than the rollout columns hold none: the mean starts again from the next episode.
        self.rollouts.clear()
        self.rollouts.extend((float(r), int(length)) for r, length in state.get("rollouts", []))
        self._rollout_means = self._means()

    def stats(self) -> dict[str, Any]:
        return {
            "episodes_received": self.episodes_received,
            "transitions_received": self.transitions_received,
            "episodes_rejected": sum(self.rejections.values()),
            "episodes_missing": self.episodes_missing,
            "rejections": dict(self.rejections),
            "latest_episode_policy_version": self.last_episode_version,
            "updates_since_last_episode": self.limiter.samples - self.samples_at_last_episode,
        } | self.rollout_meta()
