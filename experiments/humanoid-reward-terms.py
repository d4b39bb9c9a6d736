"""Where a Humanoid policy's return comes from: the mean of each term of Humanoid-v5's reward over
deterministic episodes, with the episode length and the distance walked, for one or more learner
checkpoints or model files. A return near 5,000 can be a humanoid that stands for 1,000 steps (5 a
step for staying healthy) or one that walks and falls; this tells the two apart.

    python experiments/humanoid-reward-terms.py runs/humanoid-1m/*/checkpoints/learner.pt --episodes 20
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np

from silcr import model_file
from silcr.actor.policy import policy_for
from silcr.common.envs import EnvSpec
from silcr.learner.checkpoint import CheckpointError
from silcr.policy_commands import policy_weights

TERMS = ("reward_survive", "reward_forward", "reward_ctrl", "reward_contact")


def episode(env, policy, spec: EnvSpec, seed: int) -> dict[str, float]:
    obs, info = env.reset(seed=seed)
    x0, sums, steps, ret = info["x_position"], dict.fromkeys(TERMS, 0.0), 0, 0.0
    while True:
        action = spec.to_env_action(policy.deterministic(np.asarray(obs, np.float32)[None]))[0]
        obs, reward, terminated, truncated, info = env.step(action)
        steps, ret = steps + 1, ret + float(reward)
        for term in TERMS:
            sums[term] += float(info[term])
        if terminated or truncated:
            return {"return": ret, **sums, "length": steps, "distance": float(info["x_position"] - x0),
                    "full_length": float(truncated)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", type=Path)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=12345, help="first episode's seed (silcr eval's default)")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    policies = []  # every file checked before any episode runs
    for path in args.checkpoints:
        try:
            weights, env_id = policy_weights(path)
        except (CheckpointError, model_file.ModelFileError) as e:
            parser.error(str(e))
        if not env_id.startswith("Humanoid-"):
            parser.error(f"{path}: a {env_id} policy; this script reads Humanoid's reward terms")
        policies.append((path, weights, env_id))
    print("| checkpoint | return | survive | forward | ctrl | contact | length | distance, m | "
          "forward a step | full-length episodes |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path, weights, env_id in policies:
        spec, env = EnvSpec.of(env_id), gym.make(env_id)
        policy = policy_for(weights, spec)
        eps = [episode(env, policy, spec, args.seed + i) for i in range(args.episodes)]
        mean = {k: float(np.mean([e[k] for e in eps])) for k in eps[0]}
        per_step = sum(e["reward_forward"] for e in eps) / sum(e["length"] for e in eps)
        print(f"| {path} | {mean['return']:,.0f} | {mean['reward_survive']:,.0f} | {mean['reward_forward']:,.0f} | "
              f"{mean['reward_ctrl']:,.0f} | {mean['reward_contact']:,.0f} | {mean['length']:.0f} | "
              f"{mean['distance']:.1f} | {per_step:.2f} | {int(sum(e['full_length'] for e in eps))} of {len(eps)} |",
              flush=True)


if __name__ == "__main__":
    main()
