"""Keeping what D_E holds (issue 61): the columns that show it in every run, `eval_x_velocity` and `keep_ratio`,
and the behaviour-cloning term on D_E rows (`--bc-weight`). Real MuJoCo where the env's own numbers matter."""

from __future__ import annotations

import csv

import gymnasium as gym
import numpy as np
import pytest
import torch

from silcr.actor.policy import initial_weights
from silcr.buffer_service.tables import Tables
from silcr.common.config import Config, ConfigError, from_options
from silcr.common.envs import EnvSpec, make_env
from silcr.learner.evaluate import evaluate, rollout
from silcr.learner.evaluations import Evaluations, keep_ratio
from silcr.learner.sac import Sac, SacHyper
from silcr.learner.update import Update
from silcr.actor.policy import policy_for
from tests.conftest import make_episode


class Strider(gym.Env):
    """Five steps; each step's info reports a forward velocity and, under other keys, numbers that are not it."""

    observation_space = gym.spaces.Box(-10, 10, (2,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(2, np.float32), {"x_position": 0.0}

    def step(self, action):
        self.t += 1
        v = 0.5 + self.t  # 1.5, 2.5, ... 5.5: mean 3.5
        info = {"x_velocity": v, "y_velocity": -v, "reward_forward": 3 * v, "x_position": 10.0 * self.t}
        return np.array([self.t, 0], np.float32), 0.0, False, self.t >= 5, info


gym.register("silcr-test/Strider-v0", entry_point=Strider)


def _weights(spec: EnvSpec):
    return initial_weights(spec.obs_dim, spec.act_dim, [16], seed=0)


def test_eval_x_velocity_is_the_mean_of_the_steps_x_velocity_and_empty_without_it():
    spec = EnvSpec.of("silcr-test/Strider-v0")
    assert evaluate(_weights(spec), spec, 2, seed=0).x_velocity == pytest.approx(3.5)  # not -3.5, 10.5 or 30
    pendulum = EnvSpec.of("InvertedPendulum-v5")  # reports no x_velocity: the column stays empty
    assert evaluate(_weights(pendulum), pendulum, 2, seed=0).x_velocity is None


def test_eval_x_velocity_on_mujoco_is_the_distance_the_torso_covered_per_second():
    """Hopper-v5 (real MuJoCo): the mean velocity over the evaluation's steps is the distance the torso moved,
    summed over episodes, over the time they took: a check from x_position, another key of the env's own."""
    spec = EnvSpec.of("Hopper-v5")
    weights = _weights(spec)
    got = evaluate(weights, spec, 3, seed=11).x_velocity
    env = make_env("Hopper-v5", "dense")
    distance, steps = 0.0, 0
    for i in range(3):
        infos: list[dict] = []
        rollout(env, policy_for(weights, spec), spec, 11 + i, infos=infos)
        distance += infos[-1]["x_position"] - infos[0]["x_position"]
        steps += len(infos) - 1
    assert got == pytest.approx(distance / (steps * env.unwrapped.dt), rel=1e-6)
    assert abs(got) > 1e-3  # a moving torso: the check above is not 0 == 0


def test_keep_ratio_waits_for_a_full_d_e():
    assert keep_ratio(300.0, {"expert_min_return": 400.0, "expert_full": True}) == pytest.approx(0.75)
    assert keep_ratio(300.0, {"expert_min_return": 400.0, "expert_full": False}) == ""  # D_E still filling
    assert keep_ratio(300.0, {"expert_min_return": 400.0}) == ""  # a buffer that predates expert_full
    assert keep_ratio(300.0, {"expert_min_return": None, "expert_full": True}) == ""  # no D_E (plain SAC)
    assert keep_ratio(-3.0, {"expert_min_return": -5.0, "expert_full": True}) == ""  # a ratio to a negative bar


def test_the_buffer_says_d_e_is_full_once_it_first_turns_an_episode_away():
    tables = Tables(Config(run="t", env="Hopper-v5", algo="silcr", expert_capacity=30), EnvSpec.of("Hopper-v5"))
    fullness = []
    for seq, (length, ret) in enumerate([(10, 1.0), (10, 2.0), (10, 3.0), (10, 4.0), (5, 0.5)]):
        tables.add(make_episode(length, ret, obs_dim=11, act_dim=3, seq=seq))
        fullness.append(tables.expert_meta()["expert_full"])
    assert fullness == [False, False, False, True, True]  # the fourth found no room (it evicted the first)


def test_a_progress_row_has_keep_ratio_only_once_d_e_is_full(tmp_path):
    cfg = Config(run="keep", env="silcr-test/Strider-v0", hidden=[16], eval_episodes=2, algo="silcr")
    spec = EnvSpec.of(cfg.env)
    evaluations = Evaluations(cfg, spec, tmp_path, resumed=False)
    w = _weights(spec)
    for steps, full in ((100, False), (200, True)):
        evaluations.run(w, {"time": 0.0, "env_steps": steps, "updates": steps}, {}, steps,
                        {"expert_min_return": 0.5, "expert_full": full})
    evaluations.close()
    with open(tmp_path / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["keep_ratio"] for r in rows][0] == ""
    assert float(rows[1]["keep_ratio"]) == pytest.approx(float(rows[1]["eval_return"]) / 0.5)
    assert all(float(r["eval_x_velocity"]) == pytest.approx(3.5) for r in rows)


def _sac(bc_weight: float) -> Sac:
    torch.manual_seed(0)
    return Sac(3, 2, [32, 32], SacHyper(bc_weight=bc_weight), torch.device("cpu"))


def _batch(n: int = 64):
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(n, 3, generator=g)
    actions = torch.full((n, 2), -0.8)
    actions[n // 2:] = 0.8  # D_E's rows all act +0.8
    rewards = torch.zeros(n)
    rewards[n // 2:] = 1.0
    return obs, actions, rewards, torch.randn(n, 3, generator=g), torch.zeros(n), torch.zeros(n)


def test_the_bc_term_pulls_the_policy_toward_d_es_actions_only():
    batch = _batch()
    expert_obs = batch[0][32:]
    plain, cloning = _sac(0.0), _sac(2.0)
    for _ in range(150):
        torch.manual_seed(5)
        plain_stats = plain.update(*batch, expert_from=32)
        torch.manual_seed(5)
        bc_stats = cloning.update(*batch, expert_from=32)
    gap = {name: float((s.actor.mean_action(expert_obs).detach() - 0.8).abs().mean()) for name, s in
           (("plain", plain), ("bc", cloning))}
    assert gap["bc"] < 0.5 * gap["plain"], gap
    assert "bc_loss" in bc_stats and "bc_loss" not in plain_stats
    assert float(bc_stats["bc_loss"]) == pytest.approx(float(((cloning.actor.mean_action(expert_obs).detach() - 0.8)
                                                               ** 2).mean()), rel=0.2)
    # with no D_E rows in the batch the term is off: the same update as without it, to the last digit
    torch.manual_seed(5)
    a = _sac(2.0).update(*batch, expert_from=None)
    torch.manual_seed(5)
    b = _sac(0.0).update(*batch, expert_from=None)
    assert float(a["actor_loss"]) == float(b["actor_loss"]) and "bc_loss" not in a


def test_the_target_entropy_is_the_option_per_action_dimension():
    """`--target-entropy-per-dim` sets the target of the temperature loss (J(alpha), learner/sac.py): -|A| by default."""
    spec = EnvSpec.of("Hopper-v5")  # |A| = 3
    default = Update(from_options({"env": "Hopper-v5", "hidden": [16, 16]}, "train"), spec)
    lower = Update(from_options({"env": "Hopper-v5", "hidden": [16, 16], "target_entropy_per_dim": -2.5}, "train"), spec)
    assert default.sac.target_entropy == -3.0 and lower.sac.target_entropy == -7.5
    # the temperature rises while the policy's entropy is below the target and falls while it is above
    batch = _batch()
    high = Sac(3, 2, [32, 32], SacHyper(target_entropy=2 * 0.65), torch.device("cpu"))  # near the most, 2 log 2
    low = Sac(3, 2, [32, 32], SacHyper(target_entropy=2 * -5.0), torch.device("cpu"))
    for _ in range(20):
        high.update(*batch, expert_from=32)
        low.update(*batch, expert_from=32)
    assert float(high.alpha) > 1.0 > float(low.alpha)
    with pytest.raises(ConfigError, match="--target-entropy-per-dim: must be below log 2"):
        from_options({"env": "Hopper-v5", "target_entropy_per_dim": 0.7}, "train")
    with pytest.raises(ValueError, match="--target-entropy-per-dim: .* has discrete actions"):
        Update(from_options({"env": "MiniGrid-Empty-5x5-v0", "target_entropy_per_dim": -2.0}, "train"),
               EnvSpec.of("MiniGrid-Empty-5x5-v0"))


def test_bc_weight_is_refused_where_it_cannot_act():
    with pytest.raises(ConfigError, match="--bc-weight: only --algo silcr or --algo sqil or --algo ircr uses it"):
        from_options({"env": "Hopper-v5", "algo": "sac", "bc_weight": 0.4}, "train")
    with pytest.raises(ConfigError, match="--bc-weight: must be >= 0"):
        from_options({"env": "Hopper-v5", "bc_weight": -0.1}, "train")
    assert from_options({"env": "Hopper-v5", "bc_weight": 0.4}, "train").bc_weight == 0.4
