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
    silcr.api             the Python API: `from silcr import SILCR` (SAC, SQIL, GASIL, IRCR), learn, save, load, predict

Importing any part of silcr first runs this module, which sets the thread-pool
defaults below before numpy or torch is loaded.
"""

# First, before anything imports numpy or torch: the thread-pool defaults (common/process_env.py).
from silcr.common.process_env import (ENV_BEFORE_DEFAULTS, SINGLE_PROCESS_SPIN, THREAD_DEFAULTS,  # noqa: F401, I001
                                      openmp_wait, spin_in_single_process)
from silcr.common.version import __version__  # noqa: F401

from typing import TYPE_CHECKING  # noqa: E402

if TYPE_CHECKING:  # what IDEs and type checkers see; at run time the API loads on first use (below)
    from silcr.api import GASIL, IRCR, SAC, SILCR, SQIL, Callback, Model  # noqa: F401

#: The Python API's names at the package root (tests/test_api.py keeps it equal to silcr.api.__all__).
API_NAMES = ("Model", "Callback", "SILCR", "SAC", "SQIL", "GASIL", "IRCR")
__all__ = [*API_NAMES, "__version__"]


def __getattr__(name: str):
    """`from silcr import SILCR` (and SAC, SQIL, GASIL, IRCR, Model, Callback): the Python API (silcr/api.py),
    imported on first use, so that the command line and the components do not load it."""
    if name in API_NAMES:
        import silcr.api

        return getattr(silcr.api, name)
    raise AttributeError(f"module 'silcr' has no attribute {name!r}")
