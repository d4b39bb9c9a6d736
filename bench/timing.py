"""Measuring on a shared, noisy machine: alternate the candidate and its reference, report ratios."""

from __future__ import annotations

import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any, Callable


def rate(fn: Callable[[], None], n: int, sync: Callable[[], None] = lambda: None) -> float:
    """Calls per second of `fn` over `n` calls."""
    sync()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    sync()
    return n / (time.perf_counter() - t0)


def alternate(candidate: Callable[[], float], reference: Callable[[], float], rounds: int) -> tuple[float, float, float]:
    """Median candidate rate, median reference rate and the median of per-round ratios.

    Interleaving the two in each round exposes both to the same background load,
    so the ratio is far steadier than either absolute figure.
    """
    c, r, ratios = [], [], []
    for _ in range(rounds):
        rc, rr = candidate(), reference()
        c.append(rc)
        r.append(rr)
        ratios.append(rc / rr)
    return statistics.median(c), statistics.median(r), statistics.median(ratios)


def machine() -> dict[str, Any]:
    import os

    import torch

    info = {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            # idle OpenMP threads sleeping (PASSIVE, silcr's default) or spinning changes CPU
            # update rates by up to 30%, either way depending on what else runs (docs/performance.md)
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name()
    return info


def write_json(out_dir: Path, name: str, payload: dict[str, Any]) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.json"
    path.write_text(json.dumps({"bench": name, "machine": machine(), "time": time.time(), **payload}, indent=2))
    return path


def print_table(title: str, columns: list[str], rows: list[list[Any]]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=title)
    for c in columns:
        t.add_column(c, justify="right")
    for row in rows:
        t.add_row(*[f"{v:,.2f}" if isinstance(v, float) else str(v) for v in row])
    Console(width=max(Console().width, 150)).print(t)
