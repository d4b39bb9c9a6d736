"""Every seed a run derives from `--seed`, in one place.

A run is reproducible from its base seed (`silcr train --single-process` to the last
digit), so each consumer of randomness gets its own stream, far enough from the others
that no two collide for any realistic actor count or run length:

    actor i                      base + i (its env j resets with that + 10,000 j)
    the buffer's sampling        base + STRIDE
    evaluation k                 base + 1,000,000 + 1,000 k (episode e adds e)
    an actor restarted           its seed + STRIDE (else it replays its predecessor's episodes)
    actors after a resume        base + STRIDE x transitions already collected
    the learner's torch seed     base
"""

from __future__ import annotations

#: A prime far from base + actor id for any realistic actor count.
STRIDE = 1_000_003
_ENV_STRIDE = 10_000
_EVAL_OFFSET = 1_000_000
_EVAL_STRIDE = 1_000


def actor(base: int, actor_id: int) -> int:
    return base + actor_id


def actor_env(actor_seed: int, env_index: int) -> int:
    """The first reset of an actor's `env_index`-th env (later resets continue its generator)."""
    return actor_seed + _ENV_STRIDE * env_index


def buffer_sampling(base: int) -> int:
    return base + STRIDE


def evaluation(base: int, evals_done: int) -> int:
    return base + _EVAL_OFFSET + _EVAL_STRIDE * evals_done


def restarted(seed: int) -> int:
    """A restarted component's seed: new episodes, not its predecessor's again."""
    return seed + STRIDE


def resumed(base: int, transitions: int) -> int:
    """The actors' base seed after a resume at `transitions` collected: the episodes of the first start are not replayed."""
    return base + STRIDE * transitions
