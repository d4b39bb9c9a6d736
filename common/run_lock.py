"""One run directory, one run: an OS file lock held for the run's life.

Two `silcr train` with the same `--run` in the same directory used to both run: their
progress.csv rows interleaved and config.toml held whichever wrote last. The lock is
`fcntl.flock` on `<run dir>/.lock`, so the kernel releases it when the holder exits,
however it exits: a crashed launcher leaves no stale lock. A second launcher, or a
`--resume` of a live run, is refused before it writes anything.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path
from typing import Iterator

from silcr.common import run_layout


class RunInUse(RuntimeError):
    """The run directory is locked by a live process."""


def _try_lock(fd: int) -> bool:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as e:
        if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        raise


def _lock_or_refuse(fd: int, run_dir: Path) -> None:
    """Take the lock on `fd`, or raise `RunInUse` naming the process that holds it (the pid it wrote)."""
    if not _try_lock(fd):
        holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
        raise RunInUse(f"run directory {run_dir} is in use by a live run (process {holder}); wait for it to "
                       f"finish, stop it, or pick another --run")


def check_free(run_dir: Path) -> None:
    """Raise `RunInUse` if a live process holds `run_dir`'s lock. Writes nothing."""
    path = run_layout.lock(run_dir)
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        _lock_or_refuse(fd, run_dir)
    finally:
        os.close(fd)  # closing drops a lock taken by the probe


@contextlib.contextmanager
def hold(run_dir: Path) -> Iterator[None]:
    """Create `run_dir` and hold its lock while the block runs; `RunInUse` if another process holds it."""
    check_free(run_dir)  # before creating anything
    run_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(run_layout.lock(run_dir), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        _lock_or_refuse(fd, run_dir)  # another launcher may have taken it between the check and now
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)  # for the message a second launcher prints
        yield
    finally:
        os.close(fd)  # releases the lock
