"""Mixed-batch composition: the SILCR sampling rule (paper eq. 3 and Algorithm 1).

SILCR: each batch is half D_O transitions with reward 0 and half D_E transitions
with reward 1 (`expert` first half rounded down, as the official 64 + 64).
SAC and GASIL: the whole batch from D_O with the rewards the env gave (dense or episodic).
GASIL's discriminator rows (`discriminator_rows`): D_E transitions and the newest D_O ones.
"""

from __future__ import annotations

import numpy as np

from .expert_heap import ExpertHeap
from .online_fifo import OnlineFifo


def online_rows(batch_size: int, mixed: bool) -> int:
    """Rows of each batch drawn from D_O (the first ones); the rest, if `mixed`, come from D_E."""
    return batch_size - (batch_size // 2 if mixed else 0)


def compose_batches(
    fifo: OnlineFifo,
    heap: ExpertHeap | None,
    batches: int,
    batch_size: int,
    rng: np.random.Generator,
    constant_rewards: bool,
    obs_dim: int,
    act_dim: int,
) -> dict[str, np.ndarray]:
    """`batches` consecutive batches of `batch_size` rows; see the module docstring for the rule.

    With `heap=None` (plain SAC) every row comes from `fifo`.
    """
    n = batches * batch_size
    out = {
        "obs": np.empty((n, obs_dim), np.float32),
        "next_obs": np.empty((n, obs_dim), np.float32),
        "actions": np.empty((n, act_dim), np.float32),
        "rewards": np.empty(n, np.float32),
        "terminated": np.empty(n, np.uint8),
        "truncated": np.empty(n, np.uint8),
        "policy_version": np.empty(n, np.int64),
    }
    n_online = online_rows(batch_size, heap is not None)
    n_expert = batch_size - n_online
    if n_expert == 0:
        fifo.gather(n, rng, out, slice(0, n), not constant_rewards)
    else:
        # One draw per table for all the batches: batch b's rows are [b * batch_size, ...),
        # online first. Per-call overhead, not row copies, dominates at batch 128.
        position = np.arange(n).reshape(batches, batch_size)
        fifo.gather(batches * n_online, rng, out, position[:, :n_online].ravel(), not constant_rewards)
        assert heap is not None
        heap.gather(batches * n_expert, rng, out, position[:, n_online:].ravel(), not constant_rewards)
    if constant_rewards:
        rewards = out["rewards"].reshape(batches, batch_size)
        rewards[:, :n_online] = 0.0
        rewards[:, n_online:] = 1.0
    return out


def discriminator_rows(fifo: OnlineFifo, heap: ExpertHeap, n: int, recent_window: int,
                       rng: np.random.Generator) -> dict[str, np.ndarray]:
    """GASIL's discriminator data: `n` (s, a) pairs from D_E (label 1) and `n` from the newest
    `recent_window` transitions of D_O (label 0: what the current policy does)."""
    expert_obs, expert_actions = heap.index.gather_state_actions(heap.storage, n, rng)
    recent_obs, recent_actions = fifo.gather_recent(n, recent_window, rng)
    return {"disc_expert_obs": expert_obs, "disc_expert_actions": expert_actions,
            "disc_recent_obs": recent_obs, "disc_recent_actions": recent_actions}
