"""The learner's CPU threads, chosen by timing the update itself, as FFTW plans and `cudnn.benchmark` do.

torch's default is one thread per core. At 256-256 on a 2-core laptop that is slower than
one thread: the threads sleep between the update's many small kernels, and waking them
costs more than the second core gives (measured: 17 s of system time in an 87 s run, and
62 s with one thread; issue 21). At 800-400 or with more cores the balance can tip the
other way. So the learner times a few updates of a throwaway copy of its networks at one
thread and at the cores it may use, alternating, and keeps the faster; during the run it
times them again every minute on its own updates (`Retimer`), since another process that
takes a core turns the choice around. `--torch-threads N` skips both and uses N.
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


class Retimer:
    """Re-chooses the threads during the run, on the run's own updates, every `every_s` seconds.

    The choice at start holds only while the machine stays as it was. Another process that
    takes a core makes a multi-thread update wait for its other threads: measured on 2 cores,
    two `--single-process` runs side by side at 800-400 took 54 ms per update at 2 threads
    against 15 ms at 1 (docs/performance.md). So now and then the next `updates` updates run
    at each candidate count in turn (they are real updates, counted as usual), and the faster
    count is kept; a change is logged. It costs the slower count's extra time for `updates`
    updates a minute: about 0.1% when the choice is right (10 x 5 ms at 800-400 on 2 cores).
    """

    def __init__(self, candidates: list[int], current: int, every_s: float = 60.0, updates: int = 10,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.candidates, self.current = candidates, current
        self.every_s, self.updates, self.clock = every_s, updates, clock
        self._next_at = clock() + every_s
        self._queue: list[int] = []  # counts still to time in this re-check; the first is the one in use
        self._seen: dict[int, list[float]] = {}  # count -> [updates, seconds]

    def observe(self, updates: int, seconds: float) -> int:
        """Note `updates` updates that took `seconds` at the current count; the count for the next ones."""
        if self._queue:
            seen = self._seen.setdefault(self._queue[0], [0, 0.0])
            seen[0] += updates
            seen[1] += seconds
            if seen[0] >= self.updates:
                self._queue.pop(0)
                if not self._queue:
                    self._decide()
        elif len(self.candidates) > 1 and self.clock() >= self._next_at:
            # the current count last, so a switch back costs nothing when it stays
            self._queue = [n for n in self.candidates if n != self.current] + [self.current]
            self._seen = {}
        n = self._queue[0] if self._queue else self.current
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)
        return n

    def _decide(self) -> None:
        per_update = {n: s / u for n, (u, s) in self._seen.items()}
        best = min(per_update, key=per_update.get)
        if best != self.current:
            log.info("torch threads: %d, was %d (re-timed on the run's updates: %s)", best, self.current,
                     ", ".join(f"{k} thread{'s' if k > 1 else ''} {1000 * t:.2f} ms" for k, t in sorted(per_update.items())))
        self.current = best
        self._next_at = self.clock() + self.every_s
