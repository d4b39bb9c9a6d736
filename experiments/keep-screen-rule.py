"""The keep screen's decision rule (RESULTS.md, "Keeping what D_E holds"), computed from the records, so that
its answer is one command and the same every time it is asked.

For each arm against the control (the critics-check study's `silcr-layernorm-clip` cells, same seeds and
settings), over Walker2d-v5 and Hopper-v5, 3 seeds each:
  1. P(arm > control) with rliable's stratified bootstrap (95%, 2,000 replications), under both final-return
     definitions (the last evaluation; the mean of the last five). Computed as `silcr plot CELLS --stats rliable
     --compare silcr-layernorm-clip` computes P(control > arm), read as 1 - that, as every interim figure was.
  2. The arm helps only if the lower end is above 0.5 under both definitions.
  3. Per task: the median keep ratio at the end (mean of the last five evaluations over D_E's lowest return at
     the end), the evaluation length and forward velocity of the last five.
  4. The arm for Humanoid: among arms with P above 0.5 under both definitions, the highest P on the last five
     (two within 0.05 tie and both go); if none, the arm with the highest median keep ratio on Walker2d, called a
     guess. Given only when every arm's six cells are in.
  5. Walker2d's goal, keep ratio at or above 0.8, per arm: in how many seeds it is met.
Only finished cells count (those with the sweep's sweep-done.json).

    python experiments/keep-screen-rule.py
    python experiments/keep-screen-rule.py --screen /work/study/runs/keep-screen     # cells not yet collected
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from silcr.common.run_records import load_run
from silcr.stats import REPS, interval_estimates, quiet_bootstrap, require_rliable

REPO = Path(__file__).resolve().parent.parent
CONTROL = "silcr-layernorm-clip"
ARMS = ("silcr-table-i", "silcr-bc", "silcr-utd2", "silcr-de4x", "silcr-lowent")
TASKS = ("Walker2d-v5", "Hopper-v5")
SEEDS = (0, 1, 2)
LAST = 5  # "the last five evaluations"
TIE = 0.05
GOAL_KEEP = 0.8  # the goal for Walker2d at 200k


@dataclass
class Cell:
    last: float  # the last evaluation's return
    last_five: float  # the mean of the last five evaluations' returns
    keep: float  # last_five over D_E's lowest return at the end
    length: float  # mean evaluation length of the last five
    velocity: float | None  # mean forward velocity of the last five (None: the run predates the column)
    wall_s: float


def _column(path: Path, metric: str) -> np.ndarray | None:
    """progress.csv's values of `metric`, resumed stretches' superseded rows left out; None when it has none."""
    try:
        return load_run(path, metric).returns
    except ValueError:
        return None


def read_cell(path: Path) -> Cell | None:
    """A finished cell's figures; None while it has no done marker; ValueError naming a record it cannot read."""
    if not (path / "sweep-done.json").is_file():
        return None
    run = load_run(path)
    lowest, lengths = _column(path, "expert_min_return"), _column(path, "eval_length")
    if lowest is None or lengths is None:
        raise ValueError(f"{path}: progress.csv has no expert_min_return or eval_length values")
    velocity = _column(path, "eval_x_velocity")  # None: a run from before the column
    last_five = float(np.mean(run.returns[-LAST:]))
    return Cell(float(run.returns[-1]), last_five, last_five / lowest[-1], float(np.mean(lengths[-LAST:])),
                None if velocity is None else float(np.mean(velocity[-LAST:])), run.wall_s or 0.0)


def cells(root: Path, label: str) -> dict[str, list[Cell]]:
    """Finished cells per task, in seed order; a task with a missing seed lists only those found."""
    found = {task: [read_cell(root / f"{label}_{task}_s{seed}") for seed in SEEDS] for task in TASKS}
    return {task: [c for c in found[task] if c is not None] for task in TASKS}


def p_over_control(rly, metrics, control: dict[str, list[Cell]], arm: dict[str, list[Cell]], field: str):
    """P(arm > control) over both tasks with its interval, from P(control > arm) as `silcr plot` computes it (tasks
    in its order, sorted by name: the stratified bootstrap draws task by task, so the order changes the interval)."""
    scores = [np.array([[getattr(c, field) for c in group[task]] for task in sorted(TASKS)]).T for group in (control, arm)]
    points, intervals = interval_estimates(rly, {"p": tuple(scores)}, metrics.probability_of_improvement, REPS, seed=0)
    low, high = intervals["p"][:, 0]
    return 1.0 - float(points["p"]), 1.0 - float(high), 1.0 - float(low)


def _span(values: list[float], fmt: str) -> str:
    low, high = min(values), max(values)
    return format(low, fmt) if low == high else f"{low:{fmt}}{' to ' if low < 0 else '-'}{high:{fmt}}"


