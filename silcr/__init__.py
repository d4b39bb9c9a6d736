"""silcr: distributed Self-Imitation Learning with Constant Reward.

One installed name, `silcr`, holds the components (each a top-level folder of the
repository, mapped here by pyproject.toml):

    silcr.actor           roll out episodes, publish them
    silcr.buffer_service  D_O, D_E, the rate limiter, mixed batches, checkpoints
    silcr.learner         the SAC/SILCR update, weights, evaluation, checkpoints
    silcr.common          what every component shares: protocol, clients, options, envs, sessions
    silcr.deploy          launchers (`silcr train`, single-process mode, sweeps), monitor, router
    silcr.bench           the benchmark suite
    silcr.cli             the `silcr` command

Importing any part of silcr first runs this module, which sets the thread-pool
defaults below before numpy or torch is loaded.
"""

import os

__version__ = "0.3.0"

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

#: How many times an idle OpenMP thread of `silcr train --single-process` spins before it sleeps.
#: Alone on its cores, a learner's second thread that sleeps between kernels costs more than it
#: gives (a 256-256 update at 2 sleeping threads: 10.1 ms, at 1 thread: 4.8 ms), one that spins
#: this long stays awake through an update and sleeps between them (3.9 ms at 2 threads; 800-400:
#: 9.3 ms against 13.7 at 1 thread). Measured on the 2-core development machine, 2026-12-02.
ALONE_SPIN_COUNT = "20000"


def spin_openmp_threads_briefly() -> bool:
    """For a process that has its cores to itself (`silcr train --single-process`): idle OpenMP threads spin
    ALONE_SPIN_COUNT times before sleeping, instead of sleeping at once. True if set.

    Only before torch is imported (libgomp reads its settings once, when torch loads it), and only
    where the user set neither OMP_WAIT_POLICY nor GOMP_SPINCOUNT. A process started by another silcr
    process (a sweep's cells, which share the cores) inherits that one's PASSIVE as if the user had
    set it, and keeps it. The learner's thread probe still decides between 1 and all cores.
    """
    import sys

    if "torch" in sys.modules or ENV_BEFORE_DEFAULTS["OMP_WAIT_POLICY"] is not None or "GOMP_SPINCOUNT" in os.environ:
        return False
    os.environ.pop("OMP_WAIT_POLICY", None)  # libgomp's default policy, bounded by the spin count below
    os.environ["GOMP_SPINCOUNT"] = ALONE_SPIN_COUNT
    return True
