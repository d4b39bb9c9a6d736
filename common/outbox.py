"""An actor's outbox: its finished episodes that the buffer has not confirmed yet, and which of them to send.

Episodes wait here, oldest first, until a cumulative `EpisodeAck` says the buffer holds them
durably (docs/reliability.md, "What confirmed means"). What is due to be sent (`due`): the episodes
never sent; those from a gap the buffer asked for again (`resend_from` in an ack; one ask per gap,
since the refusals of what was in flight behind it repeat it for a moment); and, as a probe whose
answer says what is missing, the oldest one when a buffer comes back after none listened or when no
ack has come for `ack_timeout` seconds (doubled while none comes, up to MAX_ACK_TIMEOUT_S). A stepping
actor's next episodes show the buffer any gap behind the probe; a stopping actor sends none, so once it
`hurry`s, a timeout sends everything unconfirmed again (the buffer drops what it already holds). The
bound is in bytes; the outbox always takes one episode, however large. The Zenoh end that sends
and hears the acks is `episode_channel.ZenohEpisodeWriter`.
"""

from __future__ import annotations

import collections
import math
import threading
import time

from silcr.common import protocol as P

#: An actor's outbox holds this many bytes of episodes by default (`--actor-outbox-mb`).
DEFAULT_OUTBOX_BYTES = 64 * 1024 * 1024
#: Seconds without an ack before an actor probes the buffer with its oldest unconfirmed episode. A
#: buffer that keeps up acks within tens of milliseconds.
ACK_TIMEOUT_S = 5.0
MAX_ACK_TIMEOUT_S = 60.0
#: An ask to send again from the same seq within this many seconds is the same ask.
REWIND_HOLDOFF_S = 1.0


def ep_bytes(ep: P.Episode) -> int:
    """What an episode holds in memory (its arrays), for the outbox's bound."""
    return ep.obs.nbytes + ep.actions.nbytes + ep.rewards.nbytes


class Outbox:
    """Unconfirmed episodes by seq, oldest first; safe to use from the actor's thread and Zenoh's callbacks."""

    def __init__(self, limit_bytes: int = DEFAULT_OUTBOX_BYTES, ack_timeout: float = ACK_TIMEOUT_S) -> None:
        self.limit_bytes = limit_bytes
        self._lock = threading.Lock()
        self._episodes: collections.OrderedDict[int, P.Episode] = collections.OrderedDict()
        self.bytes = 0
        self._next = 0  # the next seq to send
        self._sent_upto = 0  # one past the highest seq ever sent: a send below it is a resend
        self._confirmed = -1
        self._rewind_to: int | None = None  # set by an ack asking for episodes again
        self._rewound, self._rewound_at = -1, -math.inf  # the last such ask taken, and when
        self._base_timeout = self._timeout = ack_timeout
        self._last_progress = time.monotonic()
        self._stopping = False  # set by `hurry`: a timeout sends everything unconfirmed again, not one probe
        self.confirmed = self.sent = self.resent = self.rewinds = self.acks = 0

    def __len__(self) -> int:
        return len(self._episodes)

    def full(self) -> bool:
        return self.bytes >= self.limit_bytes

    def add(self, ep: P.Episode) -> None:
        with self._lock:
            self._episodes[ep.seq] = ep
            self.bytes += ep_bytes(ep)
            if len(self._episodes) == 1:
                self._last_progress = time.monotonic()  # the ack clock starts with the oldest unconfirmed

    def take_ack(self, ack: P.EpisodeAck) -> int:
        """Let go of what `ack` confirms; remember an ask to send again. Returns how many it confirmed."""
        n = 0
        with self._lock:
            self.acks += 1
            while self._episodes and next(iter(self._episodes)) <= ack.confirmed:
                _, ep = self._episodes.popitem(last=False)
                self.bytes -= ep_bytes(ep)
                n += 1
            if ack.confirmed > self._confirmed:
                self._confirmed = ack.confirmed
                self._last_progress = time.monotonic()
                self._timeout = self._base_timeout
            if ack.resend_from is not None and ack.resend_from < self._next:
                self._rewind_to = ack.resend_from
        self.confirmed += n
        return n

    def anything_due(self, now: float) -> bool:
        """Cheap: whether `due` could return anything but a probe for a buffer that came back. Under the lock: an
        ack taken in Zenoh's thread can empty the outbox between the two looks (StopIteration, seen once)."""
        with self._lock:
            return bool(self._episodes) and (self._rewind_to is not None or now - self._last_progress > self._timeout
                                             or next(reversed(self._episodes)) >= self._next)

    def due(self, now: float, buffer_came_back: bool) -> list[P.Episode]:
        """What to send now, in order, each stamped with the oldest seq this outbox still holds."""
        with self._lock:
            if not self._episodes:
                return []
            oldest = next(iter(self._episodes))
            timed_out = now - self._last_progress > self._timeout
            rewind, self._rewind_to = self._rewind_to, None
            if rewind is not None and rewind < self._next and (
                    rewind != self._rewound or now - self._rewound_at > REWIND_HOLDOFF_S):
                self._next = max(rewind, oldest)
                self._rewound, self._rewound_at = rewind, now
                self.rewinds += 1
            due = []
            if buffer_came_back or timed_out:
                # Doubled while acks do not come; a buffer that is back starts the clock afresh.
                self._timeout = self._base_timeout if buffer_came_back else min(2 * self._timeout, MAX_ACK_TIMEOUT_S)
                self._last_progress = now
                if self._stopping and oldest < self._next:
                    # Lost behind the probe and nothing after it to show the gap: all of it again, now.
                    self._next = oldest
                    self.rewinds += 1
                elif oldest < self._next:
                    due.append(self._episodes[oldest])
            due += [ep for seq, ep in self._episodes.items() if seq >= self._next]
        for ep in due:
            ep.resend_from = oldest  # what this actor can still send again, as of now
        return due

    def mark_sent(self, ep: P.Episode) -> None:
        self.sent += 1
        self.resent += ep.seq < self._sent_upto
        self._next = max(self._next, ep.seq + 1)
        self._sent_upto = max(self._sent_upto, ep.seq + 1)

    def hurry(self, ack_timeout: float) -> None:
        """The actor stops: send everything unconfirmed again once `ack_timeout` s pass without an ack (the wait
        doubling while none comes, as a probe's does): it has no time to back off, nor new episodes whose arrival
        would show the buffer a gap."""
        self._base_timeout = self._timeout = min(self._timeout, ack_timeout)
        self._stopping = True

    def give_up(self) -> tuple[int, int, int] | None:
        """Empty the outbox (the actor stops); (how many, first seq, last seq) it held, or None."""
        with self._lock:
            if not self._episodes:
                return None
            held = (len(self._episodes), next(iter(self._episodes)), next(reversed(self._episodes)))
            self._episodes.clear()
            self.bytes = 0
            return held

    def stats(self) -> dict:
        return {"episodes_unconfirmed": len(self._episodes), "outbox_bytes": self.bytes,
                "outbox_limit_bytes": self.limit_bytes, "outbox_full": self.full(), "episodes_sent": self.sent,
                "episodes_resent": self.resent, "resend_rounds": self.rewinds, "acks_received": self.acks}
