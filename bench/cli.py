"""`silcr bench [learner|buffer|actor|e2e|scale|peer|all]`: run benchmarks, print tables, write JSON."""

from __future__ import annotations

from pathlib import Path


def run_bench(which: str, out_dir: Path, device: str, quick: bool, counts: list[int] | None = None,
              envs_per_actor: int = 1, seconds: float = 0.0, rounds: int = 0, paced: bool = False,
              train_args: list[str] = (), tag: str = "", hosts: int = 0) -> int:
    from . import actor, buffer, e2e, learner, peer, scale

    if which == "peer":
        peer.run(out_dir, quick, rounds)
    if which == "scale":
        scale.run(out_dir, quick, counts or None, envs_per_actor, seconds=seconds or None, paced=paced,
                  train_args=train_args, tag=tag, hosts=hosts)

    if which in ("learner", "all"):
        learner.run(out_dir, "cpu", quick)
        if device in ("cuda", "auto"):
            import torch

            if torch.cuda.is_available():
                learner.run(out_dir, "cuda", quick)
            elif device == "cuda":
                print("silcr bench: CUDA is not available; skipped the GPU learner benchmark")
    if which in ("buffer", "all"):
        buffer.run(out_dir, quick)
    if which in ("actor", "all"):
        actor.run(out_dir, quick)
    if which in ("e2e", "all"):
        e2e.run(out_dir, quick)
    print(f"results written to {out_dir}/")
    return 0
