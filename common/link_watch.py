"""Whether a component's Zenoh session is linked to anyone, logged when that changes.

Zenoh reconnects by itself after a lost link (a router restart, a network cut) and
re-declares subscriptions and tokens; the session raises nothing, and a liveliness
subscriber on the far side's token does not see it leave when the link that carried it
dies. Without this watch a component cut off from the run logs nothing: an actor
blocked on its next episode looks like a slow one. The watch polls the session's
routers and peers (`session.info`) a few times a second and logs the loss as a WARNING
and the return with the outage's length.
"""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from silcr.common.lifecycle import StopFlag

log = logging.getLogger(__name__)

POLL_S = 0.25


def linked(session: zenoh.Session) -> bool:
    """Whether the session has a router or a peer now."""
    return bool(session.info.routers_zid()) or bool(session.info.peers_zid())


class LinkWatch:
    """A thread that logs when `session` loses its last link and when it has one again.

    A loss while `stop` is set is the run ending (the router stops last, but a peer may
    go first), so it is not reported. `close()` before the session closes."""

    def __init__(self, session: zenoh.Session, stop: StopFlag, name: str) -> None:
        self._session, self._stop, self._name = session, stop, name
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="silcr-link-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        lost_at: float | None = None
        was_linked = linked(self._session)  # a peer may start alone: only a link lost later is reported
        while not self._done.wait(POLL_S):
            now_linked = linked(self._session)
            if was_linked and not now_linked and not self._stop.is_set():
                lost_at = time.monotonic()
                log.warning("%s lost its last Zenoh link (router or peers): nothing reaches it or leaves it until "
                            "Zenoh reconnects", self._name)
            elif now_linked and not was_linked and lost_at is not None:
                log.info("%s linked again after %.1f s", self._name, time.monotonic() - lost_at)
                lost_at = None
            was_linked = now_linked

    def close(self) -> None:
        self._done.set()
        self._thread.join()
