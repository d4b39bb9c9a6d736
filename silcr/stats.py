"""Few-seed statistics for `silcr plot --stats rliable` (Agarwal et al., NeurIPS 2021: rliable).

With 3 seeds a mean +- std says little, so the final returns are summarised the way
rliable recommends, with its own code:

* per task, the interquartile mean (IQM) of the final return over seeds, with a 95%
  stratified bootstrap confidence interval;
* over tasks, the IQM of normalised final returns: 0 is the untrained policy's return
  (every run's first evaluation, averaged per task) and 1 the reference group's final
  return (by default SAC with the dense reward at the same budget), so tasks of
  different scales can be pooled;
* the probability of improvement P(X > Y) of one group over each other, per task and
  over tasks, with its interval: the chance that a run of X beats a run of Y on a task;
* with `--against SETTING`, the final return against one numeric setting (an ablation's
  axis, such as `expert_capacity`): per task, the IQM and its interval at each value,
  one line per family of runs that share every other setting.

A run's final return is its last evaluation (the mean over `--eval-episodes` episodes
of the deterministic policy), or with `--final-evals K` the mean of its last K. rliable
is an optional dependency (`pip install rliable`, or the `stats` extra).
"""

from __future__ import annotations

import warnings
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from silcr.common.run_records import (NOT_A_SETTING, RunCurve, applies, base_label, differing_settings, final_name,
                                      final_value, group, label_key)
from silcr.figures import group_colours, panels

#: Bootstrap replications: enough for stable 95% intervals at a few seeds, and fast.
REPS = 2000


def require_rliable():
    try:
        from rliable import library as rly
        from rliable import metrics
    except ImportError:
        raise ValueError("--stats rliable needs the rliable package: pip install rliable (or silcr[stats])") from None
    return rly, metrics


@contextmanager
def quiet_bootstrap():
    """rliable hands `random_state` to arch's bootstrap, which warns on every call that the
    argument is deprecated: a line per estimate on the user's screen that says nothing about
    their runs. The draws are the same either way."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=FutureWarning, module=r"arch\.")
        yield


def _ci(estimate: float, interval: np.ndarray, runs: int = 2) -> str:
    """A bootstrap over one run draws that run every time, so its "interval" is a point:
    written as the one value it is, not as an interval that claims certainty."""
    if runs < 2:
        return f"{estimate:,.2f} (one seed: no interval)"
    return f"{estimate:,.2f} [{interval[0]:,.2f}, {interval[1]:,.2f}]"


def _tasks(n: int) -> str:
    return f"{n} task{'s' if n != 1 else ''}"


def _pair_ci(estimate: float, interval: np.ndarray, scores: tuple[np.ndarray, np.ndarray],
             names: tuple[str, str]) -> str:
    """P(X > Y) with one side a single seed: the interval then resamples the other side only."""
    runs = (len(scores[0]), len(scores[1]))
    text = _ci(estimate, interval, max(runs))
    single = [name for name, n in zip(names, runs) if n < 2]
    if single and max(runs) >= 2:
        other = names[1 - names.index(single[0])]
        text += f" ({single[0]}: one seed; the interval resamples {other}'s runs only)"
    return text


def _final(runs: list[RunCurve], evals: int) -> np.ndarray:
    return np.array([final_value(r, evals) for r in runs], np.float64)


def _iqm(metrics):
    """rliable's interquartile mean in the shape its bootstrap wants (an array of estimates)."""
    return lambda scores: np.array([metrics.aggregate_iqm(scores)])


def interval_estimates(rly, scores: dict, func, reps: int, seed: int) -> tuple[dict, dict]:
    """rliable's interval estimates, one key at a time, each from the same draws. rliable's
    StratifiedBootstrap takes `random_state` but draws its indices from NumPy's global generator
    (`np.random.choice`), so without this an interval would depend on every estimate made before
    it in the process (which tasks and groups were plotted together). The global generator is
    seeded for each key and given back its state after."""
    points, intervals = {}, {}
    for key, value in scores.items():
        state = np.random.get_state()
        np.random.seed(seed)
        try:
            point, interval = rly.get_interval_estimates({key: value}, func, reps=reps,
                                                         random_state=np.random.RandomState(seed))
        finally:
            np.random.set_state(state)
        points[key], intervals[key] = point[key], interval[key]
    return points, intervals


def default_reference(labels: set[str]) -> str | None:
    return next((label for label in sorted(labels) if label.startswith("sac-dense")), None)


def rliable_report(runs: list[RunCurve], compare: str | None = None, reference: str | None = None,
                   reps: int = REPS, seed: int = 0, figure: Path | None = None, final_evals: int = 1) -> str:
    """The Markdown report (and, with `figure`, an interval plot) described in the module docstring."""
    with quiet_bootstrap():
        return _report(runs, compare, reference, reps, seed, figure, final_evals)


