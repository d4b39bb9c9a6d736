"""Learner benchmark: updates/s of `learner.sac.Sac` against the plain reference, and the matmul ceiling."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from silcr.learner.sac import Sac, SacHyper

from .reference_sac import PlainSac, matmul_gflops, matmul_only_rate, random_batch, record_matmuls, update_flops
from .timing import alternate, print_table, rate, write_json

SHAPES = {"Hopper": (11, 3), "Humanoid": (348, 17)}


def run(out_dir: Path, device: str = "cpu", quick: bool = False, hidden: list[int] | None = None, batch: int = 128) -> dict[str, Any]:
    dev = torch.device(device)
    hidden = hidden or [800, 400]
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    n = 5 if quick else 20 if dev.type == "cpu" else 500
    rounds = 3 if quick else 7
    gflops = matmul_gflops(dev, 0.5 if quick else 2.0)
    rows, results = [], {}
    for name, (obs_dim, act_dim) in SHAPES.items():
        torch.manual_seed(0)
        proj = Sac(obs_dim, act_dim, hidden, SacHyper(), dev)
        ref = PlainSac(obs_dim, act_dim, hidden, dev)
        b = random_batch(obs_dim, act_dim, batch, dev)
        for _ in range(3):
            proj.update(*b)
            ref.update(*b)
        ups, ref_ups, ratio = alternate(lambda: rate(lambda: proj.update(*b), n, sync),
                                        lambda: rate(lambda: ref.update(*b), n, sync), rounds)
        flops = update_flops(obs_dim, act_dim, hidden, batch)
        ceiling = gflops * 1e9 / flops
        # The update's own matmuls replayed alone, alternated with the update itself:
        # the ceiling at the shapes the update really has (thin layers, batch 128).
        calls = record_matmuls(lambda: proj.update(*b))
        _, own_ceiling, own_fraction = alternate(lambda: rate(lambda: proj.update(*b), n, sync),
                                                 lambda: matmul_only_rate(calls, dev, 0.3 if quick else 1.0), rounds)
        results[name] = {"updates_per_s": ups, "reference_updates_per_s": ref_ups, "ratio_vs_reference": ratio,
                         "update_gflop": flops / 1e9, "ceiling_updates_per_s": ceiling, "fraction_of_ceiling": ups / ceiling,
                         "matmuls_alone_per_s": own_ceiling, "fraction_of_own_shape_ceiling": own_fraction}
        rows.append([name, ups, ref_ups, ratio, ceiling, ups / ceiling, own_ceiling, own_fraction])
    print_table(f"learner on {device}: batch {batch}, networks {hidden}, matmul {gflops:.0f} GFLOP/s",
                ["task shape", "updates/s", "plain ref/s", "ratio", "ceiling/s", "of ceiling",
                 "matmuls alone/s", "of that"], rows)
    payload = {"device": device, "batch": batch, "hidden": hidden, "matmul_gflops": gflops, "threads": torch.get_num_threads(),
               "results": results}
    write_json(out_dir, f"learner-{device}", payload)
    return payload
