"""Buffer checkpoints: the file format, and the thread that writes them.

What goes in is not decided here: the state checkpointed (`Checkpointed`, the buffer's
`ReplayState`) gathers it, each of its parts (the tables, the intake, the sampler, the
rate limiter) providing its own, and puts it back. Other parts of the service (the inbox's
and the writer's counters) ride along by name. This module only stores that structure,
and keeps the schedule both launchers share (`PeriodicCheckpoints`).

Layout: a msgpack stream, written atomically (temporary file, fsync, rename), so
a crash while checkpointing leaves the previous checkpoint usable:

1. a header map: `v`, `kind` ("silcr-buffer"), `env`, `algo`, `written_at`,
   `transitions` (received when it was taken), `state` (by part) and `parts`, where every
   episode is replaced by `{"episode": i}`, an index into the list that follows;
2. the episodes, each once as an `EpisodeCodec` message, even when D_O and D_E
   both hold it (in memory each table has its own copy, for vectorised sampling).

Loading re-validates every episode against the run's env with the same codec
that guards the network, so a corrupt or foreign file is refused with one line.
Files of version 1 (silcr 0.1, which wrote the tables' fields one by one) and version 2
(silcr 0.5, whose `state` held the counters of the intake and the sampler in one map) are read too.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Protocol

import msgpack

from silcr.common import protocol as P
from silcr.common.algorithms import algorithm
from silcr.common.atomic_file import write_atomic
from silcr.common.schedule import Every

from .episode_log import EpisodeLog
from .expert_heap import AdmissionMismatch

log = logging.getLogger("buffer")

SNAPSHOT_KIND = "silcr-buffer"
SNAPSHOT_VERSION = 3
_EPISODE = "episode"  # the marker key standing for an episode in the header


class SnapshotError(RuntimeError):
    pass


class Part(Protocol):
    def state(self) -> dict: ...

    def restore(self, state: dict) -> None: ...


class Checkpointed(Part, Protocol):
    """What a buffer checkpoint is taken of (`ReplayState`)."""

    limits: P.EpisodeLimits  # what a stored episode must satisfy, checked again on loading

    @property
    def transitions_received(self) -> int: ...

    def identity(self) -> dict[str, str]:
        """What a checkpoint must match to be restored (env, algo)."""

    def activity(self) -> tuple[int, ...]:
        """Changes whenever the state does."""

    def locks(self) -> tuple[threading.Lock, ...]:
        """The row storages' locks, held while an episode they hold is encoded."""


@dataclass
class Snapshot:
    """What one checkpoint holds, taken in the service thread (cheap: references, not copies).

    The episodes view rows that the service keeps rewriting; `locks` are the row
    storages' locks, held while each episode is encoded (see `storage.RowStorage`).
    """

    header: dict[str, Any]
    episodes: list[P.Episode]
    locks: tuple[threading.Lock, ...] = ()
    parts: dict[str, dict] = field(default_factory=dict)

    @property
    def transitions(self) -> int:
        return int(self.header["transitions"])


def _identity(ep: P.Episode) -> tuple:
    # D_O and D_E keep separate copies of an episode in both; these fields name it
    # (the service never stores two episodes with the same sender and seq).
    return ep.actor_id, ep.incarnation, ep.seq, ep.length, ep.episode_return


def _replace_episodes(obj: Any, ref) -> Any:
    if isinstance(obj, P.Episode):
        return {_EPISODE: ref(obj)}
    if isinstance(obj, dict):
        return {k: _replace_episodes(v, ref) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_replace_episodes(v, ref) for v in obj]
    return obj


def _put_episodes_back(obj: Any, episodes: list[P.Episode]) -> Any:
    if isinstance(obj, dict):
        if obj.keys() == {_EPISODE}:
            return episodes[obj[_EPISODE]]
        return {k: _put_episodes_back(v, episodes) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_put_episodes_back(v, episodes) for v in obj]
    return obj


def take(state: Checkpointed, **parts: Part) -> Snapshot:
    """A snapshot of `state` and of the named `parts` (anything with `state()`), in the service thread."""
    episodes: list[P.Episode] = []
    index: dict[tuple, int] = {}

    def ref(ep: P.Episode) -> int:
        key = _identity(ep)
        if key not in index:
            index[key] = len(episodes)
            episodes.append(ep)
        return index[key]

    header = {
        "v": SNAPSHOT_VERSION,
        "kind": SNAPSHOT_KIND,
        **state.identity(),
        "written_at": time.time(),
        "transitions": state.transitions_received,
        "state": _replace_episodes(state.state(), ref),
        "parts": {name: part.state() for name, part in parts.items()},
    }
    header["n_episodes"] = len(episodes)
    return Snapshot(header, episodes, state.locks())


