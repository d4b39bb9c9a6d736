"""Run records as `silcr plot` reads them: a run directory's config.toml and progress.csv, its label, its group.

A run directory holds `config.toml` (env, algo, seed) and `progress.csv`
(`env_steps`, `eval_return`). Runs of the same (env, label) are seeds of one
curve. A label is the algorithm (with SAC's reward and a non-default M), plus every
setting that differs between the runs read together (`tau=0.005`,
`expert_admission=recent`, ...), so that runs of different settings are never
pooled. Cells of `silcr sweep` (directories named `<variant>_<task>_s<seed>`) are
labelled by their experiment's variant names instead, when each name stands for one
set of settings; cells of one variant from several studies (runs directories) are
pooled as seeds of one configuration only when every setting matches, and refused
otherwise (`check_pooling`). The figures (`silcr.plot`) and the statistics
(`silcr.stats`) both read runs through this module.
"""

from __future__ import annotations

import csv
import re
import tomllib
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from silcr.common import run_layout
from silcr.common.algorithms import ALGORITHM_OPTIONS, ALGORITHMS
from silcr.common.config import Config, saved_options


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
                 "final_eval_episodes",
                 "total_steps"}


_DEFAULTS = Config(run="defaults").to_dict()


def base_label(cfg: dict) -> str:
    """The algorithm's name; only the algorithms that learn from the env's reward say which one they had."""
    algo = cfg.get("algo", "?")
    spec = ALGORITHMS.get(algo)
    return f"{algo}-{cfg.get('reward', '')}" if spec is not None and spec.uses_env_reward else algo


def load_run(path: Path, metric: str = "eval_return") -> RunCurve:
    path = Path(path)
    if path.is_file() and path.name in (run_layout.PROGRESS, run_layout.CONFIG):
        path = path.parent  # what users type: runs/<run>/progress.csv stands for its run directory
    try:
        # A run from before an option existed did what the option did when it was added (options
        # are added keeping the behaviour they replace), so a missing key reads as that value.
        cfg = saved_options(run_layout.config(path))
        with open(run_layout.progress(path), newline="") as f:
            all_rows = list(csv.DictReader(f))
    except FileNotFoundError as e:
        raise ValueError(f"{path} is not a run directory (missing {Path(e.filename).name})") from None
    except NotADirectoryError:
        raise ValueError(f"{path} is not a run directory (give the directory holding config.toml and "
                         f"progress.csv)") from None
    except (tomllib.TOMLDecodeError, csv.Error, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: unreadable run files ({e})") from None
    # `a/b` is one column over another, e.g. q_max/q_bound: how close the critics are to the soft-Q bound.
    columns = metric.split("/") if metric.count("/") == 1 else [metric]
    rows = [r for r in all_rows if all(r.get(c) not in (None, "") for c in columns)]
    if not rows:
        raise ValueError(f"{path}: progress.csv has no values of {metric} yet")
    try:
        steps = np.array([float(r["env_steps"]) for r in rows])
        values = np.array([float(r[columns[0]]) for r in rows])
        if len(columns) == 2:
            values = values / np.array([float(r[columns[1]]) for r in rows])
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


#: Config keys that say where or how a cell ran, not what it learned: cells of one variant from
#: several studies may differ in these and still be seeds of one configuration.
NOT_A_RESULT = {"run", "runs_dir", "seed", "resume", "connect", "listen", "zenoh_mode", "actor_zenoh_mode", "zenoh_config",
                "zenoh_listen", "device", "torch_threads", "stats_interval", "checkpoint_interval",
                "buffer_checkpoint_interval", "max_restarts", "actor_id", "weights_wait"}


def check_pooling(runs: list[RunCurve]) -> None:
    """Refuse (ValueError, one line) to pool sweep cells of one variant and task from several studies (runs
    directories) unless they are one configuration: every setting but where and how they ran the same, and
    no seed twice. Cells that pass are pooled as seeds of one group (ten seeds from two studies, say)."""
    cells: dict[tuple[str, str], list[RunCurve]] = defaultdict(list)
    for r in runs:
        variant = sweep_variant(r)
        if variant is not None:
            cells[(r.env, variant)].append(r)
    for (env, variant), group_runs in sorted(cells.items()):
        studies = sorted({str(r.path.resolve().parent) for r in group_runs})
        if len(studies) < 2:
            continue
        where = f"cells {variant}_{env}_s* from {len(studies)} studies ({', '.join(studies)})"
        seeds = [r.seed for r in group_runs]
        twice = sorted({s for s in seeds if seeds.count(s) > 1})
        if twice:
            raise ValueError(f"{where}: seed {', '.join(map(str, twice))} appears in more than one; a seed is pooled once")
        keys = sorted({k for r in group_runs for k in r.config} - NOT_A_RESULT)
        differ = {k: sorted({repr(r.config.get(k)) for r in group_runs}) for k in keys}
        differ = {k: v for k, v in differ.items() if len(v) > 1}
        if differ:
            shown = "; ".join(f"{k}: {' vs '.join(v)}" for k, v in differ.items())
            raise ValueError(f"{where} differ in {shown}: they are not one configuration and are not pooled "
                             f"(plot them apart, or give the variants different names)")


def applies(key: str, run: RunCurve) -> bool:
    """Settings that only some algorithms use: other runs carry their defaults, which say nothing about them."""
    spec = ALGORITHMS.get(run.config.get("algo", ""))
    return key not in ALGORITHM_OPTIONS or (spec is not None and key in spec.options)


def differing_settings(runs: list[RunCurve], excluded: set[str]) -> list[str]:
    """The config keys, less `excluded`, whose values differ between the runs they apply to."""
    keys = sorted({k for r in runs for k in r.config} - excluded)
    return [k for k in keys if len({repr(r.config.get(k)) for r in runs if applies(k, r)}) > 1]


def distinguish(runs: list[RunCurve]) -> list[RunCurve]:
    """Add to each label the settings that differ between `runs` (so different settings never share a curve)."""
    differing = differing_settings(runs, NOT_A_SETTING)
    for r in runs:
        extra = " ".join(f"{k}={r.config.get(k) if r.config.get(k) != '' else 'none'}" for k in differing if applies(k, r))
        r.algo = f"{r.algo} {extra}" if extra else r.algo
    return runs


def label_key(label: str) -> list:
    """Groups' order everywhere: numbers in a name by value, so an ablation reads silcr-M1000,
    silcr-M2000, silcr-M10000 rather than in character order."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", label)]


def group(runs: list[RunCurve]) -> dict[str, dict[str, list[RunCurve]]]:
    out: dict[str, dict[str, list[RunCurve]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        out[r.env][r.algo].append(r)
    return out


def final_value(run: RunCurve, evals: int = 1) -> float:
    """A run's final value: the mean of its last `evals` rows (1: the last evaluation)."""
    return float(np.mean(run.returns[-evals:]))


def final_name(metric: str, evals: int) -> str:
    rows = "evaluations" if metric == "return" else "values"
    return f"final {metric}" if evals == 1 else f"final {metric} (mean of the last {evals} {rows})"
