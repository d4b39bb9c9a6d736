"""What every silcr component shares: the wire protocol, config, envs, Zenoh sessions, lifecycle."""

import os

# silcr processes share their machine with each other (a learner beside its actors,
# several runs of a sweep), and thread pools that busy-wait collapse when another
# process holds a core they spin on. Measured on a 2-core machine with a second run
# going (docs/performance.md):
# * NumPy's OpenBLAS: an actor's forward pass for 4 envs took 20 ms instead of 0.1 ms,
#   so each process gets one BLAS thread (actors are single-threaded by design);
# * torch's OpenMP pool: an 800-400 SAC update on 2 threads ran at 1.4 updates/s
#   instead of 35, so idle OpenMP threads sleep instead of spinning.
# Both are defaults: a value already in the environment wins. Every component package
# imports this module first, so library use (`import learner.sac`) gets them too, unless
# numpy or torch was imported before it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
