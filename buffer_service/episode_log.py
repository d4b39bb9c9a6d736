"""The buffer's episode log: every episode stored since the last checkpoint, on disk before it is acknowledged.

A buffer killed between two checkpoints used to lose what arrived since the older one, although
the actors had let it go. Now each stored episode's message is appended here (a length, a CRC-32,
the message as it came), and the actors' episodes are acknowledged only once the log has handed
them to the operating system: a SIGKILL or a crash of the process loses none of them (a power loss
can: the log is not fsynced per episode, which would cost a disk flush per episode). On a restart
the buffer restores its checkpoint and then replays the log's segments in order; the intake's
sequence numbers skip what the checkpoint already holds.

Segments: `<run dir>/checkpoints/episode-log/<n>.log`. Each checkpoint starts a new segment when it
is taken (`rotate`) and deletes the older ones once it is on disk (`checkpoint_written`), so the log
holds about one checkpoint interval of episodes. A write that fails (a full disk) stops the log;
acks wait until a checkpoint taken after the failure is on disk, which then stands for everything
before it (`confirms`).
"""

from __future__ import annotations

import logging
import struct
import threading
import zlib
from collections.abc import Iterator
from pathlib import Path

from silcr.common import protocol as P
from silcr.common.run_layout import buffer_checkpoint

log = logging.getLogger("buffer")

_RECORD = struct.Struct("<II")  # the message's length, its CRC-32
SUFFIX = ".log"


def log_dir(run_dir: Path) -> Path:
    return buffer_checkpoint(run_dir).parent / "episode-log"


def segments(folder: Path) -> list[Path]:
    """The log's segments, oldest first."""
    found = [p for p in folder.glob(f"*{SUFFIX}") if p.stem.isdigit()] if folder.is_dir() else []
    return sorted(found, key=lambda p: int(p.stem))


def read(folder: Path, limits: P.EpisodeLimits) -> Iterator[P.Episode]:
    """The episodes the log holds, oldest first. A record cut short or whose CRC does not match (the buffer
    was killed mid-write) ends its segment: it was never acknowledged. An invalid episode is skipped, logged."""
    for path in segments(folder):
        data = path.read_bytes()
        pos = 0
        while pos + _RECORD.size <= len(data):
            size, crc = _RECORD.unpack_from(data, pos)
            body = data[pos + _RECORD.size:pos + _RECORD.size + size]
            if len(body) < size or zlib.crc32(body) != crc:
                break
            pos += _RECORD.size + size
            try:
                yield P.Episode.decode(body, limits)
            except P.ProtocolError as e:
                log.warning("episode log %s: skipping an invalid record (%s): %s", path, e.reason, e)
        if pos < len(data):
            log.warning("episode log %s: the last %d bytes are an unfinished record (never acknowledged); ignored",
                        path, len(data) - pos)


class EpisodeLog:
    """The segment being appended to, and whether acks may confirm what it holds."""

    def __init__(self, folder: Path, replayed: int = 0) -> None:
        self.folder = folder
        self.replayed = replayed  # episodes an earlier buffer logged, stored again at this one's start
        existing = segments(folder)
        self.segment = int(existing[-1].stem) + 1 if existing else 0
        self.appended = self.bytes_written = self.failures = 0
        self.last_error = ""
        # False after a failed write: the segments no longer hold every stored episode, and nothing
        # more is appended until the next checkpoint is taken (`rotate`) ...
        self.intact = True
        # ... and then acks still wait until that checkpoint is on disk (set from its writer thread).
        self._healing_at: int | None = None
        self._lock = threading.Lock()
        self._file = None  # opened by the first append to a segment: a buffer that stores nothing writes nothing

    def _open(self) -> None:
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._file = open(self.folder / f"{self.segment}{SUFFIX}", "ab")
        except OSError as e:
            self._fail(e)

    def _fail(self, e: OSError) -> None:
        self.failures += 1
        self.last_error = str(e)
        if self.intact:
            log.error("the episode log could not be written (%s): acks wait for the next buffer checkpoint", e)
        self.intact = False
        self._close_file()

    def _close_file(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except OSError:
                pass  # what it held is counted as not written already, or was flushed
            self._file = None

    def append(self, payload: bytes) -> None:
        """Append one stored episode's message (buffered: `flush` hands it to the operating system)."""
        if not self.intact:
            return
        if self._file is None:
            self._open()
            if self._file is None:
                return
        try:
            self._file.write(_RECORD.pack(len(payload), zlib.crc32(payload)))
            self._file.write(payload)
            self.appended += 1
            self.bytes_written += _RECORD.size + len(payload)
        except OSError as e:
            self._fail(e)

    def flush(self) -> bool:
        """Hand what was appended to the operating system; whether acks may now confirm every stored episode."""
        if self._file is not None:
            try:
                self._file.flush()
            except OSError as e:
                self._fail(e)
        return self.confirms()

    def confirms(self) -> bool:
        return self.intact and self._healing_at is None

    def rotate(self) -> int:
        """A checkpoint is being taken of everything stored so far: start a new segment; return its number."""
        self.flush()
        self._close_file()
        self.segment += 1
        if not self.intact:
            self.intact = True  # a new chain starts from this checkpoint ...
            self._healing_at = self.segment  # ... which acks wait for
        return self.segment

    def checkpoint_written(self, segment: int) -> None:
        """The checkpoint taken when `segment` began is on disk: the older segments are no longer needed.
        Called from the checkpoint's writer thread."""
        with self._lock:
            for path in segments(self.folder):
                if int(path.stem) < segment:
                    path.unlink(missing_ok=True)
            if self._healing_at is not None and segment >= self._healing_at:
                self._healing_at = None

    def close(self, checkpointed: bool) -> None:
        """On the way out; with `checkpointed` (the final checkpoint holds everything), remove every segment."""
        self._close_file()
        if checkpointed:
            with self._lock:
                for path in segments(self.folder):
                    path.unlink(missing_ok=True)
                try:
                    self.folder.rmdir()  # a finished run's folder holds what it held before the log existed
                except OSError:
                    pass  # not there, or something else put there: left alone

    def stats(self) -> dict:
        return {"episode_log_replayed": self.replayed, "episode_log_appended": self.appended, "episode_log_bytes_written": self.bytes_written,
                "episode_log_failures": self.failures, "episode_log_segment": self.segment,
                "episode_log_confirms": self.confirms()}
