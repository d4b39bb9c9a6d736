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


def _gather(eps: list[Episode], ts: np.ndarray, out: dict[str, np.ndarray], rows: slice, rewards: bool) -> None:
    """Copy the sampled transitions into `out[...][rows]`.

    Only the array rows need a Python loop (each lives in its own episode's
    arrays); the per-episode scalars are gathered once per row with `fromiter`
    and the flags computed vectorised. Rewards are skipped when the caller
    overwrites them (constant rewards).
    """
    n = len(eps)
    obs, nxt, act, rew = out["obs"][rows], out["next_obs"][rows], out["actions"][rows], out["rewards"][rows]
    for i, (ep, t) in enumerate(zip(eps, ts)):
        o = ep.obs
        obs[i] = o[t]
        nxt[i] = o[t + 1]
        act[i] = ep.actions[t]
    if rewards:
        rew[:] = [ep.rewards[t] for ep, t in zip(eps, ts)]
    last = ts == np.fromiter((ep.length for ep in eps), np.int64, n) - 1
    terminated = np.fromiter((ep.terminated for ep in eps), bool, n)
    truncated = np.fromiter((ep.truncated for ep in eps), bool, n)
    out["terminated"][rows] = last & terminated
    # gymnasium may report both on the same step; termination wins (no bootstrap).
    out["truncated"][rows] = last & truncated & ~terminated
    out["policy_version"][rows] = np.fromiter((ep.policy_version for ep in eps), np.int64, n)


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
        _gather(eps, ts, out, slice(base, base + n_online), not constant_rewards)
        if n_expert:
            eps, ts = heap.sample_locations(n_expert, rng)  # type: ignore[union-attr]
            _gather(eps, ts, out, slice(base + n_online, base + batch_size), not constant_rewards)
        if constant_rewards:
            out["rewards"][base : base + n_online] = 0.0
            out["rewards"][base + n_online : base + batch_size] = 1.0
    return out
