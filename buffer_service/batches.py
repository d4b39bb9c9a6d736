"""Batch composition: the SILCR sampling rule (paper eq. 3 and Algorithm 1), labelled per algorithm.

Mixing algorithms (SILCR, SQIL): each batch is half D_O transitions and half D_E
transitions (`expert` half rounded down, as the official 64 + 64). The others (SAC,
GASIL): the whole batch from D_O. The labeller (`labels.py`) then writes the rewards.
GASIL's discriminator rows (`discriminator_rows`): D_E transitions and the newest D_O ones.
"""

from __future__ import annotations

import numpy as np

from silcr.common.protocol import Batch, BatchHeader, DiscriminatorRows

from .expert_heap import ExpertHeap
from .labels import Labeller
from .online_fifo import OnlineFifo


def compose_batches(fifo: OnlineFifo, heap: ExpertHeap | None, batches: int, batch_size: int, rng: np.random.Generator,
                    labeller: Labeller, obs_dim: int, act_dim: int,
                    action_dtype: type = np.float32) -> Batch[np.ndarray]:
    """`batches` consecutive batches of `batch_size` rows; with `heap`, half of each from it (see above).

    With `heap=None` every row comes from `fifo`.
    """
    n = batches * batch_size
    out = Batch.empty(n, obs_dim, act_dim, action_dtype)
    n_online = BatchHeader.online_rows_for(batch_size, heap is not None)
    copy_rewards = labeller.copies_env_rewards
    if n_online == batch_size:
        online, expert = fifo.gather(n, rng, out, slice(0, n), copy_rewards), None
    else:
        # One draw per table for all the batches: batch b's rows are [b * batch_size, ...),
        # online first. Per-call overhead, not row copies, dominates at batch 128.
        assert heap is not None
        position = np.arange(n).reshape(batches, batch_size)
        online = fifo.gather(batches * n_online, rng, out, position[:, :n_online].ravel(), copy_rewards)
        expert = heap.gather(batches * (batch_size - n_online), rng, out, position[:, n_online:].ravel(), copy_rewards)
    labeller.label(out.rewards.reshape(batches, batch_size), online, expert)
    return out


def discriminator_rows(fifo: OnlineFifo, heap: ExpertHeap, n: int, recent_window: int,
                       rng: np.random.Generator) -> DiscriminatorRows[np.ndarray]:
    """GASIL's discriminator data: `n` (s, a) pairs from D_E (label 1) and `n` from the newest
    `recent_window` transitions of D_O (label 0: what the current policy does)."""
    expert_obs, expert_actions = heap.gather_state_actions(n, rng)
    recent_obs, recent_actions = fifo.gather_recent(n, recent_window, rng)
    return DiscriminatorRows(expert_obs, expert_actions, recent_obs, recent_actions)
