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
    #: Episodes sent again that the buffer did not store (not rejections: an actor resends what it has no ack
    #: for, after a cut link or a buffer restart). Absent from checkpoints before 0.9.
    RESENT = ("episodes_duplicate", "episodes_out_of_order")

    def __init__(self, tables: Tables, limiter: SamplesPerInsertLimiter, limits: P.EpisodeLimits) -> None:
        self.tables, self.limiter, self.limits = tables, limiter, limits
        self.episodes_received = 0
        self.transitions_received = 0
        self.last_episode_version = -1
        self.episodes_missing = 0
        self.episodes_duplicate = self.episodes_out_of_order = 0
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
        ep = self.decode(payload)
        self.store(ep)
        return ep

    def decode(self, payload: bytes) -> P.Episode:
        """The episode in a message; raise `ProtocolError` (and count it) if it is malformed."""
        try:
            return P.Episode.decode(payload, self.limits)
        except P.ProtocolError as e:
            self.reject(e)
            raise

    def reject(self, e: P.ProtocolError) -> None:
        """Count an episode message rejected before it was decoded (an oversized one, by its size alone)."""
        self.rejections[e.reason] += 1

    def store(self, ep: P.Episode) -> None:
        """Store a decoded episode (an in-process actor's, or a message's) if it is the next one its sender owes.

        A sender's episodes are stored in sequence order, none twice: one at or below the last stored is a
        `duplicate` (resent after its ack went missing); one after a gap is refused as `out_of_order`, and
        the sender, which still holds the missing ones, is asked for them again (`expected`). Episodes the
        sender no longer holds (before its `resend_from`) can never come: they are counted missing.
        """
        sender = (ep.actor_id, ep.incarnation)
        last = self.last_seq.get(sender)
        if last is not None and ep.seq <= last:
            self.episodes_duplicate += 1
            raise P.ProtocolError(
                "duplicate", f"actor {ep.actor_id} (incarnation {ep.incarnation}) sent seq {ep.seq} again"
            )
        expected = self.expected(ep)
        if ep.seq > expected:
            self.episodes_out_of_order += 1
            raise P.ProtocolError("out_of_order", f"actor {ep.actor_id} (incarnation {ep.incarnation}) sent seq "
                                                  f"{ep.seq} before {expected}; it is asked for {expected} on again")
        if last is not None and expected > last + 1:
            # Sequence numbers count every episode an actor publishes: a gap its sender can no longer fill
            # is episodes that were sent and are not here (an older actor's lost on the way, or ones it
            # gave up on when it stopped).
            self.episodes_missing += expected - last - 1
        if sender not in self.last_seq and len(self.last_seq) >= MAX_SENDERS:
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

    def expected(self, ep: P.Episode) -> int:
        """The seq the buffer stores next from `ep`'s sender: the one after its last, unless the sender no
        longer holds that one (an actor before 0.9 holds none but the episode it sends)."""
        held_from = ep.seq if ep.resend_from is None else ep.resend_from
        last = self.last_seq.get((ep.actor_id, ep.incarnation))
        return held_from if last is None else max(last + 1, held_from)

    def replay(self, ep: P.Episode) -> bool:
        """Store an episode from the episode log on a restart, unless the checkpoint already holds it. It was
        confirmed, so it is stored even after a gap (a record of the log that could not be read): the gap is
        counted missing."""
        if ep.seq <= self.last_seq.get((ep.actor_id, ep.incarnation), -1):
            return False
        if ep.seq > self.expected(ep):
            ep.resend_from = ep.seq
        self.store(ep)
        return True

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
        return {name: getattr(self, name) for name in self.COUNTERS + self.RESENT} | {
            "rejections": dict(self.rejections), "last_seq": [[a, inc, seq] for (a, inc), seq in self.last_seq.items()],
            "rollouts": [list(r) for r in self.rollouts]}

    def restore(self, state: dict[str, Any]) -> None:
        for name in self.COUNTERS:
            setattr(self, name, int(state[name]))
        for name in self.RESENT:
            setattr(self, name, int(state.get(name, 0)))
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
            "episodes_duplicate": self.episodes_duplicate,
            "episodes_out_of_order": self.episodes_out_of_order,
            "rejections": dict(self.rejections),
            "latest_episode_policy_version": self.last_episode_version,
            "updates_since_last_episode": self.limiter.samples - self.samples_at_last_episode,
        } | self.rollout_meta()
