"""Training records: `progress.csv` (one row per evaluation) and TensorBoard events."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from silcr.common import run_layout

#: The critics' health at the last update before the row (docs/algorithm.md, "Divergence"):
#: `q_bound_exceeded` counts every update so far whose largest Q passed the soft-Q bound.
DIVERGENCE_COLUMNS = ["q_mean", "q_max", "target_q_mean", "log_pi_mean", "q_bound", "q_bound_exceeded"]
#: GASIL's discriminator at the last update before the row (empty for other algorithms).
GASIL_COLUMNS = ["disc_loss", "disc_acc_expert", "disc_acc_policy", "gasil_reward_mean"]
#: D_E as the buffer service last described it (empty for plain SAC).
EXPERT_COLUMNS = ["expert_transitions", "expert_episodes", "expert_min_return", "expert_max_return"]
#: The mean return and length of the last 100 episodes the actors finished (their sampled actions; the
#: reward as the actors' env pays it), as the buffer service last described them.
ROLLOUT_COLUMNS = ["rollout_return", "rollout_length"]

PROGRESS_COLUMNS = [
    "time",
    "env_steps",
    "updates",
    "policy_version",
    "eval_return",
    "eval_return_std",
    "eval_length",
    "alpha",
    "critic_loss",
    "actor_loss",
    "updates_per_s",
    *DIVERGENCE_COLUMNS,
    *EXPERT_COLUMNS,
    *GASIL_COLUMNS,
    "checkpoints_failed",  # learner checkpoints that could not be written (silcr 0.4)
    "eval_success",  # share of evaluation episodes that reached the goal; empty for tasks without one (silcr 0.5)
    "q_target_clipped",  # share of the last update's TD targets cut at the soft-Q bound (--q-target-clip bound)
    *ROLLOUT_COLUMNS,
    # mean info["x_velocity"] over the evaluation's steps (m/s); empty for envs without it (silcr 0.6)
    "eval_x_velocity",
    # eval_return over D_E's lowest return, once D_E has filled (`evaluations.keep_ratio`; silcr 0.6)
    "keep_ratio",
    "bc_loss",  # the last update's behaviour-cloning loss on D_E rows (--bc-weight above 0)
    "wall_time",  # seconds since the run first started, every resumed stretch added (`time` restarts; silcr 0.6)
]


def read_rows(run_dir: Path) -> list[dict[str, str]]:
    """The rows of a run's progress.csv so far, as written (strings); none when it is missing or unreadable."""
    try:
        with open(run_layout.progress(run_dir), newline="") as f:
            return list(csv.DictReader(f))
    except (OSError, csv.Error):
        return []


def typed(row: dict[str, str]) -> dict[str, Any]:
    """A progress.csv row as the learner wrote it: numbers as numbers (int where whole), "" where empty."""
    out: dict[str, Any] = {}
    for key, text in row.items():
        try:
            out[key] = int(text)
        except (TypeError, ValueError):
            try:
                out[key] = float(text)
            except (TypeError, ValueError):
                out[key] = text
    return out


class ProgressLog:
    def __init__(self, run_dir: Path, resume: bool = False) -> None:
        from torch.utils.tensorboard import SummaryWriter  # imported late: it is slow to import

        run_dir.mkdir(parents=True, exist_ok=True)
        self.csv_path = run_layout.progress(run_dir)
        new = not (resume and self.csv_path.exists())
        if not new:
            _upgrade_header(self.csv_path)
        self._file = open(self.csv_path, "w" if new else "a", newline="")
        self._csv = csv.DictWriter(self._file, fieldnames=PROGRESS_COLUMNS, extrasaction="ignore")
        if new:
            self._csv.writeheader()
            self._file.flush()
        self.tb = SummaryWriter(log_dir=str(run_layout.tensorboard(run_dir)))

    def row(self, values: dict[str, Any]) -> dict[str, Any]:
        """Write one row; the row as written (a column of none, NaN or infinity is empty, ""), by column."""
        clean = {k: ("" if v is None or isinstance(v, float) and not math.isfinite(v) else v)
                 for k, v in values.items() if k in PROGRESS_COLUMNS}
        clean = {k: clean.get(k, "") for k in PROGRESS_COLUMNS}
        self._csv.writerow(clean)
        self._file.flush()
        step = int(values["env_steps"])
        for k in ("eval_return", "eval_return_std", "eval_length", "eval_success", "eval_x_velocity"):
            if k in values and isinstance(values[k], (int, float)):
                self.tb.add_scalar(f"eval/{k.removeprefix('eval_')}", values[k], step)
        if isinstance(values.get("keep_ratio"), (int, float)):
            self.tb.add_scalar("eval/keep_ratio", values["keep_ratio"], step)
        return clean

    def scalars(self, values: dict[str, float], step: int) -> None:
        for k, v in values.items():
            self.tb.add_scalar(k, v, step)

    def close(self) -> None:
        self._file.close()
        self.tb.close()


def _upgrade_header(path: Path) -> None:
    """Rewrite a progress.csv written with other columns (an older silcr) under today's, so resumed rows line up."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames == PROGRESS_COLUMNS:
            return
        rows = list(reader)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=PROGRESS_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
