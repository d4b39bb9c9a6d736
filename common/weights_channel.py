"""The weights channel, learner -> actors, both ends, and the rules for which weights an actor takes.

`WeightsServer` publishes (over Zenoh `ZenohWeightsServer`, paced by `fanout.FanoutPacer`; in-process
`InProcessWeights`); `WeightsClient` holds the newest policy an actor may act with (`ZenohWeightsClient`,
`InProcessWeightsClient`), and `WeightsClient._offer` is the one place that decides whether a set is taken.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable, Generic, TypeVar

import numpy as np
import zenoh

from silcr.common import protocol as P
from silcr.common.fanout import FanoutPacer
from silcr.common.lifecycle import StopFlag
from silcr.common.presence import Presence
from silcr.common.schedule import Every

log = logging.getLogger("clients")


# ---------------------------------------------------------------------------
# learner -> actors: weights
# ---------------------------------------------------------------------------

PolicyT = TypeVar("PolicyT")


class WeightsClient(Generic[PolicyT]):
    """The newest policy an actor has. `update()` takes new weights when there are any.

    Weights are taken when they are newer than the current ones or come from another
    learner incarnation (`Weights.supersedes`): a learner restarted from an older
    checkpoint counts versions again from there. Weights the policy cannot use
    (`make_policy` raises ProtocolError or ValueError, e.g. wrong shapes) are
    rejected and counted; the actor keeps acting with what it has.
    """

    def __init__(self, make_policy: Callable[[P.Weights], PolicyT], initial: P.Weights) -> None:
        self._make_policy = make_policy
        self.weights = initial
        self.policy: PolicyT = make_policy(initial)
        self._previous: tuple[P.Weights, PolicyT] | None = None  # the last good policy before the current one
        self._refused: set[tuple[int, int]] = set()  # (incarnation, version) of weights found unusable in use
        self.updates = 0
        self.rejections: collections.Counter[str] = collections.Counter()  # weights not taken, by reason
        self.latency_ms: collections.deque[float] = collections.deque(maxlen=100)
        self._warned: dict[str, Every] = {}  # one warning per reason every 10 s, with the count so far

    def _warn(self, reason: str, message: str) -> None:
        """A rejection's warning, grouped: a flood of bad weights (hundreds a second) logs one line per reason
        every 10 s with the count so far, as the buffer does for sample requests; every one is counted."""
        if self._warned.setdefault(reason, Every(10.0)).due():
            log.warning("%s (%d rejected for %s so far)", message, self.rejections[reason], reason)

    def _offer(self, new: P.Weights) -> bool:
        if not new.supersedes(self.weights) or (new.incarnation, new.version) in self._refused:
            return False
        try:
            policy = self._make_policy(new)
        except (P.ProtocolError, ValueError) as e:
            reason = getattr(e, "reason", "unusable")
            self.rejections[reason] += 1
            self._warn(reason, f"ignoring unusable weights (version {new.version}): {e}")
            return False
        self._previous = (self.weights, self.policy)
        self.weights, self.policy = new, policy
        self.updates += 1
        if new.sent_at:
            self.latency_ms.append(1000 * (time.time() - new.sent_at))  # same clock only on one machine
        return True

    def update(self) -> bool:
        """Take the newest weights if there are any; whether the policy changed."""
        raise NotImplementedError

    @property
    def version(self) -> int:
        return self.weights.version

    @property
    def rejected(self) -> int:
        return sum(self.rejections.values())

    def _malformed(self, e: P.ProtocolError) -> None:
        self.rejections[e.reason] += 1
        self._warn(e.reason, f"ignoring malformed weights ({e.reason}): {e}")

    def fall_back(self, reason: str) -> None:
        """The current weights turned out unusable in use (NaN actions): back to the previous policy, the current
        ones refused from now on, counted under `reason`."""
        self.rejections[reason] += 1
        self._refused.add((self.weights.incarnation, self.weights.version))
        self._warn(reason, f"weights version {self.weights.version} gave NaN or infinite actions; acting with version "
                           f"{self._previous[0].version if self._previous else '?'} again")
        if self._previous is not None:
            self.weights, self.policy = self._previous
            self._previous = None

    def stats(self) -> dict:
        return {"policy_version": self.version, "weights_rejected": self.rejected,
                "weights_rejections": dict(self.rejections),
                "weights_latency_ms_p50": float(np.median(self.latency_ms)) if self.latency_ms else None,
                "weights_latency_ms_p99": float(np.percentile(self.latency_ms, 99)) if self.latency_ms else None}


class ZenohWeightsClient(WeightsClient[PolicyT]):
    """Follows the weights topic keeping only the newest set (a slow actor never holds the learner
    back). Each message is decoded as it arrives, so a malformed one is counted even when a newer set
    replaces it before the actor looks (a paused actor looks every 0.25 s). At start it asks the
    learner's queryable for the latest weights, so a late joiner does not wait for the next
    broadcast; with no learner within `wait_s` it starts from `initial`."""

    def __init__(self, session: zenoh.Session, keys: P.Keys, make_policy: Callable[[P.Weights], PolicyT],
                 initial: Callable[[], P.Weights], wait_s: float, stop: StopFlag) -> None:
        super().__init__(make_policy, initial())
        self._lock = threading.Lock()
        self._newest: P.Weights | None = None
        self._sub = session.declare_subscriber(keys.weights, self._on_weights)  # before the fetch: none missed
        fetched = self._fetch(session, keys, wait_s, stop)
        if fetched is None or not self._offer(fetched):
            log.info("no learner answered; acting with a local random policy until weights arrive")

    def _fetch(self, session: zenoh.Session, keys: P.Keys, wait_s: float, stop: StopFlag) -> P.Weights | None:
        # Right after a session opens a query can find no queryable yet (discovery is
        # asynchronous), so wait for the learner's queryable to match before asking.
        querier = session.declare_querier(keys.weights, timeout=10.0)
        try:
            deadline = time.monotonic() + wait_s
            while not querier.matching_status.matching:
                if time.monotonic() > deadline or stop.wait(0.05):
                    return None
            for reply in querier.get():
                if reply.ok is not None:
                    try:
                        return P.Weights.decode(reply.ok.payload.to_bytes())
                    except P.ProtocolError as e:
                        self._malformed(e)
            return None
        finally:
            querier.undeclare()

    def _on_weights(self, sample: zenoh.Sample) -> None:
        try:
            weights = P.Weights.decode(sample.payload.to_bytes())
        except P.ProtocolError as e:
            self._malformed(e)
            return
        with self._lock:
            self._newest = weights

    def update(self) -> bool:
        with self._lock:
            new, self._newest = self._newest, None
        return new is not None and self._offer(new)


class WeightsServer:
    """The learner's side: `publish(weights)` reaches every actor (`final`: the run's last, sent whatever
    the pacing); `poll()` sends a publication the pacing held back once it is due."""

    def publish(self, weights: P.Weights, final: bool = False) -> None:
        raise NotImplementedError

    def poll(self) -> None:
        pass

    def stats(self) -> dict:
        return {}


class ZenohWeightsServer(WeightsServer):
    """Publishes with BLOCK congestion control and high priority, paced by `FanoutPacer` to a budget of
    bytes per second across all actors, and answers queries for the latest weights (late-joining actors
    ask at start; a query always gets the newest, held back or not)."""

    def __init__(self, session: zenoh.Session, keys: P.Keys, fanout_budget_bytes_per_s: float = 0.0) -> None:
        self._key = keys.weights
        self._latest = b""
        self._lock = threading.Lock()
        self.published = 0
        self.actors = Presence.actors(session, keys) if fanout_budget_bytes_per_s > 0 else None
        self.pacer = FanoutPacer(fanout_budget_bytes_per_s, lambda: len(self.actors) if self.actors is not None else 1)
        self._pub = session.declare_publisher(keys.weights, congestion_control=zenoh.CongestionControl.BLOCK,
                                              priority=zenoh.Priority.DATA_HIGH)
        session.declare_queryable(keys.weights, self._answer)

    def _answer(self, query: zenoh.Query) -> None:
        with query:  # leaving the block finalizes the query
            with self._lock:
                latest = self._latest
            if latest:
                query.reply(self._key, latest)

    def publish(self, weights: P.Weights, final: bool = False) -> None:
        payload = weights.encode()
        with self._lock:
            self._latest = payload
        self._send(self.pacer.offer(payload, final))

    def poll(self) -> None:
        self._send(self.pacer.due())

    def _send(self, payload: bytes | None) -> None:
        if payload is not None:
            self._pub.put(payload)
            self.published += 1

    def stats(self) -> dict:
        """What goes out: each publication reaches every actor (`weights_bytes` x actors), paced to the budget."""
        return {"weights_published": self.published, "weights_bytes": len(self._latest),
                "weights_held": self.pacer.held, "weights_replaced": self.pacer.replaced,
                "weights_fanout_budget_mb_s": self.pacer.budget / 1e6,
                "weights_actors": len(self.actors) if self.actors is not None else None}


class InProcessWeights(WeightsServer):
    """Server and clients in one process: `publish` sets the latest weights, each client's `update` takes them."""

    def __init__(self) -> None:
        self.latest: P.Weights | None = None

    def publish(self, weights: P.Weights, final: bool = False) -> None:
        # the actors act with what the wire would have given them (float16 weights rounded)
        self.latest = weights if weights.wire_dtype == "float32" else P.Weights.decode(weights.encode())

    def client(self, make_policy: Callable[[P.Weights], PolicyT], initial: P.Weights) -> "InProcessWeightsClient[PolicyT]":
        c = InProcessWeightsClient(self, make_policy, initial)
        c.update()  # as a Zenoh client asks the learner at start
        return c


class InProcessWeightsClient(WeightsClient[PolicyT]):
    def __init__(self, board: InProcessWeights, make_policy: Callable[[P.Weights], PolicyT], initial: P.Weights) -> None:
        super().__init__(make_policy, initial)
        self._board = board

    def update(self) -> bool:
        return self._board.latest is not None and self._offer(self._board.latest)
