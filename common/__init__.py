"""What every silcr component shares: the wire protocol, config, envs, Zenoh sessions, lifecycle."""

import os

# NumPy's OpenBLAS runs each matmul on one busy-waiting thread per core. An actor's
# forward pass (2-16 observations through 800-400 layers) then took 20 ms instead of
# 0.1 ms on a 2-core machine where other silcr processes hold the cores
# (docs/performance.md). Every silcr process shares its machine with others, so each
# gets one BLAS thread; the learner's torch has its own pool (--torch-threads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
