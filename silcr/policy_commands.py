"""`silcr eval` and `silcr demos`: run a learner checkpoint's policy, to score it or to record demonstrations."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _policy_from_checkpoint(args: argparse.Namespace, parser: argparse.ArgumentParser):
    """The checked `--episodes` and the actor weights and env id of `args.checkpoint` (exit 2 if unusable)."""
    from silcr.learner.checkpoint import CheckpointError, load_checkpoint
    from silcr.learner.evaluate import weights_from_checkpoint

    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        payload = load_checkpoint(Path(args.checkpoint))
    except CheckpointError as e:
        parser.error(str(e))
    return weights_from_checkpoint(payload)


def eval_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """`silcr eval CHECKPOINT [--episodes N] [--video out.mp4] [--stochastic]`."""
    weights, env_id = _policy_from_checkpoint(args, parser)
    from silcr.common.envs import EnvSpec
    from silcr.learner.evaluate import evaluate

    try:
        mean, std, length, success = evaluate(weights, EnvSpec.of(env_id), args.episodes, args.seed,
                                              Path(args.video) if args.video else None, not args.stochastic)
    except RuntimeError as e:
        print(f"silcr eval: error: {e}", file=sys.stderr)
        return 1
    sampled = ", sampled actions" if args.stochastic else ""
    print(f"{env_id}, policy version {weights.version}{sampled}: return {mean:.1f} ± {std:.1f} over {args.episodes} "
          f"episodes (mean length {length:.0f})"
          + ("" if success is None else f", goal reached in {success:.0%}") + (f"; video: {args.video}" if args.video else ""))
    return 0


def demos_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """`silcr demos CHECKPOINT --episodes N -o demos.npz [--stochastic]`."""
    import numpy as np

    out = Path(args.out)
    if out.suffix != ".npz":
        parser.error(f"-o {args.out}: the demonstrations file must end in .npz")
    weights, env_id = _policy_from_checkpoint(args, parser)
    from silcr.common.demos import save_demos
    from silcr.common.envs import EnvSpec
    from silcr.learner.evaluate import record_demos

    spec = EnvSpec.of(env_id)
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
