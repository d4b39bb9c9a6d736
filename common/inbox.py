"""A bounded hand-over from Zenoh's callback threads to a service's one working thread.

Two lanes: requests (served first, so a burst of episodes never makes the learner
wait) and data. `put_*` blocks while its lane is full: the callback then holds
Zenoh's delivery, which back-pressures the publisher (BLOCK congestion control), so
nothing is dropped while the service runs. Once `close()` is called a put gives up
and counts the item as dropped (`dropped_at_close`).
"""

from __future__ import annotations

import collections
import threading
from typing import Any


class Inbox:
    def __init__(self, max_data: int = 64, max_requests: int = 256) -> None:
        self._cond = threading.Condition()
        self._data: collections.deque[Any] = collections.deque()
        self._requests: collections.deque[Any] = collections.deque()
        self.max_data = max_data
        self.max_requests = max_requests
        self.closed = False
        self.dropped_at_close = 0
        self.blocked_puts = 0

    def _put(self, q: collections.deque, item: Any, limit: int) -> None:
        with self._cond:
            if len(q) >= limit:
                self.blocked_puts += 1
            while len(q) >= limit and not self.closed:
                self._cond.wait(0.1)
            if self.closed:
                self.dropped_at_close += 1
                return
            q.append(item)
            self._cond.notify_all()

    def put_data(self, item: Any) -> None:
        self._put(self._data, item, self.max_data)

    def put_request(self, item: Any) -> None:
        self._put(self._requests, item, self.max_requests)

    def get(self, timeout: float) -> Any | None:
        """The next request, else the next data item, waiting up to `timeout` s; None if there is none."""
        with self._cond:
            if not (self._requests or self._data):
                self._cond.wait(timeout)
            if self._requests:
                item = self._requests.popleft()
            elif self._data:
                item = self._data.popleft()
            else:
                return None
            self._cond.notify_all()
            return item

    def depth(self) -> tuple[int, int]:
        """(data, requests) waiting."""
        with self._cond:
            return len(self._data), len(self._requests)

    def state(self) -> dict[str, int]:
        return {"blocked_puts": self.blocked_puts, "dropped_at_close": self.dropped_at_close}

    def restore(self, state: dict[str, int]) -> None:
        self.blocked_puts, self.dropped_at_close = int(state["blocked_puts"]), int(state["dropped_at_close"])

    def close(self) -> list[Any]:
        """Stop accepting; return the requests still waiting so they can be answered."""
        with self._cond:
            self.closed = True
            pending = list(self._requests)
            self._requests.clear()
            self._cond.notify_all()
            return pending
