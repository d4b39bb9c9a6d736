"""The learner's CPU threads, chosen by timing the update itself, as FFTW plans and `cudnn.benchmark` do.

torch's default is one thread per core. At 256-256 on a 2-core laptop that is slower than
one thread: the threads sleep between the update's many small kernels, and waking them
costs more than the second core gives (measured: 17 s of system time in an 87 s run, and
62 s with one thread; issue 21). At 800-400 or with more cores the balance can tip the
other way. So the learner times a few updates of a throwaway copy of its networks at one
thread and at the cores it may use, alternating, and keeps the faster. `--torch-threads N`
skips this and uses N.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Callable

import torch

log = logging.getLogger("learner")


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask, which a container or `taskset` narrows)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def time_per_update(step: Callable[[], None], threads: int, updates: int) -> float:
    """Seconds per call of `step` at `threads` torch threads (after one call to warm up)."""
    torch.set_num_threads(threads)
    step()
    t0 = time.perf_counter()
    for _ in range(updates):
        step()
    return (time.perf_counter() - t0) / updates


Timer = Callable[[Callable[[], None], int, int], float]


def choose_threads(step: Callable[[], None], cores: int, updates: int = 10, rounds: int = 2,
                   timer: Timer | None = None) -> tuple[int, dict[int, float]]:
    """The faster of 1 thread and `cores` threads for `step` (one update), and the median time of each.

    The candidates alternate for `rounds` rounds, so a burst of load from elsewhere hits both.
    """
    timer = timer or time_per_update
    candidates = [1] if cores <= 1 else [1, cores]
    times: dict[int, list[float]] = {n: [] for n in candidates}
    for _ in range(rounds):
        for n in candidates:
            times[n].append(timer(step, n, updates))
    medians = {n: sorted(ts)[len(ts) // 2] for n, ts in times.items()}
    best = min(candidates, key=lambda n: medians[n])
    return best, medians
