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
