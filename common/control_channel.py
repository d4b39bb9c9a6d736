"""The control and stats channels: the buffer's throttle to the actors, the run's end announced to everyone
(BLOCK: never lost), and any component's stats to monitors (DROP: superseded every second)."""

from __future__ import annotations

import collections
import logging
from typing import Callable

import zenoh

from silcr.common import protocol as P
from silcr.common.lifecycle import StopFlag

log = logging.getLogger("clients")


# ---------------------------------------------------------------------------
# any component -> monitors: stats
# ---------------------------------------------------------------------------


class StatsPublisher:
    """JSON stats on one key. DROP congestion control and low priority: stats are superseded every
    second, and a slow monitor must never hold a component back."""

    def __init__(self, session: zenoh.Session, key: str, extra: Callable[[], dict] | None = None,
                 on_put: Callable[[], None] | None = None) -> None:
        self._pub = session.declare_publisher(key, encoding=zenoh.Encoding.APPLICATION_JSON,
                                              congestion_control=zenoh.CongestionControl.DROP,
                                              priority=zenoh.Priority.DATA_LOW)
        self._extra = extra
        self._on_put = on_put

    def put(self, stats: dict) -> None:
        """Publish `stats` (and the `extra` counters every message of this component carries); `on_put` follows
        (the component's heartbeat, `common.health`: written from the loop that publishes)."""
        self._pub.put(P.Stats(stats | (self._extra() if self._extra else {})).encode())
        if self._on_put is not None:
            self._on_put()


# ---------------------------------------------------------------------------
# control: the end of a run
# ---------------------------------------------------------------------------


class Throttle:
    """The buffer's rate limiter telling actors to pause or go on (BLOCK, high priority)."""

    def __init__(self, session: zenoh.Session, keys: P.Keys) -> None:
        self._pub = session.declare_publisher(keys.control_throttle, congestion_control=zenoh.CongestionControl.BLOCK,
                                              priority=zenoh.Priority.DATA_HIGH)

    def send(self, paused: bool) -> None:
        self._pub.put(P.ThrottleNotice(paused).encode())


class Shutdown:
    """Announces the end of the run to every component (BLOCK: it must not be lost)."""

    def __init__(self, session: zenoh.Session, keys: P.Keys) -> None:
        self._pub = session.declare_publisher(keys.control_shutdown, congestion_control=zenoh.CongestionControl.BLOCK)

    def announce(self, reason: str) -> None:
        self._pub.put(P.ShutdownNotice(reason).encode())


def finished_reason() -> str:
    """The `StopFlag` reason a component stops with when the run's end was announced as finished."""
    return f"shutdown message ({P.ShutdownNotice.FINISHED})"


class ShutdownListener:
    """Sets `stop` when anyone announces the end of the run; a malformed announcement is counted
    (`rejections`, by reason) and ignored."""

    def __init__(self, session: zenoh.Session, keys: P.Keys, stop: StopFlag) -> None:
        self._stop = stop
        self.rejections: collections.Counter[str] = collections.Counter()
        session.declare_subscriber(keys.control_shutdown, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        try:
            notice = P.ShutdownNotice.decode(sample.payload.to_bytes())
        except P.ProtocolError as e:
            self.rejections[e.reason] += 1
            log.warning("ignoring malformed shutdown message (%s): %s", e.reason, e)
            return
        self._stop.set(f"shutdown message ({notice.reason})")

    def stats(self) -> dict:
        return {"shutdown_rejections": dict(self.rejections)}


def stop_on_shutdown(session: zenoh.Session, keys: P.Keys, stop: StopFlag) -> ShutdownListener:
    """Set `stop` when anyone announces the end of the run."""
    return ShutdownListener(session, keys, stop)
