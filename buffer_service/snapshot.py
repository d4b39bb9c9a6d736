"""Buffer checkpoints: D_O, D_E, the rate limiter and the counters in one file.

Layout: a msgpack stream, written atomically (temporary file, fsync, rename), so
a crash while checkpointing leaves the previous checkpoint usable:

1. a header map: `v`, `kind` ("silcr-buffer"), `env`, `algo`, `written_at`, the
   counters, the limiter state, the duplicate-detection table, and the two tables
   as lists of episode indices (D_E entries also carry return and admission order);
2. the episodes, each once as an `EpisodeCodec` message, even when both D_O and
   D_E hold it (in memory each table has its own copy, for vectorised sampling;
   in the file it is stored once and referenced from both tables).

Loading re-validates every episode against the run's env with the same codec
that guards the network, so a corrupt or foreign file is refused with one line.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import msgpack

from silcr.common import protocol as P
from silcr.common.atomic_file import write_atomic

if TYPE_CHECKING:
    from .service import ReplayState

SNAPSHOT_KIND = "silcr-buffer"
SNAPSHOT_VERSION = 1


class SnapshotError(RuntimeError):
    pass


@dataclass
class Snapshot:
    """What one checkpoint holds, taken in the service thread (cheap: references, not copies).

    The episodes view rows that the service keeps rewriting; `locks` are the row
    storages' locks, held while each episode is encoded (see `storage.RowStorage`).
    """

    header: dict[str, Any]
    episodes: list[P.Episode]
    locks: tuple[threading.Lock, ...] = ()

    @property
    def transitions(self) -> int:
        return int(self.header["counters"]["transitions_received"])


def _identity(ep: P.Episode) -> tuple:
    # D_O and D_E keep separate copies of an episode in both; these fields name it
    # (the service never stores two episodes with the same sender and seq).
    return ep.actor_id, ep.incarnation, ep.seq, ep.length, ep.episode_return


def take(state: "ReplayState") -> Snapshot:
    episodes: list[P.Episode] = []
    index: dict[tuple, int] = {}

    def ref(ep: P.Episode) -> int:
        key = _identity(ep)
        if key not in index:
            index[key] = len(episodes)
            episodes.append(ep)
        return index[key]

    fifo_ids = [ref(ep) for ep in state.fifo.episodes()]
    heap = state.heap if state.cfg.algo == "silcr" else None  # SQIL's D_E is reloaded from --demos
    heap_entries = [[ref(ep), float(ret), int(order)] for ret, order, ep in heap.entries()] if heap else []
    lim = state.limiter
    header = {
        "v": SNAPSHOT_VERSION,
        "kind": SNAPSHOT_KIND,
        "env": state.spec.env_id,
        "algo": state.cfg.algo,
        "expert_admission": heap.admission if heap else None,
        "written_at": time.time(),
        "counters": {
            "episodes_received": state.episodes_received,
            "transitions_received": state.transitions_received,
            "batches_served": state.batches_served,
            "sample_requests": state.sample_requests,
            "last_episode_version": state.last_episode_version,
            "rejections": dict(state.rejections),
            "fifo_evicted": state.fifo.evicted_episodes,
            "heap": [heap.admitted, heap.rejected, heap.evicted] if heap else [0, 0, 0],
        },
        "limiter": {"inserts": lim.inserts, "samples": lim.samples},
        "last_seq": [[a, inc, seq] for (a, inc), seq in state.last_seq.items()],
        "fifo": fifo_ids,
        "heap": heap_entries,
        "n_episodes": len(episodes),
    }
    locks = (state.fifo.storage.lock,) + ((heap.storage.lock,) if heap else ())
    return Snapshot(header, episodes, locks)


def write(path: Path, snap: Snapshot) -> None:
    def body(f: BinaryIO) -> None:
        packer = msgpack.Packer(use_bin_type=True)
        f.write(packer.pack(snap.header))
        for ep in snap.episodes:
            for lock in snap.locks:  # always in this order; the service holds at most one
                lock.acquire()
            try:
                payload = P.EpisodeCodec.encode(ep)
            finally:
                for lock in snap.locks:
                    lock.release()
            f.write(packer.pack(payload))

    write_atomic(path, body)


def restore(path: Path, state: "ReplayState") -> Snapshot:
    """Load `path` into a fresh `state`; raise `SnapshotError` naming the problem."""
    try:
        with open(path, "rb") as f:
            unpacker = msgpack.Unpacker(f, raw=False, max_buffer_size=2 * state.codec.max_bytes)
            header = next(unpacker)
            if not isinstance(header, dict) or header.get("kind") != SNAPSHOT_KIND:
                raise SnapshotError(f"{path} is not a silcr buffer checkpoint")
            if header.get("v") != SNAPSHOT_VERSION:
                raise SnapshotError(f"{path}: checkpoint version {header.get('v')} is not supported")
            if header["env"] != state.spec.env_id or header["algo"] != state.cfg.algo:
                raise SnapshotError(f"{path} is for {header['algo']} on {header['env']}, this run is "
                                    f"{state.cfg.algo} on {state.spec.env_id}")
            admission = state.heap.admission if state.cfg.algo == "silcr" and state.heap is not None else None
            if state.cfg.algo == "silcr" and header.get("expert_admission", "return") != admission:
                raise SnapshotError(f"{path} ranks D_E by {header.get('expert_admission', 'return')}, this run by "
                                    f"{admission} (--expert-admission)")
            episodes = []
            for _ in range(int(header["n_episodes"])):
                payload = next(unpacker)
                if not isinstance(payload, bytes):
                    raise SnapshotError(f"{path}: episode record is not bytes")
                episodes.append(state.codec.decode(payload))
    except StopIteration:
        raise SnapshotError(f"{path} is truncated") from None
    except P.ProtocolError as e:
        raise SnapshotError(f"{path} holds an invalid episode ({e.reason}: {e})") from None
    except (OSError, ValueError, KeyError, TypeError, msgpack.exceptions.ExtraData, msgpack.exceptions.UnpackException) as e:
        raise SnapshotError(f"{path} is unreadable or corrupt ({type(e).__name__}: {e})") from None

    try:
        for i in header["fifo"]:
            state.fifo.add(episodes[i])
        c = header["counters"]
        if state.cfg.algo == "silcr" and state.heap is not None:
            state.heap.restore([(ret, order, episodes[i]) for i, ret, order in header["heap"]], *c["heap"])
        state.fifo.evicted_episodes = int(c["fifo_evicted"])
        state.episodes_received = int(c["episodes_received"])
        state.transitions_received = int(c["transitions_received"])
        state.batches_served = int(c["batches_served"])
        state.sample_requests = int(c["sample_requests"])
        state.last_episode_version = int(c["last_episode_version"])
        state.rejections.update(c["rejections"])
        state.limiter.inserts = int(header["limiter"]["inserts"])
        state.limiter.samples = int(header["limiter"]["samples"])
        state.last_seq = {(int(a), int(inc)): int(seq) for a, inc, seq in header["last_seq"]}
    except (IndexError, KeyError, TypeError, ValueError) as e:
        raise SnapshotError(f"{path} has an inconsistent index ({type(e).__name__}: {e})") from None
    return Snapshot(header, episodes)


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
        self.last_seconds = 0.0
        self.last_error = ""

    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, snap: Snapshot) -> bool:
        if self.busy():
            self.skipped += 1
            return False
        self._thread = threading.Thread(target=self._write, args=(snap,), name="buffer-checkpoint", daemon=True)
        self._thread.start()
        return True

    def _write(self, snap: Snapshot) -> None:
        t0 = time.monotonic()
        try:
            write(self.path, snap)
        except OSError as e:
            self.failed += 1
            self.last_error = str(e)
            return
        self.written += 1
        self.last_transitions = snap.transitions
        self.last_written_at = time.time()
        self.last_seconds = time.monotonic() - t0

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()
