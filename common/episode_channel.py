"""The episode channel, actor -> buffer, both ends: `EpisodeWriter` over Zenoh (`ZenohEpisodeWriter`, BLOCK,
holding each episode until the buffer confirms it) or in-process (`InProcessEpisodeWriter`, straight into the
buffer's intake, `EpisodeStore`). The buffer's Zenoh end is `replay_server.ZenohReplayServer` for the episodes and
`EpisodeAcks` for the confirmations; the throttle that pauses a writer comes back on the control channel
(`control_channel.Throttle`).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

import zenoh

from silcr.common import protocol as P
from silcr.common.lifecycle import StopFlag
from silcr.common.outbox import ACK_TIMEOUT_S, DEFAULT_OUTBOX_BYTES, Outbox

log = logging.getLogger("clients")


class EpisodeStore(Protocol):
    """What the in-process writer needs of the buffer (`buffer_service.intake.Intake`): nothing in common/
    imports a component."""

    limits: P.EpisodeLimits

    def store(self, ep: P.Episode) -> None: ...

    def reject(self, e: P.ProtocolError) -> None: ...


#: How long a stopping actor waits for a buffer out of reach to come back and confirm its last episodes.
RECONNECT_GRACE_S = 3.0
#: A stopping actor probes the buffer this often while its last episodes are unconfirmed (a probe or its
#: ack sent while a link comes back can be lost before the routes are there again).
CLOSE_PROBE_S = 1.0


# ---------------------------------------------------------------------------
# actor -> buffer: episodes
# ---------------------------------------------------------------------------


class EpisodeWriter:
    """Writes finished episodes to the buffer service; `paused()` says whether actors should wait."""

    def __init__(self) -> None:
        self.written = 0
        self.unwritten = 0  # episodes given up because the process was stopping
        self.waited_for_buffer_s = 0.0

    def paused(self) -> bool:
        return False

    def wait_unpaused(self, timeout: float) -> bool:
        """Wait up to `timeout` s for the buffer to let inserts go on; True if it does."""
        return not self.paused()

    def buffer_listening(self) -> bool:
        """Whether a buffer service would receive an episode written now."""
        return True

    def wait_for_buffer(self, timeout: float) -> bool:
        """Wait up to `timeout` s for a buffer service to listen (counted in `waited_for_buffer_s`); True if one does."""
        return self.buffer_listening()

    def write(self, ep: P.Episode) -> bool:
        """Store `ep` (or keep it until the buffer confirms it); False if stopped first (the episode is lost)."""
        raise NotImplementedError

    def outbox_full(self) -> bool:
        """Whether the episodes waiting for the buffer's confirmation fill what the writer may hold."""
        return False

    def wait_for_room(self, timeout: float) -> bool:
        return not self.outbox_full()

    def pump(self) -> None:
        """Send what is due (new episodes, or ones the buffer did not confirm)."""

    def close(self, timeout: float) -> None:
        """Wait up to `timeout` s for what is unconfirmed; count the rest as not written."""

    def stats(self) -> dict:
        return {"episodes_written": self.written, "episodes_unwritten": self.unwritten,
                "waited_for_buffer_s": self.waited_for_buffer_s}


