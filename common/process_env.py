"""The environment silcr's processes set for their thread pools, before numpy or torch is loaded.

`silcr/__init__.py` imports this first, so importing any part of silcr applies the defaults.
"""

import os
import sys

# silcr processes share their machine with each other (a learner beside its actors,
# several runs of a sweep), and thread pools that busy-wait collapse when another
# process holds a core they spin on. Measured on a 2-core machine with a second run
# going (docs/performance.md):
# * NumPy's OpenBLAS: an actor's forward pass for 4 envs took 20 ms instead of 0.1 ms,
#   so each process gets one BLAS thread (actors are single-threaded by design);
# * torch's OpenMP pool: an 800-400 SAC update on 2 threads ran at 1.4 updates/s
#   instead of 35, so idle OpenMP threads sleep instead of spinning.
# Both are defaults: a value already in the environment wins. Every silcr module is
# under this package, so library use (`import silcr.learner.sac`) gets them too,
# unless numpy or torch was imported before it.
THREAD_DEFAULTS = {"OPENBLAS_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
#: The environment as it was before these defaults (None: unset), for programs that must run with their own
#: (`silcr bench peer` runs Stable-Baselines3 as a user would).
ENV_BEFORE_DEFAULTS = {name: os.environ.get(name) for name in THREAD_DEFAULTS}
for _name, _value in THREAD_DEFAULTS.items():
    os.environ.setdefault(_name, _value)

#: `silcr train --single-process` has no silcr process beside it, so its idle OpenMP threads may spin briefly
#: before they sleep; sleeping at once makes every kernel of a 2-thread update wait for a wake-up. Measured on
#: 2 cores, Hopper-v5, in the loop (docs/performance.md): an 800-400 update took 15.6 ms at 2 sleeping threads,
#: 14.5 at 1 and 9.7 at 2 spinning 20,000 rounds (8.8 at libgomp's own default, which spins about 15 times
#: longer and, with a second such run on the cores, made each 11 times slower instead of 3.4; the learner
#: re-times its threads during the run and drops to one when another process takes a core: learner/threads.py).
SINGLE_PROCESS_SPIN = {"GOMP_SPINCOUNT": "20000"}


def spin_in_single_process() -> str:
    """Let OpenMP threads spin briefly (`SINGLE_PROCESS_SPIN`) in place of silcr's PASSIVE default; how they wait.

    Only before torch loads, and only where silcr set the policy: a user's OMP_WAIT_POLICY, or
    one inherited from a silcr parent such as a sweep's (its cells share the machine), wins,
    and so does a user's GOMP_SPINCOUNT.
    """
    if "torch" not in sys.modules and ENV_BEFORE_DEFAULTS["OMP_WAIT_POLICY"] is None:
        os.environ.pop("OMP_WAIT_POLICY", None)
        for name, value in SINGLE_PROCESS_SPIN.items():
            os.environ.setdefault(name, value)
    return openmp_wait()


def openmp_wait() -> str:
    """How this process's OpenMP threads wait when idle, from the environment libgomp read (for the run's log)."""
    if "GOMP_SPINCOUNT" in os.environ:
        return f"spin {os.environ['GOMP_SPINCOUNT']} rounds, then sleep"
    return {"PASSIVE": "sleep at once", "ACTIVE": "spin"}.get(os.environ.get("OMP_WAIT_POLICY", "").upper(),
                                                         "libgomp's default (spin a while, then sleep)")
