"""MiniGrid tasks as silcr runs them: the agent's view as one flat vector, its actions as indices.

MiniGrid (Farama's `minigrid` package) gives a dict observation: `image`, the 7x7
cells in front of the agent, each as three integer codes (object kind, colour, state);
`direction`, where the agent faces (0-3); and `mission`, a sentence. silcr's networks
are MLPs over a flat float vector, so `make_minigrid` passes each observation through:

1. minigrid's own `OneHotPartialObsWrapper`: every code one-hot (11 object kinds, 6
   colours, 3 door states: 20 values per cell). The codes are categories: read as
   numbers, an MLP would see a key (5) as lying between a door (4) and a ball (6).
2. `FlatViewAndDirection`: that image flattened (7 x 7 x 20 = 980 values) followed by the
   direction one-hot (4 values): 984 values in {0, 1}. The view is egocentric, so it
   does not say which way the agent faces; on DoorKey-8x8 the goal is often out of view
   and the direction is what is left to orient by. The mission is dropped: on the tasks
   silcr runs (Empty, DoorKey, KeyCorridor) it is the same sentence in every episode.

The reward is MiniGrid's own, 1 - 0.9 * (steps / max_steps) on reaching the goal and 0
otherwise: already episodic, and higher for faster successes, which is the order a
top-M D_E needs. Episodes end on reaching the goal (`terminated`) or at the task's
`max_steps` (`truncated`, by MiniGrid itself, not by a gymnasium TimeLimit).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

#: env ids that `make_env` hands to `make_minigrid`
MINIGRID_PREFIXES = ("MiniGrid-", "BabyAI-")
DIRECTIONS = 4


def is_minigrid(env_id: str) -> bool:
    return env_id.startswith(MINIGRID_PREFIXES)


class FlatViewAndDirection(gym.ObservationWrapper):
    """A one-hot MiniGrid view, flattened, followed by the agent's direction one-hot (float32 in {0, 1})."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        image = env.observation_space["image"]
        self._size = int(np.prod(image.shape))
        self.observation_space = gym.spaces.Box(0.0, 1.0, (self._size + DIRECTIONS,), np.float32)

    def observation(self, obs: dict[str, Any]) -> np.ndarray:
        out = np.zeros(self._size + DIRECTIONS, np.float32)
        out[: self._size] = obs["image"].reshape(-1)
        out[self._size + int(obs["direction"])] = 1.0
        return out


def make_minigrid(env_id: str, **kwargs: Any) -> gym.Env:
    """`env_id` from MiniGrid with flat one-hot observations; ValueError if minigrid is missing or the id unknown."""
    try:
        import minigrid  # noqa: F401  (importing registers the MiniGrid-* and BabyAI-* ids)
        from minigrid.wrappers import OneHotPartialObsWrapper
    except ImportError:
        raise ValueError(f"{env_id!r} is a MiniGrid task and the minigrid package is not installed "
                         "(pip install minigrid)") from None
    try:
        env = gym.make(env_id, **kwargs)
    except gym.error.Error as e:
        raise ValueError(f"unknown or unusable environment {env_id!r}: {e}") from None
    return FlatViewAndDirection(OneHotPartialObsWrapper(env))
