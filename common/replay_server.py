"""The buffer's Zenoh ends of the episode and sample channels, `ZenohReplayServer`: a subscriber and a
queryable feeding one bounded inbox, so that the buffer's one thread takes episodes and queries in the order
they came. In one process the clients talk to the buffer's parts directly (`episode_channel.EpisodeStore`,
`sample_channel.BatchSource`).
"""

from __future__ import annotations

import zenoh

from silcr.common import protocol as P
from silcr.common.inbox import Inbox


class SampleQuery:
    """One sample query, held until the buffer answers it (the receiving end of the sample channel)."""

    def __init__(self, query: zenoh.Query, key: str) -> None:
        self._query = query
        self._key = key

    @property
    def payload(self) -> bytes | None:
        return self._query.payload.to_bytes() if self._query.payload is not None else None

    def answer(self, reply: P.BatchReply) -> None:
        with self._query:  # leaving the block finalizes the query, so the learner's get() ends at once
            self._query.reply(self._key, reply.encode())

    def refuse(self, why: str) -> None:
        with self._query:
            self._query.reply_err(why.encode())


class ZenohReplayServer:
    """The buffer's end of the episode and sample channels: a subscriber and a queryable that hand
    what arrives to one bounded `Inbox` (see there: a full inbox back-pressures the actors, so no
    episode is dropped), read by the service's one thread with `next()`."""

    def __init__(self, session: zenoh.Session, keys: P.Keys, inbox: Inbox,
                 max_episode_bytes: int = P.DEFAULT_MAX_EPISODE_BYTES) -> None:
        self.inbox = inbox
        self.max_episode_bytes = max_episode_bytes
        self.episode_bytes_received = 0  # every episode message's size, oversized ones included
        session.declare_subscriber(keys.episodes, self._on_episode)
        session.declare_queryable(keys.sample, lambda q: inbox.put_request(SampleQuery(q, keys.sample)))

    def _on_episode(self, sample: zenoh.Sample) -> None:
        # The size first, from Zenoh's buffer: an oversized message is never copied into Python
        # (three of 240 MB left the buffer 500 MB larger), only its rejection is queued.
        size = len(sample.payload)
        self.episode_bytes_received += size
        if size > self.max_episode_bytes:
            self.inbox.put_data(P.ProtocolError("oversized", f"message of {size} bytes exceeds the limit of "
                                                             f"{self.max_episode_bytes}"))
        else:
            self.inbox.put_data(sample.payload.to_bytes())

    def next(self, timeout: float) -> bytes | P.ProtocolError | SampleQuery | None:
        """A waiting sample query (first), else an episode message (or the rejection of one too large to
        copy), else None after `timeout` s."""
        return self.inbox.get(timeout)

    def close(self) -> None:
        """Stop taking messages; refuse the queries still waiting (their learners retry elsewhere or stop)."""
        for query in self.inbox.close():
            query.refuse("buffer service is shutting down")
