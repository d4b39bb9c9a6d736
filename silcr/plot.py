"""Learning curves and summary tables from run directories (`silcr plot`).

A run directory holds `config.toml` (env, algo, seed) and `progress.csv`
(`env_steps`, `eval_return`). Runs of the same (env, label) are seeds of one
curve: their values are interpolated onto a common grid of environment steps
(up to the shortest run) and shown as the mean with a +-1 std band.

A label is the algorithm (with SAC's reward and a non-default M), plus every
setting that differs between the runs plotted together (`tau=0.005`,
`expert_admission=recent`, ...), so that runs of different settings are never
averaged into one curve. Cells of one `silcr sweep` (directories named
`<variant>_<task>_s<seed>`) are labelled by their experiment's variant names
instead, when each name stands for one set of settings. `--metric` plots another progress.csv column
(`expert_min_return`: D_E's lowest return; `q_max`: the critics' largest Q).
"""

from __future__ import annotations

import argparse
import csv
import re
import tomllib
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from silcr.common.algorithms import ALGORITHM_OPTIONS, ALGORITHMS
from silcr.common.config import Config


@dataclass
class RunCurve:
    path: Path
    env: str
    algo: str  # the curve's label
    seed: int
    steps: np.ndarray
    returns: np.ndarray  # the plotted metric (the evaluation return unless --metric says otherwise)
    config: dict = field(default_factory=dict)
    q_watched: bool = False  # progress.csv has the divergence counter (silcr 0.2 and later)
    first_past_q_bound: float | None = None  # env steps of the first row where q_bound_exceeded > 0
    wall_s: float | None = None  # the run's processes' wall time, every resumed stretch added


def wall_seconds(rows: list[dict]) -> float | None:
    """progress.csv's `time` counts from each start of the run, so a resume starts it again
    from zero: the run's wall time is the sum of each stretch's last value. Rows that a resume
    wrote again count too, as their compute was spent."""
    try:
        times = [float(r["time"]) for r in rows if r.get("time") not in (None, "")]
    except ValueError:
        return None
    if not times:
        return None
    ends = [t for t, following in zip(times, times[1:]) if following < t]
    return sum(ends) + times[-1]


#: Config keys that never tell curves apart: they name or place a run, say how it was
#: executed, or are already in the label.
NOT_A_SETTING = {"run", "runs_dir", "seed", "resume", "connect", "listen", "zenoh_mode", "actor_zenoh_mode",
                 "zenoh_config", "zenoh_listen",
                 "device", "torch_threads", "stats_interval", "checkpoint_interval", "buffer_checkpoint_interval",
                 "max_restarts", "actor_id", "actors", "envs_per_actor", "single_process", "weights_poll_steps",
                 "weights_wait", "batches_per_request", "requests_in_flight", "max_episode_bytes", "no_throttle",
                 "spi_tolerance", "env", "algo", "reward", "expert_capacity", "demos", "eval_interval", "eval_episodes",
                 "total_steps"}


_DEFAULTS = Config(run="defaults").to_dict()


def base_label(cfg: dict) -> str:
    """The algorithm's name; only the algorithms that learn from the env's reward say which one they had."""
    algo = cfg.get("algo", "?")
    spec = ALGORITHMS.get(algo)
    return f"{algo}-{cfg.get('reward', '')}" if spec is not None and spec.uses_env_reward else algo


