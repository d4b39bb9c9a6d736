"""`silcr eval` and `silcr demos`: run the policy of a learner checkpoint or a model file, to score it or to record
demonstrations."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def policy_weights(path: Path):
    """The actor weights and env id of a learner checkpoint or a model file (`Model.save`, a run's best.silcr).
    Raises `CheckpointError` or `ModelFileError`, each one line naming the file and the problem."""
    from silcr.learner import model_file
    from silcr.learner.checkpoint import CheckpointError, checked_checkpoint, load_plain
    from silcr.learner.evaluate import weights_from_checkpoint

    payload = load_plain(path, CheckpointError, "checkpoint")
    if model_file.is_model(payload):
        payload = model_file.checked(payload, path)
        return model_file.weights_of(payload["policy"]), str(payload["config"]["env"])
    return weights_from_checkpoint(checked_checkpoint(payload, path))


def _policy_from_checkpoint(args: argparse.Namespace, parser: argparse.ArgumentParser):
    """The checked `--episodes`, and the actor weights, env id and `EnvSpec` of `args.checkpoint`; exit 2 if
    unusable."""
    from silcr.learner import model_file
    from silcr.common.envs import EnvSpec
    from silcr.learner.checkpoint import CheckpointError

    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        weights, env_id = policy_weights(Path(args.checkpoint))
    except (CheckpointError, model_file.ModelFileError) as e:
        parser.error(str(e))
    try:
        return weights, env_id, EnvSpec.of(env_id)
    except ValueError as e:  # a model of an env registered only in the process that trained it
        parser.error(f"{args.checkpoint}: {e}")


def eval_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """`silcr eval CHECKPOINT [--episodes N] [--video out.mp4] [--stochastic] [--json]`."""
    weights, env_id, spec = _policy_from_checkpoint(args, parser)
    import numpy as np

    from silcr.learner.evaluate import evaluation_episodes, summary

    step_infos: list[dict] = []
    try:
        eps = evaluation_episodes(weights, spec, args.episodes, args.seed, Path(args.video) if args.video else None,
                                  not args.stochastic, step_infos)
    except RuntimeError as e:
        print(f"silcr eval: error: {e}", file=sys.stderr)
        return 1
    mean, std, length, success, x_velocity = summary(eps, spec, step_infos)
    returns = [e.episode_return for e in eps]
    at_limit = sum(e.truncated for e in eps)
    if args.json:
        import json

        print(json.dumps({
            "env": env_id, "policy_version": weights.version, "deterministic": not args.stochastic,
            "first_seed": args.seed, "return_mean": mean, "return_std": std, "return_median": float(np.median(returns)),
            "length_mean": length, "goal_share": success, "episodes_at_time_limit": at_limit,
            "x_velocity_mean": x_velocity,
            "episodes": [{"seed": args.seed + i, "return": e.episode_return, "length": e.length,
                          "terminated": e.terminated, "truncated": e.truncated, "goal": spec.reached_goal(e)}
                         for i, e in enumerate(eps)],
        }, indent=2))
        return 0
    sampled = ", sampled actions" if args.stochastic else ""
    # The median and the episodes that ran to the time limit tell a policy that always does middling from one
    # that either succeeds or fails early (Humanoid's walkers and fallers), which mean ± std alone does not.
    print(f"{env_id}, policy version {weights.version}{sampled}: return {mean:.1f} ± {std:.1f} over {args.episodes} "
          f"episodes (median {np.median(returns):.1f}, mean length {length:.0f}, {at_limit} of {len(eps)} ran to the "
          f"time limit)"
          + ("" if success is None else f", goal reached in {success:.0%}")
          + ("" if x_velocity is None else f", forward velocity {x_velocity:.2f} m/s")
          + (f"; video: {args.video}" if args.video else ""))
    return 0


def demos_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """`silcr demos CHECKPOINT --episodes N -o demos.npz [--stochastic]`."""
    import numpy as np

    out = Path(args.out)
    if out.suffix != ".npz":
        parser.error(f"-o {args.out}: the demonstrations file must end in .npz")
    weights, env_id, spec = _policy_from_checkpoint(args, parser)
    from silcr.common.demos import save_demos
    from silcr.learner.evaluate import record_demos

    if spec.discrete:  # --algo sqil and --expert-init, which read these files, run with continuous actions only
        parser.error(f"{args.checkpoint}: {env_id} has discrete actions; demonstrations files hold continuous ones "
                     f"(for --algo sqil and --expert-init, which refuse discrete actions)")
    print(f"recording {args.episodes} episodes of {env_id}, policy version {weights.version} "
          f"({'stochastic' if args.stochastic else 'deterministic'})", flush=True)

    def show(ep) -> None:
        print(f"  episode: return {ep.episode_return:9.1f}, length {ep.length}", flush=True)

    eps = record_demos(weights, spec, args.episodes, args.seed, not args.stochastic, show)
    save_demos(out, env_id, eps)
    returns = [e.episode_return for e in eps]
    print(f"wrote {out}: {len(eps)} episodes, {sum(e.length for e in eps)} transitions, "
          f"return {np.mean(returns):.1f} ± {np.std(returns):.1f}")
    return 0
