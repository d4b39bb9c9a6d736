from __future__ import annotations

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
