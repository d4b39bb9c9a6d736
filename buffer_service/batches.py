"""Mixed-batch composition: the SILCR sampling rule (paper eq. 3 and Algorithm 1).

SILCR: each batch is half D_O transitions with reward 0 and half D_E transitions
with reward 1 (`expert` first half rounded down, as the official 64 + 64).
SAC: the whole batch from D_O with the rewards the env gave (dense or episodic).
"""

from __future__ import annotations

import numpy as np

from common.protocol import Episode

from .expert_heap import ExpertHeap
from .online_fifo import OnlineFifo


def _gather(eps: list[Episode], ts: np.ndarray, out: dict[str, np.ndarray], rows: slice) -> None:
    obs, nxt, act = out["obs"][rows], out["next_obs"][rows], out["actions"][rows]
    rew, term, trunc, ver = out["rewards"][rows], out["terminated"][rows], out["truncated"][rows], out["policy_version"][rows]
    for i, (ep, t) in enumerate(zip(eps, ts)):
        obs[i] = ep.obs[t]
        nxt[i] = ep.obs[t + 1]
        act[i] = ep.actions[t]
        rew[i] = ep.rewards[t]
        last = t == ep.length - 1
        term[i] = last and ep.terminated
        # gymnasium may report both on the same step; termination wins (no bootstrap).
        trunc[i] = last and ep.truncated and not ep.terminated
        ver[i] = ep.policy_version


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
    n_expert = batch_size // 2 if heap is not None else 0
    n_online = batch_size - n_expert
    for b in range(batches):
        base = b * batch_size
        eps, ts = fifo.sample_locations(n_online, rng)
        _gather(eps, ts, out, slice(base, base + n_online))
        if n_expert:
            eps, ts = heap.sample_locations(n_expert, rng)  # type: ignore[union-attr]
            _gather(eps, ts, out, slice(base + n_online, base + batch_size))
        if constant_rewards:
            out["rewards"][base : base + n_online] = 0.0
            out["rewards"][base + n_online : base + batch_size] = 1.0
    return out