def load_run(path: Path, metric: str = "eval_return") -> RunCurve:
    try:
        # A run from before an option existed did what the option's default does (options are
        # added keeping the behaviour they replace), so a missing key reads as today's default.
        cfg = _DEFAULTS | tomllib.loads((path / "config.toml").read_text())
        with open(path / "progress.csv", newline="") as f:
            all_rows = list(csv.DictReader(f))
    except FileNotFoundError as e:
        raise ValueError(f"{path} is not a run directory (missing {Path(e.filename).name})") from None
    except (tomllib.TOMLDecodeError, csv.Error, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: unreadable run files ({e})") from None
    rows = [r for r in all_rows if r.get(metric) not in (None, "")]
    if not rows:
        raise ValueError(f"{path}: progress.csv has no values of {metric} yet")
    try:
        steps = np.array([float(r["env_steps"]) for r in rows])
        values = np.array([float(r[metric]) for r in rows])
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path}: progress.csv lacks env_steps/{metric} numbers ({e})") from None
    # A resumed run goes on from its last checkpoint, so its rows can step back: the rows
    # after the checkpoint that the run lost are superseded by the ones written again.
    # (Equal steps are two evaluations, as the final one after the last scheduled one.)
    later_min = np.minimum.accumulate(steps[::-1])[::-1]
    keep = np.append(steps[:-1] <= later_min[1:], True)
    steps, values = steps[keep], values[keep]
    label = base_label(cfg)
    spec = ALGORITHMS.get(cfg.get("algo", "?"))
    if spec is not None and spec.ranks_own_episodes and cfg["expert_capacity"] != _DEFAULTS["expert_capacity"]:
        label += f" (M={cfg['expert_capacity']:.0e})".replace("e+0", "e")  # the M ablation: one curve per M
    past = [float(r["env_steps"]) for r in all_rows if (r.get("q_bound_exceeded") or "0") not in ("", "0")]
    return RunCurve(path, cfg.get("env", "?"), label, int(cfg.get("seed", 0)), steps, values, cfg,
                    "q_bound_exceeded" in all_rows[0], past[0] if past else None, wall_seconds(all_rows))


def sweep_variant(run: RunCurve) -> str | None:
    """The experiment variant of a `silcr sweep` cell, from its directory's name `<variant>_<task>_s<seed>`."""
    suffix = f"_{run.env.replace('/', '-')}_s{run.seed}"
    name = run.path.name
    return name[: -len(suffix)] if name.endswith(suffix) and len(name) > len(suffix) else None


def label_by_variant(runs: list[RunCurve]) -> bool:
    """Label sweep cells by their experiment's variant names (`silcr`, `silcr-recent`, `sac`, ...) when every
    run is one and each variant's runs share their settings; say whether it did (else `distinguish` labels)."""
    variants = [sweep_variant(r) for r in runs]
    if not runs or None in variants:
        return False
    settings: dict[str, set[str]] = defaultdict(set)
    for r, v in zip(runs, variants):
        settings[v].add(repr(sorted((k, r.config.get(k)) for k in set(r.config) - NOT_A_SETTING - {"env"}
                                    | {"algo", "reward", "expert_capacity"})))
    if any(len(s) > 1 for s in settings.values()):  # one name, two settings: cells of different experiments
        return False
    for r, v in zip(runs, variants):
        r.algo = v
    return True


def _applies(key: str, run: RunCurve) -> bool:
    """Settings that only some algorithms use: other runs carry their defaults, which say nothing about them."""
    spec = ALGORITHMS.get(run.config.get("algo", ""))
    return key not in ALGORITHM_OPTIONS or (spec is not None and key in spec.options)


def differing_settings(runs: list[RunCurve], excluded: set[str]) -> list[str]:
    """The config keys, less `excluded`, whose values differ between the runs they apply to."""
    keys = sorted({k for r in runs for k in r.config} - excluded)
    return [k for k in keys if len({repr(r.config.get(k)) for r in runs if _applies(k, r)}) > 1]


def distinguish(runs: list[RunCurve]) -> list[RunCurve]:
    """Add to each label the settings that differ between `runs` (so different settings never share a curve)."""
    differing = differing_settings(runs, NOT_A_SETTING)
    for r in runs:
        extra = " ".join(f"{k}={r.config.get(k) if r.config.get(k) != '' else 'none'}" for k in differing if _applies(k, r))
        r.algo = f"{r.algo} {extra}" if extra else r.algo
    return runs


def label_key(label: str) -> list:
    """Groups' order everywhere: numbers in a name by value, so an ablation reads silcr-M1000,
    silcr-M2000, silcr-M10000 rather than in character order."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", label)]


def group_colours(labels: set[str]) -> dict[str, str]:
    """One colour per group, the same in every panel (even where a panel lacks some group) and in
    `--stats rliable`'s interval figure: matplotlib's cycle in the groups' sorted order."""
    import matplotlib.pyplot as plt

    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return {label: palette[i % len(palette)] for i, label in enumerate(sorted(labels, key=label_key))}


