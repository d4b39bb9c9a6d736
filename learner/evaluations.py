"""The learner's evaluations: when they fall due, running them, and the progress row each writes.

Every `--eval-interval` env steps (and once before the first update, every curve's baseline,
and once at the end, over `--final-eval-episodes` when given) the current policy plays
`--eval-episodes` episodes with the dense reward
(`evaluate.evaluate`, deterministic unless `--eval-stochastic`, seeded by the evaluation's index),
and one row goes to progress.csv and TensorBoard (`progress.ProgressLog`): the evaluation, the
last update's statistics (`update.Update.stats`) and D_E as the buffer last described it.
The policy of the best evaluation so far is kept as a model file, `<run dir>/best.silcr`
(`silcr eval`, `silcr.SILCR.load`), as Stable-Baselines3's EvalCallback keeps its best model.
Its counters save and restore with the learner checkpoint.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from silcr.common import protocol as P
from silcr.common import run_layout, seeds
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.learner.model_file import write as write_model

from .evaluate import evaluate
from .progress import DIVERGENCE_COLUMNS, EXPERT_COLUMNS, GASIL_COLUMNS, ROLLOUT_COLUMNS, ProgressLog

log = logging.getLogger("learner")


#: The policy of the best evaluation so far, in the run directory.


def keep_ratio(eval_return: float, buffer_meta: dict[str, Any]) -> float | str:
    """How much of what D_E holds the policy keeps: its mean evaluation return over D_E's lowest return. Empty
    until D_E has filled (before that its lowest return is whatever arrived first, not a bar the agent set),
    and where D_E's lowest return is not positive (a ratio to it says nothing)."""
    lowest = buffer_meta.get("expert_min_return")
    if not buffer_meta.get("expert_full") or lowest is None or lowest <= 0:
        return ""
    return eval_return / lowest


class Evaluations:
    COUNTERS = ("next_eval", "evals", "last_eval_return", "best_eval_return")

    def __init__(self, cfg: Config, spec: EnvSpec, run_dir: Path, resumed: bool) -> None:
        self.cfg, self.spec = cfg, spec
        self.next_eval = 0
        self.evals = 0
        self.last_eval_return: float | None = None
        self.best_eval_return: float | None = None
        self.best_path = run_layout.best_model(run_dir)
        self.last_eval_updates = -1  # the update count the last evaluation saw (not checkpointed)
        self.last_row: dict[str, Any] = {}  # the progress row the last evaluation wrote
        run_dir.mkdir(parents=True, exist_ok=True)
        self.progress = ProgressLog(run_dir, resume=resumed)

    def due(self, env_steps: int) -> bool:
        return env_steps >= self.next_eval

    def scheduled(self, env_steps: int) -> None:
        """The next evaluation falls at the next multiple of --eval-interval after `env_steps`."""
        self.next_eval = (env_steps // self.cfg.eval_interval + 1) * self.cfg.eval_interval

    @property
    def final_episodes(self) -> int:
        return self.cfg.final_eval_episodes or self.cfg.eval_episodes

    def final_due(self, updates: int) -> bool:
        """Whether the run's end needs an evaluation of its own: the schedule's last one saw an older policy, or
        fewer episodes than the closing one plays."""
        return updates != self.last_eval_updates or self.final_episodes != self.cfg.eval_episodes

    def run(self, weights: P.Weights, row: dict[str, Any], update_stats: dict[str, float], updates: int,
            buffer_meta: dict[str, Any], final: bool = False) -> None:
        """Evaluate `weights` and write a progress row: `row` (time, counters) with the evaluation, the last
        update's statistics and D_E's description added. `final`: the closing evaluation."""
        episodes = self.final_episodes if final else self.cfg.eval_episodes
        if episodes == 0:
            return
        t0 = time.monotonic()
        mean, std, length, success, x_velocity = evaluate(weights, self.spec, episodes,
                                                          seeds.evaluation(self.cfg.seed, self.evals),
                                                          deterministic=not self.cfg.eval_stochastic)
        self.evals += 1
        self.last_eval_return = mean
        self.last_eval_updates = updates
        losses = update_stats
        self.last_row = row | {
            "eval_return": mean,
            "eval_return_std": std,
            "eval_length": length,
            "critic_loss": losses.get("critic_loss", float("nan")),
            "actor_loss": losses.get("actor_loss", float("nan")),
            **{k: losses.get(k, float("nan")) for k in DIVERGENCE_COLUMNS + GASIL_COLUMNS},
            **{k: buffer_meta.get(k) for k in EXPERT_COLUMNS + ROLLOUT_COLUMNS},
            "eval_success": "" if success is None else success,
            "q_target_clipped": losses.get("q_target_clipped", float("nan")),
            "eval_x_velocity": "" if x_velocity is None else x_velocity,
            "keep_ratio": keep_ratio(mean, buffer_meta),
            "bc_loss": losses.get("bc_loss", float("nan")),
        }
        self.last_row = self.progress.row(self.last_row)  # as written: what a callback sees in either mode
        if self.best_eval_return is None or mean > self.best_eval_return:
            self.keep_best(weights, mean, std, episodes, row["env_steps"], updates)
        log.info("%s at %d env steps, %d updates: return %.1f +- %.1f over %d episodes (length %.0f%s, %.1fs)",
                 "final eval" if final else "eval", row["env_steps"], updates, mean, std, episodes, length,
                 "" if success is None else f", goal reached in {success:.0%}", time.monotonic() - t0)

    def keep_best(self, weights: P.Weights, mean: float, std: float, episodes: int, env_steps: int,
                  updates: int) -> None:
        """Write `weights` as the run's best policy (atomically), with the evaluation that chose it. A mean of a
        few episodes, picked as the highest of many, overstates the policy: `silcr eval --episodes 50` says more."""
        evaluation = {"return_mean": mean, "return_std": std, "episodes": episodes, "env_steps": env_steps,
                      "updates": updates, "deterministic": not self.cfg.eval_stochastic}
        try:
            write_model(self.best_path, self.cfg.algo, self.cfg.to_dict(), weights, self.spec, evaluation=evaluation,
                        env_steps=env_steps)
        except (OSError, RuntimeError) as e:  # a full disk must not stop training: the next best tries again
            log.error("the best policy so far (return %.1f) could not be written to %s: %s", mean, self.best_path, e)
            return
        self.best_eval_return = mean

    def scalars(self, values: dict[str, float], step: int) -> None:
        self.progress.scalars(values, step)

    def rollout_scalars(self, buffer_meta: dict[str, Any], step: int) -> None:
        """The actors' own episodes (their sampled actions), under Stable-Baselines3's TensorBoard heading."""
        self.scalars({f"rollout/{k.removeprefix('rollout_')}": v for k in ROLLOUT_COLUMNS
                      if (v := buffer_meta.get(k)) is not None}, step)

    def close(self) -> None:
        self.progress.close()

    def state(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.COUNTERS}

    def restore(self, counters: dict[str, Any]) -> None:
        for name in self.COUNTERS:
            # best_eval_return is absent from checkpoints written before best.silcr existed: the next evaluation sets it
            setattr(self, name, counters.get(name) if name == "best_eval_return" else counters[name])
