"""`silcr/PointGoal-v0`: a task where only the ranking of episodes can help.

A point in the square [-1, 1]^2 starts near the centre and moves by 0.1 * action
each step (actions in [-1, 1]^2). Every episode lasts exactly 50 steps (a time
limit; it never terminates), and the only reward comes at the last step: minus
the distance to a fixed goal at (0.7, 0.7). Observations: the position and the
fraction of the episode left.

Why it exists (docs/testing.md): on Hopper, Walker2d or Humanoid a longer episode
has more transitions, so SILCR's constant reward 1 on D_E acts as a survival bonus
whatever D_E holds. Here all episodes have the same length and surviving earns
nothing: D_E filled by recency instead of return gives no signal, and only the
ranking by return can lead the policy to the goal. It is also cheap (3-d
observations, no physics engine), so a test can learn it in a minute or two.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

GOAL = np.array([0.7, 0.7], np.float32)
STEP = 0.1
EPISODE_STEPS = 50


class PointGoalEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._pos = np.zeros(2, np.float32)
        self._t = 0

    def _obs(self) -> np.ndarray:
        return np.array([*self._pos, 1.0 - self._t / EPISODE_STEPS], np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._pos = self.np_random.uniform(-0.1, 0.1, 2).astype(np.float32)
        self._t = 0
        return self._obs(), {}

    def step(self, action):
        a = np.clip(np.asarray(action, np.float32), -1.0, 1.0)
        self._pos = np.clip(self._pos + STEP * a, -1.0, 1.0).astype(np.float32)
        self._t += 1
        distance = float(np.linalg.norm(self._pos - GOAL))
        reward = -distance if self._t >= EPISODE_STEPS else 0.0
        # The episode's end is the time limit (truncation), registered as max_episode_steps.
        return self._obs(), reward, False, False, {"distance": distance}


#: The discrete variant's moves: stay, right, left, up, down (each STEP long).
MOVES = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], np.float32)


class PointGoalDiscreteEnv(PointGoalEnv):
    """`silcr/PointGoalDiscrete-v0`: the same task with 5 discrete moves (stay, +x, -x, +y, -y).

    It is the discrete ranking test's task (tests/test_ranking.py): the goal is 14 moves
    away, a uniform random policy's 50 moves scatter it about 0.45 per axis, so D_E ranked
    by return holds the few episodes that wandered towards the goal, and D_E filled by
    recency holds whatever came last.
    """

    def __init__(self) -> None:
        super().__init__()
        self.action_space = gym.spaces.Discrete(len(MOVES))

    def step(self, action):
        return super().step(MOVES[int(action)])