def write(path: Path, snap: Snapshot) -> None:
    def body(f: BinaryIO) -> None:
        packer = msgpack.Packer(use_bin_type=True)
        f.write(packer.pack(snap.header))
        for ep in snap.episodes:
            for lock in snap.locks:  # always in this order; the service holds at most one
                lock.acquire()
            try:
                payload = ep.encode()
            finally:
                for lock in snap.locks:
                    lock.release()
            f.write(packer.pack(payload))

    write_atomic(path, body)


def _state_from_v1(header: dict[str, Any]) -> dict[str, Any]:
    """A version-1 header (silcr 0.1) as version 2's `state` layout."""
    c = header["counters"]
    return {
        "counters": {"episodes_received": c["episodes_received"], "transitions_received": c["transitions_received"],
                     "batches_served": c["batches_served"], "sample_requests": c["sample_requests"],
                     "sample_requests_rejected": 0, "not_ready_replies": 0,
                     "last_episode_version": c["last_episode_version"], "rejections": c["rejections"]},
        "last_seq": header["last_seq"],
        "fifo": {"episodes": [{_EPISODE: i} for i in header["fifo"]], "evicted_episodes": c["fifo_evicted"],
                 "evicted_for_rows": 0},
        "heap": {"admission": "return", "entries": [[{_EPISODE: i}, ret, order] for i, ret, order in header["heap"]],
                 "admitted": c["heap"][0], "rejected": c["heap"][1], "evicted": c["heap"][2]}
        if algorithm(header["algo"]).ranks_own_episodes else None,
        "limiter": {"inserts": header["limiter"]["inserts"], "samples": header["limiter"]["samples"], "paused": False},
    }


def _state_from_v2(saved: dict[str, Any]) -> dict[str, Any]:
    """Version 2's `state` (the counters of intake and sampler in one map) by part, as today's."""
    c = saved["counters"]
    return {
        "tables": {"fifo": saved["fifo"], "heap": saved["heap"]},
        "intake": {"episodes_received": c["episodes_received"], "transitions_received": c["transitions_received"],
                   "last_episode_version": c["last_episode_version"], "rejections": c["rejections"],
                   "episodes_missing": c.get("episodes_missing", 0),  # absent from checkpoints before 0.4
                   "last_seq": saved["last_seq"]},
        "sampler": {"batches_served": c["batches_served"], "sample_requests": c["sample_requests"],
                    "sample_requests_rejected": c["sample_requests_rejected"], "not_ready_replies": c["not_ready_replies"],
                    "request_rejections": c.get("request_rejections", {})},  # the same
        "limiter": saved["limiter"],
    }


def restore(path: Path, state: Checkpointed) -> Snapshot:
    """Load `path` into a fresh `state`; raise `SnapshotError` naming the problem.

    The returned snapshot's `parts` hold the named parts' states, for the caller to restore.
    """
    try:
        with open(path, "rb") as f:
            unpacker = msgpack.Unpacker(f, raw=False, max_buffer_size=2 * state.limits.max_bytes)
            header = next(unpacker)
            if not isinstance(header, dict) or header.get("kind") != SNAPSHOT_KIND:
                raise SnapshotError(f"{path} is not a silcr buffer checkpoint")
            if header.get("v") not in (1, 2, SNAPSHOT_VERSION):
                raise SnapshotError(f"{path}: checkpoint version {header.get('v')} is not supported")
            here = state.identity()
            if header["env"] != here["env"] or header["algo"] != here["algo"]:
                raise SnapshotError(f"{path} is for {header['algo']} on {header['env']}, this run is "
                                    f"{here['algo']} on {here['env']}")
            episodes = []
            for _ in range(int(header["n_episodes"])):
                payload = next(unpacker)
                if not isinstance(payload, bytes):
                    raise SnapshotError(f"{path}: episode record is not bytes")
                episodes.append(P.Episode.decode(payload, state.limits))
    except StopIteration:
        raise SnapshotError(f"{path} is truncated") from None
    except P.ProtocolError as e:
        raise SnapshotError(f"{path} holds an invalid episode ({e.reason}: {e})") from None
    except (OSError, ValueError, KeyError, TypeError, msgpack.exceptions.ExtraData, msgpack.exceptions.UnpackException) as e:
        raise SnapshotError(f"{path} is unreadable or corrupt ({type(e).__name__}: {e})") from None

    try:
        if header["v"] == 1:
            saved, parts = _state_from_v2(_state_from_v1(header)), {}
            header["transitions"] = header["counters"]["transitions_received"]
        elif header["v"] == 2:
            saved, parts = _state_from_v2(header["state"]), header["parts"]
        else:
            saved, parts = header["state"], header["parts"]
        state.restore(_put_episodes_back(saved, episodes))
    except AdmissionMismatch as e:
        raise SnapshotError(f"{path}: {e}") from None
    except (IndexError, KeyError, TypeError, ValueError) as e:
        raise SnapshotError(f"{path} has an inconsistent index ({type(e).__name__}: {e})") from None
    return Snapshot(header, episodes, parts=parts)


