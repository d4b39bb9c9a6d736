"""Environments: the episodic-reward wrapper and the env factory every component uses.

The paper's setting (§III-A): the environment gives 0 at every step and the
episode's summed reward at its last step. `EpisodicReward` turns any gymnasium
env into that; the episodic versions of the paper's five tasks are registered as
`silcr/<Task>-v5` (for example `gymnasium.make("silcr/Hopper-v5")`). The project's
own test tasks, `silcr/PointGoal-v0` and its discrete twin `silcr/PointGoalDiscrete-v0`
(common/point_goal.py), pay only at the end anyway, as MiniGrid's tasks do
(`MiniGrid-*`, made through common/minigrid_obs.py).
"""

from __future__ import annotations

import importlib
import logging
import re
from dataclasses import dataclass
from typing import Any, Callable, SupportsFloat

import gymnasium as gym
import numpy as np

from silcr.common import protocol as P
from silcr.common.minigrid_obs import is_minigrid, make_minigrid

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


#: `package.module:factory`: a zero-argument callable (a function or an env class) that returns a
#: gymnasium.Env, named so that every process can import it (the Python API's `env=callable`).
_FACTORY_REF = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")


def is_factory_ref(env_id: str) -> bool:
    """`module:name` with `name` a Python name (gymnasium's `module:EnvId-v0` has a version and is not one)."""
    return bool(_FACTORY_REF.match(env_id))


def factory_of(env_id: str) -> Callable[[], gym.Env]:
    """The callable a `module:qualname` reference names; ValueError naming what is missing."""
    module_name, qualname = env_id.split(":", 1)
    try:
        obj: Any = importlib.import_module(module_name)
    except ImportError as e:
        raise ValueError(f"environment {env_id!r}: cannot import {module_name} ({e})") from None
    for part in qualname.split("."):
        obj = getattr(obj, part, None)
        if obj is None:
            raise ValueError(f"environment {env_id!r}: {module_name} has no {qualname}")
    if not callable(obj):
        raise ValueError(f"environment {env_id!r}: {qualname} is not callable")
    return obj


def make_env(env_id: str, reward: str = "dense", **kwargs: Any) -> gym.Env:
    """Make `env_id` with dense or episodic reward; raise ValueError with a clear message on a bad id.

    `env_id` is a gymnasium id (`Hopper-v5`, `module:EnvId-v0`) or `module:factory`, a
    callable that returns the env (`is_factory_ref`). Observations must be flat vectors;
    actions a flat Box (continuous) or a Discrete set (action indices). MiniGrid tasks get a
    flat one-hot view (`minigrid_obs`).
    """
    _route_mujoco_warnings()
    if reward not in REWARD_MODES:
        raise ValueError(f"reward must be one of {REWARD_MODES}, got {reward!r}")
    if env_id in EPISODIC_IDS:
        # The wrapper is applied below from `reward`, never twice: `silcr/<Task>` with reward
        # "dense" is the plain task (evaluations score the dense return, which sums the same).
        env_id = EPISODIC_IDS[env_id]
    if is_minigrid(env_id):
        env = make_minigrid(env_id, **kwargs)
    elif is_factory_ref(env_id):
        made = factory_of(env_id)(**kwargs)
        if not isinstance(made, gym.Env):
            raise ValueError(f"environment {env_id!r}: the callable returned {type(made).__name__}, not a gymnasium.Env")
        env = made
    else:
        try:
            env = gym.make(env_id, **kwargs)
        except gym.error.Error as e:
            raise ValueError(f"unknown or unusable environment {env_id!r}: {e}") from None
    problem = _unsupported_spaces(env)
    if problem:
        env.close()
        raise ValueError(f"environment {env_id!r} {problem}")
    return EpisodicReward(env) if reward == "episodic" else env


def _unsupported_spaces(env: gym.Env) -> str | None:
    obs, act = env.observation_space, env.action_space
    if not isinstance(obs, gym.spaces.Box) or len(obs.shape) != 1:
        return "needs flat (1-D) Box observations"
    if isinstance(act, gym.spaces.Discrete):
        if act.n < 2 or act.start != 0:
            return f"has Discrete({act.n}, start={act.start}) actions; silcr needs at least 2 actions numbered from 0"
        return None
    if not isinstance(act, gym.spaces.Box) or len(act.shape) != 1:
        return "needs flat (1-D) Box (continuous) or Discrete actions"
    return None


