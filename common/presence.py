"""Liveliness: which components of a role are alive now, from their Zenoh liveliness tokens (`role_session`
declares a component's own; `ZenohBatchStream` its learner's)."""

from __future__ import annotations

import logging
import threading

import zenoh

from silcr.common import protocol as P
from silcr.common.lifecycle import StopFlag

log = logging.getLogger("clients")


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