class BackgroundWriter:
    """Writes snapshots in a thread so the service keeps answering the learner meanwhile.

    At most one write runs at a time; a checkpoint due while one is still being
    written is skipped (and counted), never queued.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._thread: threading.Thread | None = None
        self.written = 0
        self.skipped = 0
        self.failed = 0
        self.last_transitions = 0
        self.last_written_at: float | None = None
        self.last_error = ""

    def state(self) -> dict[str, int]:
        return {"written": self.written, "skipped": self.skipped, "failed": self.failed}

    def restore(self, state: dict[str, int]) -> None:
        self.written, self.skipped, self.failed = int(state["written"]), int(state["skipped"]), int(state["failed"])

    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, snap: Snapshot, on_written: Callable[[], None] | None = None) -> bool:
        """Write `snap` in the background, then call `on_written` (in the writer's thread) if it is on disk."""
        if self.busy():
            self.skipped += 1
            return False
        self._thread = threading.Thread(target=self._write, args=(snap, on_written), name="buffer-checkpoint",
                                        daemon=True)
        self._thread.start()
        return True

    def _write(self, snap: Snapshot, on_written: Callable[[], None] | None = None) -> None:
        try:
            write(self.path, snap)
        except OSError as e:
            self.failed += 1
            self.last_error = str(e)
            return
        self.written += 1
        self.last_transitions = snap.transitions
        self.last_written_at = time.time()
        if on_written is not None:
            on_written()

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()


class PeriodicCheckpoints:
    """The buffer's checkpoint schedule, the same for both launchers: a snapshot every `interval`
    seconds written in the background (none if `interval` is 0), and a last one on the way out,
    so that a clean stop (Ctrl-C, the end of the run) loses nothing. The named `parts` (the
    inbox's counters, say) ride along; the writer's own counters always do. With an `episode_log`,
    each checkpoint starts a new segment of it when taken and drops the older ones once written."""

    def __init__(self, path: Path, interval: float, episode_log: EpisodeLog | None = None, **parts: Part) -> None:
        self.writer = BackgroundWriter(path)
        self.episode_log = episode_log
        self.parts: dict[str, Part] = {**parts, "writer": self.writer}
        self._every = Every(interval, first_now=False, never_if_zero=True)
        self._restored: tuple[int, ...] | None = None

    def restore_parts(self, snap: Snapshot | None, replay: Checkpointed) -> None:
        """Put back the parts' counters a restored snapshot holds; remember what it held."""
        if snap is not None:
            for name, part in self.parts.items():
                if name in snap.parts:
                    part.restore(snap.parts[name])
            self._restored = replay.activity()

    def maybe(self, replay: Checkpointed, now: float | None = None) -> None:
        if not self._every.due(now):
            return
        if self.writer.busy():
            self.writer.skipped += 1
            return
        on_written = None
        if self.episode_log is not None:
            segment = self.episode_log.rotate()
            on_written = functools.partial(self.episode_log.checkpoint_written, segment)
        self.writer.submit(take(replay, **self.parts), on_written)

    def final(self, replay: Checkpointed) -> bool:
        """The last checkpoint, on the way out; whether the file on disk now holds this state."""
        self.writer.join()
        if self._restored == replay.activity() and self.writer.written == 0:
            # Nothing came in since the checkpoint it restored (another component could not start,
            # say): leave that file as it is rather than rewrite it.
            log.info("nothing changed since the checkpoint it resumed from; %s left as it is", self.writer.path)
            if self.episode_log is not None:
                self.episode_log.close(checkpointed=False)  # what it replayed is still only in its segments
            return True
        t0 = time.monotonic()
        written = True
        try:
            write(self.writer.path, take(replay, **self.parts))
            log.info("checkpoint of %d transitions written to %s in %.1fs", replay.transitions_received,
                     self.writer.path, time.monotonic() - t0)
        except OSError as e:
            log.error("the final checkpoint could not be written (%s): %s is stale; --resume would continue from it%s",
                      e, self.writer.path, " and the episode log" if self.episode_log is not None else "")
            written = False
        if self.episode_log is not None:
            self.episode_log.close(checkpointed=written)
        if self.writer.failed:
            log.error("%d periodic checkpoints failed; last error: %s", self.writer.failed, self.writer.last_error)
        return written

    def stats(self) -> dict[str, Any]:
        w = self.writer
        return {"checkpoints_written": w.written, "checkpoints_skipped": w.skipped, "checkpoints_failed": w.failed,
                "checkpoint_transitions": w.last_transitions,
                "checkpoint_age_s": time.time() - w.last_written_at if w.last_written_at else None}