def _report(runs: list[RunCurve], compare: str | None, reference: str | None, reps: int, seed: int,
            figure: Path | None, final_evals: int) -> str:
    rly, metrics = require_rliable()
    groups = group(runs)
    envs = sorted(groups)
    labels = sorted({label for env in envs for label in groups[env]}, key=label_key)
    iqm = _iqm(metrics)
    lines = [f"{final_name('return', final_evals).capitalize()}: interquartile mean over seeds, 95% stratified "
             f"bootstrap interval ({reps} replications, "
             f"rliable).", "", "| env | group | seeds | IQM [95% CI] |", "|---|---|---|---|"]
    per_task: dict[str, dict[str, tuple[float, np.ndarray]]] = defaultdict(dict)
    for env in envs:
        for label in sorted(groups[env], key=label_key):
            scores = _final(groups[env][label], final_evals)
            point, interval = interval_estimates(rly, {label: scores[:, None]}, iqm, reps, seed)
            per_task[env][label] = (float(point[label][0]), interval[label][:, 0])
            lines.append(f"| {env} | {label} | {len(scores)} | {_ci(*per_task[env][label], len(scores))} |")

    reference = reference or default_reference(set(labels))
    complete = [label for label in labels if all(label in groups[env] for env in envs)]
    normalised: dict[str, np.ndarray] = {}
    if reference is not None and reference in complete:
        lines += ["", f"Over {_tasks(len(envs))}: final return normalised per task, 0 = the untrained policy "
                      f"(first evaluation, mean over every run of the task), 1 = {reference}'s final return "
                      f"(its mean over seeds). IQM [95% CI] over all runs of all tasks.", "",
                  "| group | runs per task | normalised IQM [95% CI] |", "|---|---|---|"]
        for label in complete:
            columns = []
            for env in envs:
                zero = float(np.mean([r.returns[0] for g in groups[env].values() for r in g]))
                one = float(_final(groups[env][reference], final_evals).mean())
                columns.append((_final(groups[env][label], final_evals) - zero) / (one - zero if one != zero else 1.0))
            n = min(len(c) for c in columns)  # rliable wants runs x tasks: the fewest seeds any task has
            normalised[label] = np.stack([c[:n] for c in columns], axis=1)
        points, intervals = interval_estimates(rly, normalised, iqm, reps, seed)
        for label in complete:
            runs_per_task = normalised[label].shape[0]
            lines.append(f"| {label} | {runs_per_task} | {_ci(points[label][0], intervals[label][:, 0], runs_per_task)} |")
    elif reference is not None:
        lines += ["", f"(No aggregate over tasks: the reference {reference} is missing on some task.)"]

    if compare is not None:
        others = [label for label in labels if label != compare]
        lines += ["", f"Probability of improvement P({compare} > Y): the chance that a run of {compare} ends above a "
                      f"run of Y on the same task, 95% interval.", "",
                  "| env | Y | P(X > Y) [95% CI] |", "|---|---|---|"]
        for env in envs:
            if compare not in groups[env]:
                continue
            for other in others:
                if other not in groups[env]:
                    continue
                pair = {other: (_final(groups[env][compare], final_evals)[:, None],
                                _final(groups[env][other], final_evals)[:, None])}
                points, intervals = interval_estimates(rly, pair, metrics.probability_of_improvement, reps, seed)
                lines.append(f"| {env} | {other} | "
                             f"{_pair_ci(float(points[other]), intervals[other][:, 0], pair[other], (compare, other))} |")
        if compare in normalised:
            for other in others:
                if other in normalised:
                    pair = {other: (normalised[compare], normalised[other])}
                    points, intervals = interval_estimates(rly, pair, metrics.probability_of_improvement, reps, seed)
                    lines.append(f"| all {_tasks(len(envs))} | {other} | "
                                 f"{_pair_ci(float(points[other]), intervals[other][:, 0], pair[other], (compare, other))} |")
    if figure is not None:
        seeds = {env: {label: len(runs_) for label, runs_ in groups[env].items()} for env in envs}
        _interval_figure(per_task, seeds, figure)
        if normalised:
            profiles = figure.with_name(figure.stem.removesuffix("-stats") + "-profiles.png")
            at = _profile_figure(rly, normalised, profiles, reps, seed)
            lines += ["", f"Performance profiles (rliable: the share of runs whose normalised final return is above "
                          f"tau, 95% bands) in {profiles.name}; the share above tau = 0.5 and 1:", "",
                      "| group | runs | share > 0.5 | share > 1 |", "|---|---|---|---|"]
            lines += [f"| {label} | {normalised[label].size} | {half:.2f} | {one:.2f} |" for label, (half, one) in at.items()]
    return "\n".join(lines) + "\n"


