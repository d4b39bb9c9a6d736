"""The sample channel, learner -> buffer -> learner, both ends: `BatchStream` asks for mixed batches over
Zenoh (`ZenohBatchStream`: queries kept in flight, a buffer's restart noticed) or in-process
(`InProcessBatchStream`). The buffer's end is `replay_server` (`SampleQuery`: one query, answered or refused).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
from typing import Iterator, Protocol

import numpy as np
import zenoh

from silcr.common import protocol as P
from silcr.common.lifecycle import StopFlag

log = logging.getLogger("clients")

#: A sample query unanswered for this long counts as failed and is retried.
QUERY_TIMEOUT_S = 10.0


class BatchSource(Protocol):
    """What the in-process stream needs of the buffer (`buffer_service.sampler.Sampler`): nothing in common/
    imports a component."""

    def sample(self, request: P.SampleRequest, keep_ratio: bool) -> P.BatchReply: ...


# ---------------------------------------------------------------------------
# buffer -> learner: mixed batches
# ---------------------------------------------------------------------------


class BatchStream:
    """Mixed batches from the buffer service.

    Iterating yields a `BatchReply` with status `ok`, or None when the buffer had
    nothing to give this time (warming up, rate-limited, unreachable; the stream
    has already waited as long as the buffer asked), so the caller can keep its
    own schedule. It ends when the stop flag is set.

    Every reply's `meta` describes the buffer (`last_reply`, a not-ready one too). The buffer's count of
    received transitions never goes back unless it restarted from an older
    checkpoint: the stream counts such restarts and the transitions they lost.
    """

    def __init__(self, stop: StopFlag | None = None) -> None:
        self._stop = stop or StopFlag()
        self.last_reply: P.BatchReply | None = None
        self.batches = 0
        self.not_ready = 0
        self.sample_errors = 0
        self.reply_rejections: collections.Counter[str] = collections.Counter()  # malformed replies, by reason
        self.buffer_restarts = 0
        self.transitions_lost = 0
        #: the last reply said the learner is ahead of the actors (at the end of a run: nothing more will come)
        self.rate_limited = False
        self.wait_times: collections.deque[float] = collections.deque(maxlen=2000)
        self._last_buffer_steps = 0

    def get(self) -> P.BatchReply | None:
        raise NotImplementedError

    def __iter__(self) -> Iterator[P.BatchReply | None]:
        while not self._stop.is_set():
            yield self.get()

    def _account(self, reply: P.BatchReply) -> P.BatchReply | None:
        self.last_reply = reply
        buffer_steps = int(reply.meta.get("env_steps", 0))
        if buffer_steps < self._last_buffer_steps:
            self.buffer_restarts += 1
            self.transitions_lost += self._last_buffer_steps - buffer_steps
            log.warning("the buffer service restarted: %d transitions it had received since its last checkpoint "
                        "are lost (%d in all)", self._last_buffer_steps - buffer_steps, self.transitions_lost)
        self._last_buffer_steps = buffer_steps
        if reply.status == "ok":
            self.batches += int(reply.meta["batches"])
            self.rate_limited = False
            return reply
        self.not_ready += 1
        self.rate_limited = reply.reason == "rate_limited"
        return None

    def stats(self) -> dict:
        waits = np.asarray(self.wait_times) * 1000 if self.wait_times else np.zeros(1)
        return {
            "batch_wait_ms_p50": float(np.percentile(waits, 50)),
            "batch_wait_ms_p99": float(np.percentile(waits, 99)),
            "not_ready_replies": self.not_ready,
            "sample_errors": self.sample_errors,
            "reply_rejections": dict(self.reply_rejections),
            "buffer_restarts": self.buffer_restarts,
            "transitions_lost": self.transitions_lost,
        }


class ZenohBatchStream(BatchStream):
    """Keeps `requests_in_flight` sample queries of `batches_per_request` batches outstanding, so the
    next batches cross the network while the current one trains."""

    def __init__(self, session: zenoh.Session, keys: P.Keys, request: P.SampleRequest, requests_in_flight: int,
                 stop: StopFlag, updates_before: int | None = None) -> None:
        super().__init__(stop)
        # The buffer serves only requests that name a live learner: this stream's token says it is one.
        # (An outside client's sampling would spend the learner's samples-per-insert budget.)
        if not request.learner:
            request = dataclasses.replace(request, learner=P.new_incarnation())
        self._token = session.liveliness().declare_token(keys.alive("learner", request.learner))
        self._request = request
        # A learner trains each batch before it asks for more, so its count of updates is the one it
        # restored (`updates_before`) plus the batches this stream has received: each request says it,
        # and the buffer's limiter takes it from the first (ReplayState.take_learner_count).
        self._updates_before = updates_before
        self._in_flight_limit = requests_in_flight
        self._querier = session.declare_querier(keys.sample, timeout=QUERY_TIMEOUT_S,
                                                consolidation=zenoh.ConsolidationMode.NONE)
        self._key = keys.sample
        self._in_flight: collections.deque = collections.deque()
        self._last_error_log = 0.0

    def _payload(self) -> bytes:
        if self._updates_before is None:
            return self._request.encode()
        return dataclasses.replace(self._request, updates=self._updates_before + self.batches).encode()

    def wait_for_buffer(self) -> None:
        """Block until a buffer service answers sample queries (or stop)."""
        if not self._querier.matching_status.matching:
            log.info("waiting for the buffer service on %s", self._key)
        while not self._querier.matching_status.matching and not self._stop.wait(0.1):
            pass

    def get(self) -> P.BatchReply | None:
        while len(self._in_flight) < self._in_flight_limit:
            self._in_flight.append(self._querier.get(payload=self._payload()))
        t0 = time.monotonic()
        reply = next(iter(self._in_flight.popleft()), None)
        self.wait_times.append(time.monotonic() - t0)
        if reply is None or reply.ok is None:
            self.sample_errors += 1
            why = "no reply" if reply is None else reply.err.payload.to_string()
            if time.monotonic() - self._last_error_log > 10:  # the buffer may be down for a while: do not flood the log
                log.warning("sample query failed (%s); retrying (%d failures so far)", why, self.sample_errors)
                self._last_error_log = time.monotonic()
            self._stop.wait(0.5)
            return None
        try:
            batch = P.BatchReply.decode(reply.ok.payload.to_bytes())
        except P.ProtocolError as e:
            self.sample_errors += 1
            self.reply_rejections[e.reason] += 1
            log.warning("malformed batch reply (%s): %s", e.reason, e)
            return None
        out = self._account(batch)
        if out is None:
            self._stop.wait(batch.retry_after_ms / 1000)
        return out


class InProcessBatchStream(BatchStream):
    """Samples straight from the buffer's state, keeping exactly the configured updates per step:
    it serves only the updates the inserted transitions are due (never runs ahead), and never waits."""

    def __init__(self, sampler: BatchSource, request: P.SampleRequest, stop: StopFlag | None = None) -> None:
        super().__init__(stop)
        self._sampler = sampler
        self._request = request

    def get(self) -> P.BatchReply | None:
        return self._account(self._sampler.sample(self._request, keep_ratio=True))

    def due(self) -> Iterator[P.BatchReply]:
        """Every batch the buffer can serve now."""
        while (batch := self.get()) is not None:
            yield batch
