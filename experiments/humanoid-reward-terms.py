"""Where a Humanoid policy's return comes from: the mean of each term of Humanoid-v5's reward over
deterministic episodes, with the episode length and the distance walked, for one or more learner
checkpoints or model files. A return near 5,000 can be a humanoid that stands for 1,000 steps (5 a
step for staying healthy) or one that walks and falls; this tells the two apart.

With `--records`, the arguments are run directories instead, and no policy runs: from progress.csv's
in-run evaluations, per stretch of env steps, the mean evaluation length and the return above the
healthy bonus per evaluation step, (return - 5 x length) / length, which is the forward reward less
the costs. (A fall's last step pays no bonus, so for episodes that fall this understates that figure
by 5 / length per step: under 0.05 for episodes of 100 steps or more.)

    python experiments/humanoid-reward-terms.py runs/humanoid-1m/*/checkpoints/learner.pt --episodes 20
    python experiments/humanoid-reward-terms.py --records results/humanoid-1m/runs/*
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from silcr.learner import model_file
from silcr.actor.policy import policy_for
from silcr.common.envs import EnvSpec, make_env
from silcr.learner.checkpoint import CheckpointError
from silcr.learner.evaluate import rollout
from silcr.policy_commands import policy_weights
from silcr.common.run_records import load_run

TERMS = ("reward_survive", "reward_forward", "reward_ctrl", "reward_contact")
HEALTHY_BONUS = 5.0  # Humanoid-v5's healthy_reward, paid for each step the humanoid is up


def episode(env, policy, spec: EnvSpec, seed: int) -> dict[str, float]:
    infos: list[dict] = []  # the reset's, then one a step
    ep = rollout(env, policy, spec, seed, infos=infos)
    return {"return": ep.episode_return, **{term: sum(float(i[term]) for i in infos[1:]) for term in TERMS},
            "length": ep.length, "distance": float(infos[-1]["x_position"] - infos[0]["x_position"]),
            "full_length": float(ep.truncated)}


def record_stretches(run_dir: Path, stretch: int) -> list[tuple[float, float]]:
    """(mean evaluation length, return above the healthy bonus per evaluation step) for each stretch of
    `stretch` env steps, from the run's in-run evaluations (rows a resume wrote again superseded, as
    `silcr plot` does), up to the run's `total_steps`: the closing evaluation just past it is left out, and
    a stretch with no evaluation yet (a run still going) gives NaNs."""
    returns, lengths = load_run(run_dir, "eval_return"), load_run(run_dir, "eval_length")
    if not np.array_equal(returns.steps, lengths.steps):
        raise ValueError(f"{run_dir}: progress.csv's eval_return and eval_length rows differ")
    if not returns.env.startswith("Humanoid-"):
        raise ValueError(f"{run_dir}: a {returns.env} run; this script reads Humanoid's reward terms")
    out = []
    for k in range(-(-int(returns.config["total_steps"]) // stretch)):
        inside = (returns.steps > k * stretch) & (returns.steps <= (k + 1) * stretch)
        r, n = returns.returns[inside], lengths.returns[inside]
        out.append((float(n.mean()), float((r - HEALTHY_BONUS * n).sum() / n.sum())) if inside.any() else (np.nan, np.nan))
    return out


def print_records(run_dirs: list[Path], stretch: int, parser: argparse.ArgumentParser) -> None:
    try:
        table = [(d, record_stretches(d, stretch)) for d in run_dirs]
    except ValueError as e:
        parser.error(str(e))
    width = max(len(cells) for _, cells in table)
    heads = [f"{k * stretch // 1000}k-{(k + 1) * stretch // 1000}k" for k in range(width)]
    print(f"Each cell: mean evaluation length, return above the healthy bonus per evaluation step ({stretch:,} env steps a column)\n")
    print("| run | " + " | ".join(heads) + " |")
    print("|---|" + "---|" * width)
    for d, cells in table:
        print(f"| {d.name} | " + " | ".join("-" if np.isnan(n) else f"{n:.0f}, {x:.2f}" for n, x in cells) + " |" * (width - len(cells) + 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", type=Path, help="learner checkpoints or model files; "
                        "run directories with --records")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=12345, help="first episode's seed (silcr eval's default)")
    parser.add_argument("--records", action="store_true", help="read the runs' progress.csv instead of running policies")
    parser.add_argument("--stretch", type=int, default=200_000, help="env steps per stretch with --records")
    args = parser.parse_args()
    if args.records:
        if args.stretch < 1:
            parser.error(f"--stretch must be >= 1, got {args.stretch}")
        print_records(args.checkpoints, args.stretch, parser)
        return
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
        spec, env = EnvSpec.of(env_id), make_env(env_id, "dense")  # as `silcr eval` makes it
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