def report(control_root: Path, screen_root: Path) -> str:
    rly, metrics = require_rliable()
    control = cells(control_root, CONTROL)
    if any(len(control[task]) != len(SEEDS) for task in TASKS):
        raise SystemExit(f"keep-screen-rule: the control's cells are not all in {control_root}")
    arms = {arm: cells(screen_root, arm) for arm in ARMS}
    complete = [arm for arm in ARMS if all(len(arms[arm][task]) == len(SEEDS) for task in TASKS)]
    lines = ["Items 1, 2 and 5: P(arm > control) over both tasks, 3 seeds each (rliable, 95% stratified bootstrap, "
             f"{REPS} replications).", "",
             "| arm | P, last evaluation | P, mean of the last five | helps (item 2) | Walker2d keep >= 0.8 | wall time of "
             "its finished cells |",
             "|---|---|---|---|---|---|"]
    p = {}
    for arm in ARMS:
        hours = sum(c.wall_s for task in TASKS for c in arms[arm][task]) / 3600
        if arm not in complete:
            done = sum(len(arms[arm][task]) for task in TASKS)
            lines.append(f"| {arm} | {done} of {len(TASKS) * len(SEEDS)} cells finished | | | | {hours:.2f} h |")
            continue
        with quiet_bootstrap():
            p[arm] = {field: p_over_control(rly, metrics, control, arms[arm], field) for field in ("last", "last_five")}
        helps = all(p[arm][field][1] > 0.5 for field in p[arm])
        walker = [c.keep for c in arms[arm]["Walker2d-v5"]]
        lines.append(f"| {arm} | " + " | ".join(f"{v:.2f} [{lo:.2f}, {hi:.2f}]" for v, lo, hi in p[arm].values())
                     + f" | {'yes' if helps else 'no (undecided)'} | {sum(k >= GOAL_KEEP for k in walker)} of "
                       f"{len(walker)} seeds | {hours:.2f} h |")

    lines += ["", "Item 3, per task: the mean of the last five evaluations per seed, the median keep ratio, and the "
                  "span over seeds of the last five's mean evaluation length and forward velocity (m/s).", "",
              "| task | group | seeds | mean of the last five, per seed | median keep ratio | length | velocity |",
              "|---|---|---|---|---|---|---|"]
    for task in TASKS:
        for label, group in [(CONTROL + " (control)", control)] + [(arm, arms[arm]) for arm in ARMS]:
            found = group[task]
            if not found:
                continue
            velocities = [c.velocity for c in found if c.velocity is not None]
            lines.append(f"| {task} | {label} | {len(found)} | {', '.join(f'{c.last_five:,.0f}' for c in found)} | "
                         f"{np.median([c.keep for c in found]):.2f} | {_span([c.length for c in found], ',.0f')} | "
                         f"{_span(velocities, '.2f') if velocities else '-'} |")

    lines += ["", "Item 4, the arm for Humanoid: " + choose(p, arms, complete)]
    return "\n".join(lines) + "\n"


def choose(p: dict, arms: dict, complete: list[str]) -> str:
    if len(complete) < len(ARMS):
        return f"waits for every arm's cells ({len(complete)} of {len(ARMS)} arms complete)."
    above = sorted((arm for arm in ARMS if all(p[arm][field][0] > 0.5 for field in p[arm])),
                   key=lambda arm: -p[arm]["last_five"][0])
    if above:
        best = p[above[0]]["last_five"][0]
        chosen = [arm for arm in above if best - p[arm]["last_five"][0] <= TIE]
        return " and ".join(chosen) + " (P above 0.5 under both definitions" + (", tied within 0.05)." if len(chosen) > 1
                                                                               else ", the highest on the last five).")
    guess = max(ARMS, key=lambda arm: np.median([c.keep for c in arms[arm]["Walker2d-v5"]]))
    return f"{guess}, a guess (no arm's P is above 0.5 under both definitions: the highest median keep ratio on Walker2d)."


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--control", type=Path, default=REPO / "results" / "critics-check" / "runs",
                        help="the control's cells (default: %(default)s)")
    parser.add_argument("--screen", type=Path, default=REPO / "results" / "keep-screen" / "runs",
                        help="the screen's cells (default: %(default)s)")
    args = parser.parse_args()
    for option, root in (("--control", args.control), ("--screen", args.screen)):
        if not root.is_dir():
            parser.error(f"{option} {root}: no such directory")
    try:
        print(report(args.control, args.screen), end="")
    except ValueError as e:  # a record that cannot be read: one line naming it
        parser.error(str(e))


if __name__ == "__main__":
    main()