def group(runs: list[RunCurve]) -> dict[str, dict[str, list[RunCurve]]]:
    out: dict[str, dict[str, list[RunCurve]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        out[r.env][r.algo].append(r)
    return out


def _on_grid(runs: list[RunCurve], points: int = 100) -> tuple[np.ndarray, np.ndarray]:
    end = min(r.steps[-1] for r in runs)
    grid = np.linspace(0.0, end, points) if end > 0 else np.zeros(1)
    return grid, np.stack([np.interp(grid, r.steps, r.returns) for r in runs])


def mean_curve(runs: list[RunCurve], points: int = 100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    grid, ys = _on_grid(runs, points)
    return grid, ys.mean(0), ys.std(0)


def _steps_tick(value: float, _position: int) -> str:
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:g}{suffix}"
    return f"{value:g}"


def panels(count: int):
    """A figure with one panel per task, three to a row; the grid's unused panels hidden."""
    import matplotlib.pyplot as plt

    cols = min(3, count)
    rows = (count + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False)
    for ax in list(axes.flat)[count:]:
        ax.set_visible(False)
    return fig, list(axes.flat)[:count]


def plot(runs: list[RunCurve], out: Path, expert: float | None = None, title: str = "", ylabel: str = "evaluation return (dense)",
         logy: bool = False):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.ticker import FuncFormatter

    groups = group(runs)
    envs = sorted(groups)
    colour = group_colours({r.algo for r in runs})
    fig, axes = panels(len(envs))
    for ax, env in zip(axes, envs):
        for algo in sorted(groups[env], key=label_key):
            seeds = groups[env][algo]
            label = f"{algo} ({len(seeds)} seed{'s' if len(seeds) > 1 else ''})"
            if logy:  # values over orders of magnitude: the median, and the range over seeds
                x, ys = _on_grid(seeds)
                ax.plot(x, np.median(ys, 0), label=label, color=colour[algo])
                ax.fill_between(x, ys.min(0), ys.max(0), color=colour[algo], alpha=0.2)
            else:
                x, m, sd = mean_curve(seeds)
                ax.plot(x, m, label=label, color=colour[algo])
                ax.fill_between(x, m - sd, m + sd, color=colour[algo], alpha=0.2)
        if expert is not None:
            ax.axhline(expert, linestyle="--", color="black", label="expert")
        ax.set_title(env)
        ax.set_xlabel("environment steps")
        ax.xaxis.set_major_formatter(FuncFormatter(_steps_tick))  # "200k", not "200000" running into its neighbour
        ax.set_ylabel(ylabel)
        if logy:
            positive = all((r.returns > 0).all() for seeds in groups[env].values() for r in seeds)
            ax.set_yscale("log" if positive else "symlog")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    if out.suffix == ".png":
        fig.savefig(out.with_suffix(".svg"))
    return fig


def final_value(run: RunCurve, evals: int = 1) -> float:
    """A run's final value: the mean of its last `evals` rows (1: the last evaluation)."""
    return float(np.mean(run.returns[-evals:]))


def final_name(metric: str, evals: int) -> str:
    rows = "evaluations" if metric == "return" else "values"
    return f"final {metric}" if evals == 1 else f"final {metric} (mean of the last {evals} {rows})"


def summary_markdown(runs: list[RunCurve], metric: str = "return", final_evals: int = 1) -> str:
    """Final and best value per (env, label): mean +- std over seeds; whether the critics passed q_bound;
    and the wall time the runs took, per group and in all."""
    watched = any(r.q_watched for r in runs)
    timed = all(r.wall_s is not None for r in runs)
    head = f"| env | algo | seeds | env steps | {final_name(metric, final_evals)} | best {metric} |"
    lines = [head + (" critics past q_bound (first at env steps) |" if watched else "") + (" wall time, h (seeds summed) |" if timed else ""),
             "|---|---|---|---|---|---|" + ("---|" if watched else "") + ("---|" if timed else "")]
    groups = group(runs)
    for env in sorted(groups):
        for algo in sorted(groups[env], key=label_key):
            seeds = groups[env][algo]
            final = np.array([final_value(r, final_evals) for r in seeds])
            best = np.array([r.returns.max() for r in seeds])
            steps = int(min(r.steps[-1] for r in seeds))
            line = (f"| {env} | {algo} | {len(seeds)} | {steps:,} | {final.mean():.1f} ± {final.std():.1f} | "
                    f"{best.mean():.1f} ± {best.std():.1f} |")
            if watched:
                firsts = sorted(int(r.first_past_q_bound) for r in seeds if r.first_past_q_bound is not None)
                line += f" {len(firsts)}/{len(seeds)}" + (f" ({', '.join(f'{f:,}' for f in firsts)})" if firsts else "") + " |"
            if timed:
                line += f" {sum(r.wall_s for r in seeds) / 3600:.2f} |"
            lines.append(line)
    if timed:
        single = sum(bool(r.config.get("single_process")) for r in runs)
        cores = ("a `--single-process` run with one torch thread keeps about one core busy" if single == len(runs) else
                 "a distributed run's processes keep several cores busy, so its core-hours are more than its wall time"
                 if single == 0 else
                 f"{single} of the runs are `--single-process` (about one core each with one torch thread), the others "
                 "distributed (several cores each)")
        lines += ["", f"Wall time: {sum(r.wall_s for r in runs) / 3600:.2f} h for the {len(runs)} runs together "
                      f"(each run's processes from start to end, every resumed stretch added and any pause included; "
                      f"{cores})."]
    return "\n".join(lines) + "\n"


def plot_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """`silcr plot RUN_DIR... -o fig.png [--table t.md]`."""
    try:
        runs = [load_run(Path(r), args.metric) for r in args.runs]
        if not label_by_variant(runs):
            runs = distinguish(runs)
    except ValueError as e:
        parser.error(str(e))
    out = Path(args.out)
    if out.suffix not in (".png", ".svg", ".pdf"):
        parser.error(f"-o {args.out}: use a .png, .svg or .pdf file name")
    # Every option is checked before the first file is written.
    if args.final_evals < 1:
        parser.error(f"--final-evals must be >= 1, got {args.final_evals}")
    if args.stats == "rliable":
        from silcr.stats import require_rliable

        try:
            require_rliable()
        except ValueError as e:
            parser.error(str(e))
        labels = {r.algo for r in runs}
        if args.bootstrap_reps < 100:
            parser.error(f"--bootstrap-reps must be >= 100, got {args.bootstrap_reps}")
        for option, value in (("--compare", args.compare), ("--reference", args.reference)):
            if value is not None and value not in labels:
                parser.error(f"{option} {value!r}: no such group (groups: {', '.join(sorted(labels, key=label_key))})")
        if args.against is not None:
            from silcr.stats import setting_values

            try:
                setting_values(runs, args.against)
            except ValueError as e:
                parser.error(str(e))
    elif args.compare or args.reference or args.against:
        parser.error("--compare, --reference and --against go with --stats rliable")
    metric = "return" if args.metric == "eval_return" else args.metric
    plot(runs, out, args.expert, args.title, "evaluation return (dense)" if metric == "return" else args.metric, args.logy)
    table = summary_markdown(runs, metric, args.final_evals)
    if args.stats == "rliable":
        from silcr.stats import against_report, rliable_report

        try:
            table += "\n" + rliable_report(runs, args.compare, args.reference, args.bootstrap_reps,
                                            figure=out.with_name(out.stem + "-stats.png"), final_evals=args.final_evals)
            if args.against is not None:
                table += "\n" + against_report(runs, args.against, args.bootstrap_reps, final_evals=args.final_evals,
                                                figure=out.with_name(f"{out.stem}-against-{args.against}.png"))
        except ValueError as e:
            parser.error(str(e))
    print(table, end="")
    if args.table:
        Path(args.table).write_text(table)
    print(f"wrote {out}" + (f" and {out.with_suffix('.svg')}" if out.suffix == ".png" else ""))
    return 0
