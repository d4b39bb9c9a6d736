"""The episodic-reward wrapper and the env factory."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from silcr.common.envs import PAPER_TASKS, EnvSpec, EpisodicReward, make_env


def _rollout(env, seed=0, steps=None):
    env.reset(seed=seed)
    env.action_space.seed(seed)
    rewards, dense, done, n = [], [], False, 0
    while not done and (steps is None or n < steps):
        _, r, term, trunc, info = env.step(env.action_space.sample())
        rewards.append(r)
        dense.append(info.get("dense_reward"))
        done = term or trunc
        n += 1
    return rewards, dense, done


def test_episodic_reward_is_zero_until_the_end_then_the_sum():
    rewards, dense, done = _rollout(make_env("Hopper-v5", "episodic"))
    assert done
    assert all(r == 0.0 for r in rewards[:-1])
    assert rewards[-1] == pytest.approx(sum(dense))
    # identical trajectory under the dense env gives the same total
    dense_rewards, _, _ = _rollout(make_env("Hopper-v5", "dense"))
    assert sum(dense_rewards) == pytest.approx(rewards[-1])


def test_episodic_reward_pays_at_time_limit_truncation():
    env = make_env("InvertedPendulum-v5", "episodic", max_episode_steps=5)
    env.reset(seed=0)
    out = []
    for _ in range(5):
        _, r, term, trunc, info = env.step(np.zeros(1, np.float32))
        out.append((r, term, trunc, info["dense_reward"]))
    assert out[-1][2] and not out[-1][1]
    assert [o[0] for o in out[:-1]] == [0.0] * 4
    assert out[-1][0] == pytest.approx(sum(o[3] for o in out))


def test_reset_clears_the_running_sum():
    env = make_env("InvertedPendulum-v5", "episodic", max_episode_steps=3)
    for _ in range(2):
        env.reset(seed=1)
        total = 0.0
        for _ in range(3):
            _, r, *_ = env.step(np.zeros(1, np.float32))
            total += r
        assert total == pytest.approx(3.0)


@pytest.mark.filterwarnings("ignore")
def test_wrapper_passes_gymnasiums_env_checker():
    check_env(EpisodicReward(gym.make("Hopper-v5").unwrapped), skip_render_check=True)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("task", PAPER_TASKS)
def test_registered_episodic_tasks(task):
    env = gym.make(f"silcr/{task}")
    rewards, dense, done = _rollout(env, steps=50)
    if not done:
        assert all(r == 0.0 for r in rewards)
    else:
        assert rewards[-1] == pytest.approx(sum(dense))
    env.close()


def test_registered_episodic_ids_follow_the_requested_reward():
    """`make_env("silcr/Hopper-v5", "dense")` (evaluation) is the plain task, never the episodic wrapper twice."""
    dense = make_env("silcr/Hopper-v5", "dense")
    episodic = make_env("silcr/Hopper-v5", "episodic")
    assert not isinstance(dense, EpisodicReward) and isinstance(episodic, EpisodicReward)
    assert not isinstance(episodic.env, EpisodicReward)
    step_rewards, _, _ = _rollout(dense, steps=5)
    assert all(r != 0.0 for r in step_rewards)  # Hopper's dense reward: alive bonus and progress at every step
    dense.close()
    episodic.close()


def test_env_spec_and_action_rescaling():
    spec = EnvSpec.of("Humanoid-v5")
    assert (spec.obs_dim, spec.act_dim, spec.max_episode_steps) == (348, 17, 1000)
    np.testing.assert_allclose(spec.to_env_action(np.full(17, -1.0)), spec.action_low)
    np.testing.assert_allclose(spec.to_env_action(np.full(17, 1.0)), spec.action_high)
    np.testing.assert_allclose(spec.to_env_action(np.zeros(17)), (spec.action_low + spec.action_high) / 2)


@pytest.mark.parametrize("env_id,problem", [("NoSuchEnv-v0", "unknown"), ("FrozenLake-v1", "Box observations"),
                                            ("MiniGrid-NoSuchTask-v0", "unknown")])
def test_make_env_rejects_unusable_envs(env_id, problem):
    with pytest.raises(ValueError, match=problem):
        make_env(env_id)
