"""Environments: the episodic-reward wrapper and the env factory every component uses.

The paper's setting (§III-A): the environment gives 0 at every step and the
episode's summed reward at its last step. `EpisodicReward` turns any gymnasium
env into that; the episodic versions of the paper's five tasks are registered as
`silcr/<Task>-v5` (for example `gymnasium.make("silcr/Hopper-v5")`). The project's
own test task, `silcr/PointGoal-v0` (common/point_goal.py), pays only at the end anyway.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

PAPER_TASKS = ("Swimmer-v5", "Hopper-v5", "HalfCheetah-v5", "Walker2d-v5", "Humanoid-v5")
REWARD_MODES = ("episodic", "dense")
#: The registered episodic ids and the task each wraps: `silcr/Hopper-v5` is Hopper-v5 with the episodic reward.
EPISODIC_IDS = {f"silcr/{task}": task for task in PAPER_TASKS}


class EpisodicReward(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Return 0 at every step and the sum of the wrapped env's rewards at the episode's last step.

    The last step is the one where `terminated` or `truncated` is true, so this
    wrapper must sit outside gymnasium's `TimeLimit`. The dense reward of each step
    stays available as `info["dense_reward"]`.
    """

    def __init__(self, env: gym.Env) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)
        self._sum = 0.0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        self._sum = 0.0
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        r = float(reward)
        self._sum += r
        info = dict(info)
        info["dense_reward"] = r
        out: SupportsFloat = self._sum if (terminated or truncated) else 0.0
        return obs, out, terminated, truncated, info


_MUJOCO_WARNINGS_SEEN: set[str] = set()


def _route_mujoco_warnings() -> None:
    """MuJoCo's warnings to this process's log, once per message, instead of its default, which
    also writes MUJOCO_LOG.TXT into the working directory (HalfCheetah's XML warns of a
    deprecated attribute each time it loads, so every command that made it left that file
    behind). A handler the caller installed stays."""
    try:
        import mujoco
    except ImportError:
        return
    if mujoco.get_mju_user_warning() is not None:
        return

    def warn(message: str) -> None:
        if message not in _MUJOCO_WARNINGS_SEEN:
            _MUJOCO_WARNINGS_SEEN.add(message)
            logging.getLogger("mujoco").warning("%s", message)

    mujoco.set_mju_user_warning(warn)


def make_env(env_id: str, reward: str = "dense", **kwargs: Any) -> gym.Env:
    """Make `env_id` with dense or episodic reward; raise ValueError with a clear message on a bad id."""
    _route_mujoco_warnings()
    if reward not in REWARD_MODES:
        raise ValueError(f"reward must be one of {REWARD_MODES}, got {reward!r}")
    if env_id in EPISODIC_IDS:
        # The wrapper is applied below from `reward`, never twice: `silcr/<Task>` with reward
        # "dense" is the plain task (evaluations score the dense return, which sums the same).
        env_id = EPISODIC_IDS[env_id]
    try:
        env = gym.make(env_id, **kwargs)
    except gym.error.Error as e:
        raise ValueError(f"unknown or unusable environment {env_id!r}: {e}") from None
    if not isinstance(env.action_space, gym.spaces.Box) or not isinstance(env.observation_space, gym.spaces.Box):
        env.close()
        raise ValueError(f"environment {env_id!r} needs Box observation and action spaces (continuous control)")
    if len(env.observation_space.shape) != 1 or len(env.action_space.shape) != 1:
        env.close()
        raise ValueError(f"environment {env_id!r} needs flat (1-D) observations and actions")
    return EpisodicReward(env) if reward == "episodic" else env


@dataclass(frozen=True)
class EnvSpec:
    """What the buffer, learner and actors must agree on about the run's env."""

    env_id: str
    obs_dim: int
    act_dim: int
    action_low: np.ndarray
    action_high: np.ndarray
    max_episode_steps: int  # the time limit, or a generous bound (100,000) for an env without one
    time_limit: int | None = None

    @staticmethod
    def of(env_id: str) -> "EnvSpec":
        env = make_env(env_id)
        try:
            limit = env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else None
            return EnvSpec(
                env_id,
                int(env.observation_space.shape[0]),
                int(env.action_space.shape[0]),
                np.asarray(env.action_space.low, dtype=np.float32),
                np.asarray(env.action_space.high, dtype=np.float32),
                int(limit or 100_000),
                limit,
            )
        finally:
            env.close()

    def to_env_action(self, squashed: np.ndarray) -> np.ndarray:
        """Map the policy's [-1, 1] output to the env's bounds (the official code skips this)."""
        return self.action_low + (np.asarray(squashed) + 1.0) * 0.5 * (self.action_high - self.action_low)


POINT_GOAL_ID = "silcr/PointGoal-v0"


def _register_tasks() -> None:
    for task in PAPER_TASKS:
        eid = f"silcr/{task}"
        if eid not in gym.registry:
            gym.register(id=eid, entry_point=make_env, kwargs={"env_id": task, "reward": "episodic"})
    if POINT_GOAL_ID not in gym.registry:
        from silcr.common.point_goal import EPISODE_STEPS

        gym.register(id=POINT_GOAL_ID, entry_point="silcr.common.point_goal:PointGoalEnv", max_episode_steps=EPISODE_STEPS)


_register_tasks()