def _profile_figure(rly, normalised: dict[str, np.ndarray], out: Path, reps: int, seed: int) -> dict[str, tuple]:
    """rliable's performance profiles of the normalised final returns, all tasks' runs together; each group's
    share of runs above tau = 0.5 and 1, for the table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from rliable import plot_utils

    labels = sorted(normalised, key=label_key)
    high = max(1.5, float(max(np.max(v) for v in normalised.values())))
    taus = np.linspace(min(0.0, float(min(np.min(v) for v in normalised.values()))), high, 101)
    state = np.random.get_state()
    np.random.seed(seed)  # rliable's bootstrap draws from the global generator (see interval_estimates)
    try:
        profiles, bands = rly.create_performance_profile({k: normalised[k] for k in labels}, taus, reps=reps)
    finally:
        np.random.set_state(state)
    colour = group_colours(set(labels))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    plot_utils.plot_performance_profiles(profiles, taus, performance_profile_cis=bands, ax=ax,
                                         colors={k: colour[k] for k in labels},
                                         xlabel="normalised final return (tau)", ylabel="fraction of runs above tau")
    from matplotlib.lines import Line2D

    ax.legend([Line2D([], [], color=colour[k]) for k in labels], labels, loc="upper right", fontsize="small")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return {k: (float((normalised[k] > 0.5).mean()), float((normalised[k] > 1.0).mean())) for k in labels}


def figure_labels(seeds: dict[str, dict[str, int]], labels: list[str]) -> dict[str, str]:
    """The interval figure's name for each group (`seeds`: task -> group -> its runs there). A one-seed
    group's interval has no width, and a bar of no width reads as a certain value, so its name says
    why. The seeds are counted, not read off the bar: three seeds that all score 0 have no width
    either, and they are not one seed."""
    return {label: f"{label} (one seed)" if all(seeds[env].get(label, 0) <= 1 for env in seeds) else label
            for label in labels}


def _interval_figure(per_task: dict[str, dict[str, tuple[float, np.ndarray]]], seeds: dict[str, dict[str, int]],
                     out: Path) -> None:
    """rliable's interval plot: one panel per task, one bar per group present on every task."""
    import matplotlib

    matplotlib.use("Agg")
    from rliable import plot_utils

    envs = sorted(per_task)
    labels = sorted(set.intersection(*(set(per_task[env]) for env in envs)), key=label_key)
    if not labels:
        return
    shown = figure_labels(seeds, labels)
    points = {shown[label]: np.array([per_task[env][label][0] for env in envs]) for label in labels}
    intervals = {shown[label]: np.stack([per_task[env][label][1] for env in envs], axis=1) for label in labels}
    colour = group_colours({label for env in envs for label in per_task[env]})  # as in the curves' figure
    row_height = 0.5
    # rliable places the x label at a fixed fraction of the figure's height (-0.1), which lands on
    # the tick labels of a figure a few rows high; 0.45 inches below the axes clears them.
    fig, axes = plot_utils.plot_interval_estimates(points, intervals, envs, [shown[label] for label in labels],
                                                   colors={shown[label]: colour[label] for label in labels},
                                                   xlabel="final return: IQM, 95% CI", row_height=row_height,
                                                   xlabel_y_coordinate=-0.45 / (row_height * len(labels)))
    for ax in np.atleast_1d(axes):
        # A one-seed group's bar has no width: at the axis' end it was cut in half. Bars hold the
        # axis to their ends (sticky edges), so the margin needs them released.
        ax.use_sticky_edges = False
        ax.margins(x=0.03)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120, bbox_inches="tight")


#: Settings read relative to the run's budget: an ablation over M reads as budget / M, the
#: paper's axis (2M steps with M from 1e4 to 1e6 is budget/M from 200 to 2).
PER_BUDGET = {"expert_capacity": "M"}


def setting_values(runs: list[RunCurve], setting: str) -> list[float]:
    """Each run's value of `setting`, which must be a number in every run's config.toml."""
    values = []
    for r in runs:
        value = r.config.get(setting)
        if value is None:
            raise ValueError(f"--against {setting}: no such setting in {r.path / 'config.toml'}")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"--against {setting}: {r.path} has {setting} = {value!r}, not a number "
                             "(give a numeric setting of config.toml, e.g. expert_capacity or tau)")
        values.append(float(value))
    return values


