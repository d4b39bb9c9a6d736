"""Learning curves and summary tables from run directories (`silcr plot`).

Runs are read and grouped by `silcr.common.run_records`: the seeds of one (env, label) are one
curve, their values interpolated onto a common grid of environment steps (up to
the shortest run) and shown as the mean with a +-1 std band. `--metric` plots
another progress.csv column (`expert_min_return`: D_E's lowest return; `q_max`:
the critics' largest Q). `--stats rliable` adds `silcr.stats`' few-seed statistics.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from silcr.common.run_records import (RunCurve, check_pooling, distinguish, final_name, final_value, group,
                                      label_by_variant, label_key, load_run)
from silcr.figures import group_colours, panels, steps_tick


def _on_grid(runs: list[RunCurve], points: int = 100) -> tuple[np.ndarray, np.ndarray]:
    end = min(r.steps[-1] for r in runs)
    grid = np.linspace(0.0, end, points) if end > 0 else np.zeros(1)
    return grid, np.stack([np.interp(grid, r.steps, r.returns) for r in runs])


def mean_curve(runs: list[RunCurve], points: int = 100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    grid, ys = _on_grid(runs, points)
    return grid, ys.mean(0), ys.std(0)


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
        ax.xaxis.set_major_formatter(FuncFormatter(steps_tick))  # "200k", not "200000" running into its neighbour
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
        lines += ["", f"Wall time: {sum(r.wall_s for r in runs) / 3600:.2f} h for "
                      f"{'the run' if len(runs) == 1 else f'the {len(runs)} runs together'} "
                      f"(each run's processes from start to end, every resumed stretch added and any pause included; "
                      f"{cores})."]
    return "\n".join(lines) + "\n"


def plot_command(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """`silcr plot RUN_DIR... -o fig.png [--table t.md]`."""
    try:
        runs = [load_run(Path(r), args.metric) for r in args.runs]
        check_pooling(runs)
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
