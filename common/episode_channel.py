"""The episode channel, actor -> buffer, both ends: `EpisodeWriter` over Zenoh (`ZenohEpisodeWriter`, BLOCK)
or in-process (`InProcessEpisodeWriter`, straight into the buffer's `Replay`). The buffer's Zenoh end is
`replay_server.ZenohReplayServer`; the throttle that pauses a writer comes back on the control channel
(`control_channel.Throttle`).
"""

from __future__ import annotations

import collections
import logging
import threading
import time

import zenoh

from silcr.common import protocol as P
from silcr.common.lifecycle import StopFlag
from silcr.common.replay_server import Replay

log = logging.getLogger("clients")


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
        """Store `ep`, waiting while no buffer service is there; False if stopped first (the episode is lost)."""
        raise NotImplementedError

    def stats(self) -> dict:
        return {"episodes_written": self.written, "episodes_unwritten": self.unwritten,
                "waited_for_buffer_s": self.waited_for_buffer_s}


class ZenohEpisodeWriter(EpisodeWriter):
    """Publishes with BLOCK congestion control; with no buffer service subscribed a put would vanish,
    so `write` holds the episode (and the actor) until one is back."""

    def __init__(self, session: zenoh.Session, keys: P.Keys, stop: StopFlag) -> None:
        super().__init__()
        self._stop = stop
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

    def _on_throttle(self, sample: zenoh.Sample) -> None:
        try:
            paused = P.ThrottleNotice.decode(sample.payload.to_bytes()).paused
        except P.ProtocolError as e:
            self.throttle_rejections[e.reason] += 1
            log.warning("ignoring malformed throttle message (%s): %s", e.reason, e)
            return
        self._paused = paused
        (self._resumed.clear if paused else self._resumed.set)()

    def paused(self) -> bool:
        """The latest throttle message's word."""
        return self._paused

    def wait_unpaused(self, timeout: float) -> bool:
        return self._resumed.wait(timeout)

    def buffer_listening(self) -> bool:
        return self._pub.matching_status.matching

    def wait_for_buffer(self, timeout: float) -> bool:
        t0 = time.monotonic()
        # Polled: a waiting actor wakes 20 times a second, far less than the 10 ms poll that cost 5% of a core.
        while not self.buffer_listening() and time.monotonic() - t0 < timeout and not self._stop.wait(0.05):
            pass
        self.waited_for_buffer_s += time.monotonic() - t0
        return self.buffer_listening()

    def write(self, ep: P.Episode) -> bool:
        payload = ep.encode()
        if not self.buffer_listening():
            # The actor's loop stops stepping while no buffer listens (`buffer_listening`); this catches
            # a buffer that left between that check and the episode's end.
            log.info("no buffer service is listening; holding episode %d until one is", ep.seq)
            while not self.wait_for_buffer(1.0) and not self._stop.is_set():
                pass
            if self._stop.is_set():
                log.warning("stopping with episode %d unpublished (no buffer service)", ep.seq)
                self.unwritten += 1
                return False
        self._pub.put(payload)
        self.written += 1
        return True

    def stats(self) -> dict:
        return super().stats() | {"malformed_throttle": sum(self.throttle_rejections.values()),
                                  "throttle_rejections": dict(self.throttle_rejections)}


class InProcessEpisodeWriter(EpisodeWriter):
    """Stores straight into the buffer's state. Never paused: the single-process loop keeps the ratio itself."""

    def __init__(self, replay: Replay) -> None:
        super().__init__()
        self._replay = replay

    def write(self, ep: P.Episode) -> bool:
        """Store `ep` after the checks a message gets on arrival (`validate_episode`): a NaN in an episode is
        refused and counted here as the buffer service refuses it from the wire."""
        try:
            P.validate_episode(ep, self._replay.limits)
        except P.ProtocolError as e:
            self._replay.reject(e)
            return True
        self._replay.store(ep)
        self.written += 1
        return True