def families(runs: list[RunCurve], setting: str) -> list[str]:
    """Each run's line in the --against figure: its algorithm plus every other setting that differs
    between the runs (as curve labels are made), so only runs that differ in `setting` alone share a line."""
    # Curve labels name M and demos; total_steps too here: a final return at another budget is
    # another experiment, not another seed. The algorithm and its reward are in base_label already.
    label_settings = {"expert_capacity", "demos", "total_steps"}
    differing = differing_settings(runs, (NOT_A_SETTING - label_settings) | {setting})
    return [" ".join([base_label(r.config)] + [f"{k}={r.config.get(k)}" for k in differing if applies(k, r)])
            for r in runs]


def against_report(runs: list[RunCurve], setting: str, reps: int = REPS, seed: int = 0, figure: Path | None = None,
                   final_evals: int = 1) -> str:
    """The final return against `setting`: a Markdown table and, with `figure`, one panel per task."""
    with quiet_bootstrap():
        return _against(runs, setting, reps, seed, figure, final_evals)


def _against(runs: list[RunCurve], setting: str, reps: int, seed: int, figure: Path | None, final_evals: int) -> str:
    rly, metrics = require_rliable()
    iqm = _iqm(metrics)
    values = setting_values(runs, setting)
    cells: dict[str, dict[str, dict[float, list[RunCurve]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r, family, value in zip(runs, families(runs, setting), values):
        cells[r.env][family][value].append(r)
    budgets = {r.config["total_steps"] for r in runs}  # always there: load_run fills defaults in
    ratio = PER_BUDGET.get(setting) if min(values) > 0 else None
    budget = float(next(iter(budgets))) if ratio and len(budgets) == 1 else 0.0  # the figure's top axis
    lines = [f"{final_name('return', final_evals).capitalize()} against {setting}: interquartile mean over the seeds "
             f"at each value, 95% stratified bootstrap interval ({reps} replications, rliable).", "",
             f"| env | line | {setting} |" + (f" budget / {ratio} |" if ratio else "") + " seeds | IQM [95% CI] |",
             "|---|---|---|" + ("---|" if ratio else "") + "---|---|"]
    estimates: dict[str, dict[str, list[tuple[float, float, np.ndarray, np.ndarray]]]] = defaultdict(dict)
    for env in sorted(cells):
        for family in sorted(cells[env], key=label_key):
            estimates[env][family] = []
            for value in sorted(cells[env][family]):
                scores = _final(cells[env][family][value], final_evals)
                point, interval = interval_estimates(rly, {"x": scores[:, None]}, iqm, reps, seed)
                estimates[env][family].append((value, float(point["x"][0]), interval["x"][:, 0], scores))
                own_budget = float(cells[env][family][value][0].config["total_steps"]) if ratio else 0.0  # one per family
                lines.append(f"| {env} | {family} | {value:g} |" + (f" {own_budget / value:g} |" if ratio else "")
                             + f" {len(scores)} | {_ci(float(point['x'][0]), interval['x'][:, 0], len(scores))} |")
    if figure is not None:
        _against_figure(estimates, setting, figure, budget or None, ratio)
    return "\n".join(lines) + "\n"


def _against_figure(estimates: dict[str, dict[str, list[tuple[float, float, np.ndarray, np.ndarray]]]], setting: str,
                    out: Path, budget: float | None, ratio: str | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    envs = sorted(estimates)
    colour = group_colours({family for env in envs for family in estimates[env]})
    fig, axes = panels(len(envs))
    for ax, env in zip(axes, envs):
        xs = [point[0] for points in estimates[env].values() for point in points]
        logx = min(xs) > 0 and max(xs) >= 10 * min(xs)  # an ablation over orders of magnitude
        beside = (lambda v: v * 1.06) if logx else (lambda v: v + 0.015 * (max(xs) - min(xs) or 1.0))  # noqa: E731
        for family in sorted(estimates[env], key=label_key):
            x, y, ci = (np.array(column, dtype=np.float64) for column in list(zip(*estimates[env][family]))[:3])
            ax.errorbar(x, y, yerr=np.abs(ci.T - y), marker="o", capsize=3, color=colour[family], label=family)
            for value, _, _, scores in estimates[env][family]:  # each seed too, just beside its interval
                ax.scatter(np.full(len(scores), beside(value)), scores, s=14, marker="x", color=colour[family], alpha=0.6)
        if logx:
            ax.set_xscale("log")
        if budget:
            top = ax.secondary_xaxis("top", functions=(lambda v: budget / np.maximum(v, 1e-12),
                                                       lambda v: budget / np.maximum(v, 1e-12)))
            shown = sorted(set(xs))
            top.set_xticks([budget / x for x in shown], [f"{budget / x:g}" for x in shown])  # at the points only
            top.set_xlabel(f"budget / {ratio}")
        ax.set_title(env)
        ax.set_xlabel(setting)
        ax.set_ylabel("final return: IQM, 95% CI (x: each seed)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
