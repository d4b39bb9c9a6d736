"""Denormal floats flushed to zero while the learner's update runs on a CPU.

Adam keeps running averages of each gradient and of its square. A weight whose
gradient is zero for a while (a ReLU unit that went quiet, which is common in
SAC's networks) sees its averages decay by 0.9 and 0.999 per step until they
fall below float32's smallest normal number, 1.2e-38, and stay in the
denormal range for hundreds to thousands of steps. x86 CPUs compute on
denormals through a microcode assist, tens of times slower than on normal
numbers. Measured on this project's 2-core machine (docs/performance.md,
"Against Stable-Baselines3"), from a Hopper-v5 learner after 10,000 updates:
7% of the critics' Adam state and 17% of the actor's were denormal, and one
critic Adam step took 1.08 ms instead of 0.15 ms with them flushed: a fifth of
the whole update.

Flushing changes nothing an update can see: a denormal moment contributes
lr * m / (sqrt(v) + eps) < 1e-30 to a weight, far below the weight's last bit.

The CPU's mode (MXCSR's flush-to-zero and denormals-are-zero bits) belongs to
each thread. So the mode is set only around the update, not for the process:
in `silcr train --single-process` the same thread steps MuJoCo, whose physics
must not change with the learner's settings. torch's OpenMP worker threads do
not follow the thread that sets it: with 2 threads, a multiply of 2M denormals
inside `torch.set_flush_denormal(True)` left the worker's half, 1M of them,
unflushed. A 2-thread update at 800-400 then ran at 13.0 ms instead of 8.9 ms
once its networks had trained a little (a fresh network has no denormals, so
timing one hid it). So on entry and on exit the calling thread's floating-point
environment is copied to every thread of its OpenMP team: one `GOMP_parallel`
whose body is the C library's own `fesetenv` (no Python runs on the workers).
That costs about 70 us per copy with sleeping workers, and nothing at one thread.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import logging
import os
from collections.abc import Iterator

import torch

log = logging.getLogger("learner")

#: OpenMP runtimes that run a `GOMP_parallel` team on the threads torch's own parallel regions use.
OPENMP_RUNTIMES = ("libgomp", "libiomp5", "libomp")


class _TeamEnv:
    """Copies the calling thread's floating-point environment to its OpenMP team (see the module's docstring)."""

    def __init__(self, openmp: ctypes.CDLL, libm: ctypes.CDLL) -> None:
        self._parallel = openmp.GOMP_parallel
        self._parallel.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint]
        self._parallel.restype = None
        self._fegetenv = libm.fegetenv
        self._fesetenv = ctypes.cast(libm.fesetenv, ctypes.c_void_p)
        self._env = ctypes.create_string_buffer(256)  # fenv_t is 32 bytes on x86-64 glibc

    def spread(self) -> None:
        threads = torch.get_num_threads()
        if threads <= 1:
            return
        if self._fegetenv(self._env) != 0:
            raise OSError("fegetenv failed")
        # Every thread of the team, this one included, runs fesetenv(env) once.
        self._parallel(self._fesetenv, ctypes.addressof(self._env), threads, 0)


def _loaded_openmp() -> str | None:
    """The path of the OpenMP runtime loaded into this process (torch's), from /proc/self/maps (Linux)."""
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps if ".so" in line})
    except OSError:
        return None
    found = [p for p in paths if os.path.basename(p).startswith(OPENMP_RUNTIMES)]
    # torch's own copy first: a second runtime loaded by another library keeps a pool of its own
    return min(found, key=lambda p: not p.startswith(os.path.dirname(torch.__file__)), default=None)


@functools.cache
def team_env() -> _TeamEnv | None:
    """The copier for this process, or None (and one log line) where the OpenMP runtime cannot be reached."""
    path, libm_name = _loaded_openmp(), ctypes.util.find_library("m")
    try:
        if path is None or libm_name is None:
            raise OSError("no OpenMP runtime or C maths library found in this process")
        return _TeamEnv(ctypes.CDLL(path), ctypes.CDLL(libm_name))
    except (OSError, AttributeError) as e:
        log.info("denormals: only the updating thread flushes, not torch's other threads (%s)", e)
        return None


@contextlib.contextmanager
def flushed(device: torch.device, enabled: bool = True) -> Iterator[None]:
    """Run the block with denormals flushed to zero on this thread and its torch threads (CPU only; a no-op elsewhere or if not `enabled`).

    The previous mode cannot be read back through torch, so on exit it is set to
    off, the default; blocks of this kind are not nested.
    """
    if not enabled or device.type != "cpu" or not torch.set_flush_denormal(True):
        yield
        return
    team = team_env()
    try:
        if team is not None:
            team.spread()
        yield
    finally:
        torch.set_flush_denormal(False)
        if team is not None:
            team.spread()
