"""What one machine can hold: checked before a run starts, so that a bad option is one line, not a crash.

A buffer capacity or an actor count that the machine cannot hold used to fail late and
repeatedly: `online_capacity = 99999999999999999` raised `MemoryError` in the buffer five
times (once per restart) before the run exited 1, and `--actors 100000` started forking.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

#: `silcr train` starts one process per actor. Each holds a Zenoh session and its envs and
#: is 85-95 MB resident (the soak test; `silcr bench scale` at 800-400 networks: 92-95 MB);
#: 1,024 of them need about 100 GB and more processes than a default `ulimit -u` on many hosts. More envs per process
#: (`--envs-per-actor`) or actors started on other machines (`silcr actor`) scale further.
MAX_LOCAL_ACTORS = 1024
#: resident memory of one actor process, rounded up from the 95 MB `silcr bench scale` measured
ACTOR_RSS_BYTES = 100 * 2**20


def available_memory() -> int | None:
    """Bytes the kernel says can be allocated without swapping (MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB"


def release_free_memory() -> bool:
    """Hand the allocator's free pages back to the OS (glibc's `malloc_trim`); False where there is none.

    Zenoh reassembles a large message in memory it frees afterwards, but glibc keeps freed
    pages of its thread arenas for reuse: after three rejected 240 MB messages the buffer
    stayed 425 MB larger. Trimming after such a rejection gives them back.
    """
    global _libc
    if _libc is None:
        try:
            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _libc.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            _libc = False
    return bool(_libc) and bool(_libc.malloc_trim(0))


_libc: ctypes.CDLL | bool | None = None
