"""Protocol clients: both ends of every channel, each over Zenoh or in-process.

    channel    sending end                       receiving end
    episodes   EpisodeWriter (actor)             ReplayServer.next() (buffer)
    sample     BatchStream (learner)             ReplayServer.next() -> SampleQuery.answer() (buffer)
    weights    WeightsServer (learner)           WeightsClient (actor): update(); .policy
    throttle   Throttle.send(paused) (buffer)    EpisodeWriter.paused() (actor)
    shutdown   Shutdown.announce(reason)         stop_on_shutdown (everyone)
    stats      StatsPublisher.put(dict)          any Zenoh client (silcr monitor, TensorBoard's feeder)
    liveliness (role_session declares tokens;    Presence: the actors and the sampling learners
               BatchStream its learner's)        alive now (buffer)

The roles (`silcr.actor.service`, `silcr.learner.service`, `silcr.buffer_service.service`)
are loops over these objects and never touch keys, codecs or Zenoh themselves. The
Zenoh clients are what `silcr train` and a run spread over machines use; the
in-process ones let `silcr train --single-process` run the very same actor and
learner code in one process, in a fixed order, with no network (deploy/single_process.py).

The in-process clients reach the buffer through `Replay`, the two methods of
`silcr.buffer_service.replay.ReplayState` they need, so this module never imports
a component.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from typing import Callable, Generic, Iterator, Protocol, TypeVar

import numpy as np
import zenoh

from silcr.common import protocol as P
from silcr.common.inbox import Inbox
from silcr.common.lifecycle import StopFlag
from silcr.common.schedule import Every

log = logging.getLogger("clients")

#: A sample query unanswered for this long counts as failed and is retried.
QUERY_TIMEOUT_S = 10.0


class Replay(Protocol):
    """What the in-process clients need of the buffer service's state."""

    limits: P.EpisodeLimits

    def store(self, ep: P.Episode) -> None: ...

    def reject(self, e: P.ProtocolError) -> None: ...

    def sample(self, request: P.SampleRequest, keep_ratio: bool) -> P.BatchReply: ...


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


# ---------------------------------------------------------------------------
# buffer -> learner: mixed batches
# ---------------------------------------------------------------------------


class BatchStream:
    """Mixed batches from the buffer service.

    Iterating yields a `BatchReply` with status `ok`, or None when the buffer had
    nothing to give this time (warming up, rate-limited, unreachable; the stream
    has already waited as long as the buffer asked), so the caller can keep its
    own schedule. It ends when the stop flag is set.

    Every reply's `meta` describes the buffer (`last_meta`). The buffer's count of
    received transitions never goes back unless it restarted from an older
    checkpoint: the stream counts such restarts and the transitions they lost.
    """

    def __init__(self, stop: StopFlag | None = None) -> None:
        self._stop = stop or StopFlag()
        self.last_meta: dict = {}
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
        self.last_meta = reply.meta
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

    def __init__(self, replay: Replay, request: P.SampleRequest, stop: StopFlag | None = None) -> None:
        super().__init__(stop)
        self._replay = replay
        self._request = request

    def get(self) -> P.BatchReply | None:
        return self._account(self._replay.sample(self._request, keep_ratio=True))

    def due(self) -> Iterator[P.BatchReply]:
        """Every batch the buffer can serve now."""
        while (batch := self.get()) is not None:
            yield batch


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


class Presence:
    """The components of one role alive now, from their liveliness tokens `<key>/<id>` (joins and leaves are logged)."""

    def __init__(self, session: zenoh.Session, key_expr: str, role: str, leave_note: str = "",
                 stop: StopFlag | None = None) -> None:
        self._alive: set[str] = set()
        self._lock = threading.Lock()
        self._role = role
        self._leave_note = leave_note  # set: a leave is a WARNING that says what it means
        self._stop = stop  # once set, leaves are the run ending: no warning
        self._one = "*" not in key_expr  # one component's token, not a role's: its name is the role's
        session.liveliness().declare_subscriber(key_expr, self._on, history=True)

    @classmethod
    def actors(cls, session: zenoh.Session, keys: P.Keys) -> "Presence":
        return cls(session, keys.alive_actors, "actor")

    @classmethod
    def learners(cls, session: zenoh.Session, keys: P.Keys) -> "Presence":
        """The learners sampling now, by incarnation (`ZenohBatchStream` declares the token)."""
        return cls(session, keys.alive_learners, "learner")

    @classmethod
    def buffer(cls, session: zenoh.Session, keys: P.Keys, stop: StopFlag) -> "Presence":
        """Whether this component reaches the buffer service (an actor's view: a lost link shows here first)."""
        return cls(session, keys.alive("buffer"), "buffer service",
                   leave_note="a lost link or a stopped buffer; the actor holds its next episode until it is back",
                   stop=stop)

    def _on(self, sample: zenoh.Sample) -> None:
        who = str(sample.key_expr).rsplit("/", 1)[-1]
        joined = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if joined:
                self._alive.add(who)
            else:
                self._alive.discard(who)
        name = self._role if self._one else f"{self._role} {who}"
        if not joined and self._leave_note and not (self._stop and self._stop.is_set()):
            log.warning("%s left (%s)", name, self._leave_note)
        else:
            log.info("%s %s", name, "joined" if joined else "left")

    def __len__(self) -> int:
        with self._lock:
            return len(self._alive)

    def __contains__(self, ident: object) -> bool:
        with self._lock:
            return str(ident) in self._alive


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


class FanoutPacer:
    """Keeps the weights' fan-out (bytes x actors per second) within a budget.

    Each publication goes to every actor, so its cost is its size times the actors alive. After
    sending one, the next may go `actors x size / budget` seconds later; what the learner publishes
    before then waits, and a newer set replaces a waiting one (the actors keep only the newest anyway).
    A budget of 0 sends everything at once.
    """

    def __init__(self, budget_bytes_per_s: float, actors: Callable[[], int],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.budget = budget_bytes_per_s
        self._actors, self._clock = actors, clock
        self._next_at = float("-inf")
        self.waiting: bytes | None = None
        self.held = 0  # publications that waited for the budget
        self.replaced = 0  # waiting publications a newer one replaced before they went out

    def offer(self, payload: bytes, final: bool = False) -> bytes | None:
        """The payload to send now, or None if it must wait (`due()` hands it over later)."""
        if final or self.budget <= 0 or self._clock() >= self._next_at:
            self.waiting = None
            return self._sent(payload)
        self.held += 1
        self.replaced += self.waiting is not None
        self.waiting = payload
        return None

    def due(self) -> bytes | None:
        """The waiting payload once the budget allows it."""
        if self.waiting is None or self._clock() < self._next_at:
            return None
        payload, self.waiting = self.waiting, None
        return self._sent(payload)

    def _sent(self, payload: bytes) -> bytes:
        if self.budget > 0:
            self._next_at = self._clock() + max(1, self._actors()) * len(payload) / self.budget
        return payload


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