class ZenohEpisodeWriter(EpisodeWriter):
    """Publishes with BLOCK congestion control and keeps every episode until the buffer confirms it.

    BLOCK alone does not hold an episode: a put blocked for 5 s (a congested or cut link) makes Zenoh
    close the transport, and what its queues held is gone (issue 63). So each episode waits in a
    bounded `Outbox` until the buffer's cumulative ack (`EpisodeAck`, on this actor's own key) says it
    is held durably; `written` counts those. The outbox says what to send again (`outbox.py`); a full
    one (`outbox_full`) stops the actor stepping, as the rate limiter does.
    """

    def __init__(self, session: zenoh.Session, keys: P.Keys, stop: StopFlag, actor_id: int, incarnation: int,
                 outbox_bytes: int = DEFAULT_OUTBOX_BYTES, ack_timeout: float = ACK_TIMEOUT_S) -> None:
        super().__init__()
        self._stop = stop
        self.actor_id, self.incarnation = actor_id, incarnation
        self._pub = session.declare_publisher(keys.episodes, congestion_control=zenoh.CongestionControl.BLOCK,
                                              priority=zenoh.Priority.DATA)
        # A callback, not a channel to poll: a paused actor sleeps until the notice that lets it
        # go on (polling every 10 ms cost each paused actor 5% of a core, so 128 paced actors
        # left the learner about one update a second on 2 cores: docs/scaling.md).
        self._paused = False
        self._resumed = threading.Event()
        self._resumed.set()
        self.throttle_rejections: collections.Counter[str] = collections.Counter()
        self._throttle = session.declare_subscriber(keys.control_throttle, self._on_throttle)
        self.outbox = Outbox(outbox_bytes, ack_timeout)
        self._acked = threading.Event()
        self._listened, self._came_back = True, False
        self.outbox_full_s = 0.0
        self.ack_rejections: collections.Counter[str] = collections.Counter()
        self._acks = session.declare_subscriber(keys.episode_acks(actor_id), self._on_ack)

    def _on_throttle(self, sample: zenoh.Sample) -> None:
        try:
            paused = P.ThrottleNotice.decode(sample.payload.to_bytes()).paused
        except P.ProtocolError as e:
            self.throttle_rejections[e.reason] += 1
            log.warning("ignoring malformed throttle message (%s): %s", e.reason, e)
            return
        self._paused = paused
        (self._resumed.clear if paused else self._resumed.set)()

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            ack = P.EpisodeAck.decode(sample.payload.to_bytes())
        except P.ProtocolError as e:
            self.ack_rejections[e.reason] += 1
            log.warning("ignoring malformed episode ack (%s): %s", e.reason, e)
            return
        if (ack.actor_id, ack.incarnation) == (self.actor_id, self.incarnation):  # not a predecessor's
            self.written += self.outbox.take_ack(ack)
            self._acked.set()

    def paused(self) -> bool:
        """The latest throttle message's word."""
        return self._paused

    def wait_unpaused(self, timeout: float) -> bool:
        return self._resumed.wait(timeout)

    def buffer_listening(self) -> bool:
        listening = self._pub.matching_status.matching
        if listening and not self._listened:
            self._came_back = True  # probe with the oldest unconfirmed: this buffer may not have them all
        self._listened = listening
        return listening

    def wait_for_buffer(self, timeout: float) -> bool:
        t0 = time.monotonic()
        # Polled: a waiting actor wakes 20 times a second, far less than the 10 ms poll that cost 5% of a core.
        while not self.buffer_listening() and time.monotonic() - t0 < timeout and not self._stop.wait(0.05):
            pass
        self.waited_for_buffer_s += time.monotonic() - t0
        return self.buffer_listening()

    def outbox_full(self) -> bool:
        return self.outbox.full()

    def wait_for_room(self, timeout: float) -> bool:
        """Wait up to `timeout` s for acks to make room in the outbox, sending again what is due meanwhile."""
        t0 = time.monotonic()
        while self.outbox.full() and time.monotonic() - t0 < timeout and not self._stop.is_set():
            self._acked.clear()
            self.pump()
            self._acked.wait(min(0.05, timeout))
        self.outbox_full_s += time.monotonic() - t0
        return not self.outbox.full()

    def write(self, ep: P.Episode) -> bool:
        """Keep `ep` until the buffer confirms it and send it now if a buffer listens (always True: an
        episode is given up only when the actor stops, `close`)."""
        self.outbox.add(ep)
        self.pump()
        return True

    def pump(self) -> None:
        """Send what the outbox says is due. Actor thread only; cheap when nothing is (it runs after every step)."""
        now = time.monotonic()
        if not (self._came_back or self.outbox.anything_due(now)) or not self.buffer_listening():
            return
        came_back, self._came_back = self._came_back, False
        for ep in self.outbox.due(now, came_back):
            self._pub.put(ep.encode())
            self.outbox.mark_sent(ep)

    def close(self, timeout: float) -> None:
        """Wait up to `timeout` s for the buffer to confirm what is left (for a buffer out of reach, up to
        RECONNECT_GRACE_S of it: a transport Zenoh closed comes back within a second or two); count the
        rest as not written."""
        t0 = time.monotonic()
        self.outbox.hurry(CLOSE_PROBE_S)
        while len(self.outbox) and (elapsed := time.monotonic() - t0) < timeout and (
                self.buffer_listening() or elapsed < RECONNECT_GRACE_S):
            self._acked.clear()
            self.pump()
            self._acked.wait(0.1)
        held = self.outbox.give_up()
        if held is not None:
            self.unwritten += held[0]
            log.warning("stopping with %d episodes the buffer has not confirmed (seq %d to %d)", *held)

    def stats(self) -> dict:
        return super().stats() | self.outbox.stats() | {
            "malformed_throttle": sum(self.throttle_rejections.values()),
            "throttle_rejections": dict(self.throttle_rejections),
            "outbox_full_s": self.outbox_full_s, "malformed_acks": sum(self.ack_rejections.values()),
        }


class EpisodeAcks:
    """The buffer's end of the acks: one cumulative `EpisodeAck` per actor that sent since the last flush.

    Episodes are noted as they are handled (`note`); `send` goes out once the episode log holds them
    (service.run_buffer), so an ack never confirms what a crash would lose. Bounded by the senders.
    """

    def __init__(self, session: zenoh.Session, keys: P.Keys) -> None:
        self._session, self._keys = session, keys
        self.pending: dict[tuple[int, int], int | None] = {}  # sender -> the seq to send again from, if asked
        self.sent = 0

    def note(self, ep: P.Episode, resend_from: int | None = None) -> None:
        """`ep` was stored or refused; `resend_from`: ask its sender for its episodes again from there."""
        self.pending[(ep.actor_id, ep.incarnation)] = resend_from

    def send(self, confirmed: Callable[[tuple[int, int]], int]) -> None:
        """Ack every pending sender with what `confirmed` says the buffer holds of it."""
        for (actor_id, incarnation), resend_from in self.pending.items():
            ack = P.EpisodeAck(actor_id, incarnation, confirmed((actor_id, incarnation)), resend_from)
            self._session.put(self._keys.episode_acks(actor_id), ack.encode(),
                              congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA_HIGH)
            self.sent += 1
        self.pending.clear()


class InProcessEpisodeWriter(EpisodeWriter):
    """Stores straight into the buffer's intake. Never paused: the single-process loop keeps the ratio itself."""

    def __init__(self, intake: EpisodeStore) -> None:
        super().__init__()
        self._intake = intake

    def write(self, ep: P.Episode) -> bool:
        """Store `ep` after the checks a message gets on arrival (`validate_episode`): a NaN in an episode is
        refused and counted here as the buffer service refuses it from the wire."""
        try:
            P.validate_episode(ep, self._intake.limits)
        except P.ProtocolError as e:
            self._intake.reject(e)
            return True
        self._intake.store(ep)
        self.written += 1
        return True