@dataclass(frozen=True)
class EnvSpec:
    """What the buffer, learner and actors must agree on about the run's env.

    Continuous actions are `act_dim` floats, the policy's outputs in [-1, 1]. Discrete
    actions are one index in [0, n_actions) each, stored as a column of one int64
    (`act_dim` is 1): the buffer, the wire and the learner carry them as integers.
    """

    env_id: str
    obs_dim: int
    act_dim: int  # the stored action's width: the Box's size, or 1 (an index) for discrete actions
    action_low: np.ndarray
    action_high: np.ndarray
    max_episode_steps: int  # the time limit, or a generous bound (100,000) for an env without one
    time_limit: int | None = None
    n_actions: int = 0  # discrete actions: how many; 0 for continuous ones
    #: the observations' bounds as the env declares them (None: unbounded, and specs saved before silcr 0.6)
    obs_low: np.ndarray | None = None
    obs_high: np.ndarray | None = None

    @property
    def discrete(self) -> bool:
        return self.n_actions > 0

    @property
    def action_kind(self) -> str:
        return "discrete" if self.discrete else "continuous"

    @property
    def action_dtype(self) -> type:
        """How actions are stored and sent: action indices as int64, continuous actions as float32."""
        return np.int64 if self.discrete else np.float32

    @property
    def action_bytes(self) -> int:
        """Bytes of one stored action."""
        return self.act_dim * np.dtype(self.action_dtype).itemsize

    @property
    def has_goal(self) -> bool:
        """MiniGrid's tasks end at their goal and pay only there (lava ends an episode too, but pays 0)."""
        return is_minigrid(self.env_id)

    def reached_goal(self, episode: P.Episode) -> bool | None:
        """Whether a finished episode reached the task's goal; `None` for tasks without one (MuJoCo's)."""
        if not self.has_goal:
            return None
        return bool(episode.terminated and episode.rewards[-1] > 0)

    def episode_limits(self, max_bytes: int = P.DEFAULT_MAX_EPISODE_BYTES) -> P.EpisodeLimits:
        """What an episode of this env may be (`protocol.validate_episode`)."""
        return P.EpisodeLimits(self.obs_dim, self.act_dim, self.max_episode_steps, max_bytes, self.n_actions)

    @staticmethod
    def of(env_id: str) -> "EnvSpec":
        env = make_env(env_id)
        try:
            # MiniGrid ends its own episodes at `max_steps` instead of through a gymnasium TimeLimit.
            limit = (env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps
                     else getattr(env.unwrapped, "max_steps", None))
            space = env.action_space
            if isinstance(space, gym.spaces.Discrete):
                n = int(space.n)
                low, high, act_dim = np.zeros(1, np.float32), np.full(1, n - 1, np.float32), 1
            else:
                n, act_dim = 0, int(space.shape[0])
                low, high = np.asarray(space.low, dtype=np.float32), np.asarray(space.high, dtype=np.float32)
            obs = env.observation_space
            return EnvSpec(env_id, int(obs.shape[0]), act_dim, low, high, int(limit or 100_000), limit, n,
                           np.asarray(obs.low, np.float32), np.asarray(obs.high, np.float32))
        finally:
            env.close()

    @property
    def observation_space(self) -> gym.spaces.Box:
        """The env's observations as it declares them (a flat Box; unbounded where the spec does not say)."""
        if self.obs_low is None or self.obs_high is None:
            return gym.spaces.Box(-np.inf, np.inf, (self.obs_dim,), np.float32)
        return gym.spaces.Box(self.obs_low, self.obs_high, dtype=np.float32)

    @property
    def action_space(self) -> gym.spaces.Space:
        """The env's actions as it takes them: Discrete(n), or a Box with the env's bounds."""
        if self.discrete:
            return gym.spaces.Discrete(self.n_actions)
        return gym.spaces.Box(self.action_low, self.action_high, dtype=np.float32)

    def to_env_action(self, action: np.ndarray) -> np.ndarray:
        """The policy's action as the env takes it: an index as is; a continuous one mapped from [-1, 1]
        to the env's bounds (the official code skips this). Rows of actions give rows of env actions."""
        if self.discrete:
            return np.asarray(action)[..., 0]
        return self.action_low + (np.asarray(action) + 1.0) * 0.5 * (self.action_high - self.action_low)


POINT_GOAL_ID = "silcr/PointGoal-v0"
POINT_GOAL_DISCRETE_ID = "silcr/PointGoalDiscrete-v0"


def _register_tasks() -> None:
    for task in PAPER_TASKS:
        eid = f"silcr/{task}"
        if eid not in gym.registry:
            gym.register(id=eid, entry_point=make_env, kwargs={"env_id": task, "reward": "episodic"})
    from silcr.common.point_goal import EPISODE_STEPS

    for eid, entry in ((POINT_GOAL_ID, "PointGoalEnv"), (POINT_GOAL_DISCRETE_ID, "PointGoalDiscreteEnv")):
        if eid not in gym.registry:
            gym.register(id=eid, entry_point=f"silcr.common.point_goal:{entry}", max_episode_steps=EPISODE_STEPS)


_register_tasks()
