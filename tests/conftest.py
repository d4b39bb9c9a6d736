from __future__ import annotations

import faulthandler
import signal

import numpy as np
import pytest

from silcr.common.protocol import Episode


def make_episode(length: int, ret: float = 0.0, obs_dim: int = 4, act_dim: int = 1, *, actor_id: int = 0,
                 seq: int = 0, terminated: bool = True, truncated: bool = False, version: int = 0,
                 start: float = 0.0) -> Episode:
    """An episode whose observation t is filled with `start + t`, so tests can tell rows apart."""
    obs = (start + np.arange(length + 1, dtype=np.float32))[:, None].repeat(obs_dim, 1)
    actions = np.full((length, act_dim), 0.5, np.float32)
    rewards = np.zeros(length, np.float32)
    rewards[-1] = ret
    return Episode(actor_id, seq, version, float(rewards.sum(dtype=np.float64)), terminated, truncated, obs, actions, rewards)


@pytest.fixture
def episode_factory():
    return make_episode


@pytest.fixture(autouse=True)
def signal_handlers_left_as_found():
    """Code a test runs in this process (a launcher through `main`, the Python API) must hand the
    SIGINT and SIGTERM handlers back as it found them: an ignored SIGINT left behind is inherited by
    every process a later test starts, and Ctrl-C then stops their children but not them."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    after = {s: signal.getsignal(s) for s in before}
    for signum, handler in after.items():
        signal.signal(signum, before[signum])  # the next test starts clean either way
    changed = {signal.Signals(s).name: (before[s], after[s]) for s in before if after[s] != before[s]}
    assert not changed, f"the test left signal handlers changed (before, after): {changed}"
    # nor a stack dump on SIGUSR1 (a component's, `StopFlag.install_signal_handlers`) in the caller's process
    assert not faulthandler.unregister(signal.SIGUSR1), "the test left SIGUSR1 dumping stacks (faulthandler)"
