"""Learning curves and summary tables from run directories (`silcr plot`).

A run directory holds `config.toml` (env, algo, seed) and `progress.csv`
(`env_steps`, `eval_return`). Runs of the same (env, algo) are seeds of one
curve: their evaluations are interpolated onto a common grid of environment
steps (up to the shortest run) and shown as the mean with a +-1 std band.
"""

from __future__ import annotations

import argparse
import csv
import tomllib
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class RunCurve:
    path: Path
    env: str
    algo: str
    seed: int
    steps: np.ndarray
    returns: np.ndarray


def load_run(path: Path) -> RunCurve:
    try:
        cfg = tomllib.loads((path / "config.toml").read_text())
        with open(path / "progress.csv", newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("eval_return") not in (None, "")]
    except FileNotFoundError as e:
        raise ValueError(f"{path} is not a run directory (missing {Path(e.filename).name})") from None
    except (tomllib.TOMLDecodeError, csv.Error, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: unreadable run files ({e})") from None
    if not rows:
        raise ValueError(f"{path}: progress.csv has no evaluations yet")
    try:
        steps = np.array([float(r["env_steps"]) for r in rows])
        returns = np.array([float(r["eval_return"]) for r in rows])
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path}: progress.csv lacks env_steps/eval_return numbers ({e})") from None
    algo = cfg.get("algo", "?")
    # SILCR and SQIL ignore the env's reward; SAC's label says which one it had.
    label = f"{algo}-{cfg.get('reward', '')}" if algo == "sac" else algo
    if algo == "silcr" and cfg.get("expert_capacity", 50_000) != 50_000:
        label += f" (M={cfg['expert_capacity']:.0e})".replace("e+0", "e")  # the M ablation: one curve per M
    return RunCurve(path, cfg.get("env", "?"), label, int(cfg.get("seed", 0)), steps, returns)


def group(runs: list[RunCurve]) -> dict[str, dict[str, list[RunCurve]]]:
    out: dict[str, dict[str, list[RunCurve]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        out[r.env][r.algo].append(r)
    return out


def mean_curve(runs: list[RunCurve], points: int = 100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    end = min(r.steps[-1] for r in runs)
    grid = np.linspace(0.0, end, points) if end > 0 else np.zeros(1)
    ys = np.stack([np.interp(grid, r.steps, r.returns) for r in runs])
    return grid, ys.mean(0), ys.std(0)


def plot(runs: list[RunCurve], out: Path, expert: float | None = None, title: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group(runs)
    envs = sorted(groups)
    cols = min(3, len(envs))
    rows = (len(envs) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False)
    for ax, env in zip(axes.flat, envs):
        for algo in sorted(groups[env]):
            seeds = groups[env][algo]
            x, m, s = mean_curve(seeds)
            (line,) = ax.plot(x, m, label=f"{algo} ({len(seeds)} seed{'s' if len(seeds) > 1 else ''})")
            ax.fill_between(x, m - s, m + s, color=line.get_color(), alpha=0.2)
        if expert is not None:
            ax.axhline(expert, linestyle="--", color="black", label="expert")
        ax.set_title(env)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("evaluation return (dense)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    for ax in list(axes.flat)[len(envs):]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    if out.suffix == ".png":
        fig.savefig(out.with_suffix(".svg"))
    return fig


def summary_markdown(runs: list[RunCurve]) -> str:
    """Final and best evaluation return per (env, algo): mean +- std over seeds."""
    lines = ["| env | algo | seeds | env steps | final return | best return |", "|---|---|---|---|---|---|"]
    groups = group(runs)
    for env in sorted(groups):
        for algo in sorted(groups[env]):
            seeds = groups[env][algo]
            final = np.array([r.returns[-1] for r in seeds])
            best = np.array([r.returns.max() for r in seeds])
            steps = int(min(r.steps[-1] for r in seeds))
            lines.append(
                f"| {env} | {algo} | {len(seeds)} | {steps:,} | {final.mean():.1f} ± {final.std():.1f} | "
                f"{best.mean():.1f} ± {best.std():.1f} |"
            )
    return "\n".join(lines) + "\n"


def plot_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """`silcr plot RUN_DIR... -o fig.png [--table t.md]`."""
    try:
        runs = [load_run(Path(r)) for r in args.runs]
    except ValueError as e:
        parser.error(str(e))
    out = Path(args.out)
    if out.suffix not in (".png", ".svg", ".pdf"):
        parser.error(f"-o {args.out}: use a .png, .svg or .pdf file name")
    plot(runs, out, args.expert, args.title)
    table = summary_markdown(runs)
    print(table, end="")
    if args.table:
        Path(args.table).write_text(table)
    print(f"wrote {out}" + (f" and {out.with_suffix('.svg')}" if out.suffix == ".png" else ""))
    return 0
