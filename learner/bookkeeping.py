"""The learner's bookkeeping: counters, schedules, evaluation, checkpoints and records.

`Bookkeeping` keeps what a run counts (updates, env steps, policy versions,
evaluations), decides when weights are published, evaluations run and checkpoints
are written, and writes the records: progress.csv and TensorBoard (`progress.py`),
the learner checkpoint (`checkpoint.py`: its own counters beside the update's
networks) and the stats message. It also checks that the buffer service runs this
learner's algorithm (every reply names it).
"""

from __future__ import annotations

import collections
import logging
import time
from typing import Any

import numpy as np

from silcr.common import protocol as P
from silcr.common import seeds
from silcr.common.algorithms import algorithm
from silcr.common.clients import WeightsServer
from silcr.common.config import Config
from silcr.common.envs import EnvSpec

from .checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from .evaluate import evaluate
from .progress import DIVERGENCE_COLUMNS, EXPERT_COLUMNS, GASIL_COLUMNS, ProgressLog
from .update import BufferMismatch, Update

log = logging.getLogger("learner")


def _mean_lag(current: int, versions: np.ndarray) -> float | None:
    known = versions[versions >= 0]  # -1: acted before any learner weights arrived
    return float(current - known.mean()) if known.size else None


class Bookkeeping:
    """Everything a run keeps around the update."""

    COUNTERS = ("updates", "policy_version", "env_steps", "next_eval", "evals", "last_eval_return",
                "checkpoints_failed")

    def __init__(self, cfg: Config, spec: EnvSpec, update: Update, weights: WeightsServer) -> None:
        self.cfg, self.spec = cfg, spec
        self.algo = algorithm(cfg.algo)
        self.update = update
        self.weights_server = weights
        self.incarnation = P.new_incarnation()
        self.updates = 0
        self.policy_version = 0
        self.env_steps = 0
        self.next_eval = 0
        self.evals = 0
        self.last_eval_return: float | None = None
        self.last_eval_updates = -1
        self.checkpoints_failed = 0
        self.checkpoint_path = cfg.run_dir / "checkpoints" / "learner.pt"
        # --resume continues from a checkpoint when there is one, so the same command
        # serves a first start and every restart (launcher, sweep, docker restart policy).
        self.resumed = cfg.resume and self.checkpoint_path.exists()
        if self.resumed:
            payload = load_checkpoint(self.checkpoint_path)
            try:
                update.restore(payload, self.checkpoint_path)
            except (ValueError, KeyError, RuntimeError) as e:  # other networks, another --algo, missing tensors
                raise CheckpointError(f"{self.checkpoint_path} does not fit this run: {e}") from None
            self.restore(payload["counters"])
            log.info("resumed from %s: %d updates, policy version %d", self.checkpoint_path, self.updates,
                     self.policy_version)
        elif cfg.resume:
            log.info("--resume: no checkpoint at %s yet; starting fresh", self.checkpoint_path)
        self.next_checkpoint = (self.updates // cfg.checkpoint_interval + 1) * cfg.checkpoint_interval
        cfg.run_dir.mkdir(parents=True, exist_ok=True)
        self.progress = ProgressLog(cfg.run_dir, resume=self.resumed)
        self.started = time.monotonic()
        self.update_time = 0.0
        # This start's training span, from its first update to its last (logged at the end: `silcr bench peer` reads it)
        self.first_update_at: float | None = None
        self.last_update_at = 0.0
        self.updates_this_start = 0
        self.buffer_meta: dict[str, Any] = {}  # the latest reply's description of the buffer (D_E's returns)
        self.policy_lag: collections.deque[float] = collections.deque(maxlen=200)  # D_O rows only
        self.expert_age: collections.deque[float] = collections.deque(maxlen=200)  # D_E rows

    # -- counters ------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.COUNTERS}

    def restore(self, counters: dict[str, Any]) -> None:
        for name in self.COUNTERS:
            setattr(self, name, counters.get(name, 0) if name == "checkpoints_failed" else counters[name])  # 0.4

    def checkpoint(self) -> bool:
        """Write the learner checkpoint; a failure (a full disk, a directory made unwritable) is counted in
        `checkpoints_failed` and training goes on: the previous checkpoint stays whole (`write_atomic`), and
        dying here would only restart the learner from that older checkpoint, losing more updates."""
        t0 = time.monotonic()
        try:
            save_checkpoint(self.checkpoint_path,
                            self.update.state() | {"counters": self.state(), "config": self.cfg.to_dict()})
        except (OSError, RuntimeError) as e:  # torch.save reports a failed write as RuntimeError
            self.checkpoints_failed += 1
            if self.checkpoints_failed == 1:
                log.warning("checkpoint at %d updates failed (%s); training goes on, and failures are counted in "
                            "checkpoints_failed (stats, progress.csv)", self.updates, e)
            return False
        log.info("checkpoint at %d updates written in %.2fs", self.updates, time.monotonic() - t0)
        return True

    # -- what the buffer says -------------------------------------------------------------
    def see(self, meta: dict[str, Any]) -> None:
        """Take in a reply's description of the buffer (any reply: a not-ready one too)."""
        theirs = meta.get("algo", self.algo.name)  # absent from buffers before 0.4 (`note_rows` checks those)
        if theirs != self.algo.name:
            raise BufferMismatch(f"the buffer service runs --algo {theirs}, this learner --algo {self.algo.name}; "
                                 f"start both with the same --algo")
        self.env_steps = max(self.env_steps, int(meta.get("env_steps", 0)))
        if "expert_transitions" in meta:
            self.buffer_meta = meta

    def note_rows(self, reply: P.BatchReply) -> None:
        """How old the rows of a reply are: the policy lag of its D_O rows, the age of its D_E rows."""
        n, size = int(reply.meta["batches"]), int(reply.meta["batch_size"])
        online = int(reply.meta.get("online_rows", size))  # rows of each batch from D_O; the rest are D_E's
        if (online < size) != self.algo.mixes_expert:  # a buffer too old to name its algorithm
            raise BufferMismatch(f"--algo {self.algo.name}: the buffer service "
                                 f"{'mixes D_E rows into' if online < size else 'sends no D_E rows in'} its batches; "
                                 f"it runs another --algo (start both with the same --algo)")
        versions = reply.batch.policy_version.reshape(n, size)
        lag = _mean_lag(self.policy_version, versions[:, :online])
        if lag is not None:
            self.policy_lag.append(lag)
        if online < size and (age := _mean_lag(self.policy_version, versions[:, online:])) is not None:
            self.expert_age.append(age)

    # -- schedules -------------------------------------------------------------------
    def counted(self, n: int, seconds: float) -> None:
        """`n` updates were made in `seconds`: publish weights and checkpoint when due."""
        self.updates += n
        self.update_time += seconds
        now = time.monotonic()
        if self.first_update_at is None:
            self.first_update_at = now - seconds
        self.last_update_at = now
        self.updates_this_start += n
        if self.updates // self.cfg.weights_interval != (self.updates - n) // self.cfg.weights_interval:
            self.policy_version += 1
            self.publish_weights()
        if self.updates >= self.next_checkpoint:
            self.checkpoint()
            self.next_checkpoint = (self.updates // self.cfg.checkpoint_interval + 1) * self.cfg.checkpoint_interval

    def weights(self) -> P.Weights:
        return self.update.weights(self.policy_version, self.incarnation, time.time())

    def publish_weights(self, final: bool = False) -> None:
        weights = self.weights()
        weights.wire_dtype = self.cfg.weights_dtype  # how they travel; the learner evaluates its own float32 ones
        self.weights_server.publish(weights, final=final)

    def start(self) -> None:
        """Publish the first weights and, on a fresh start, evaluate the untrained policy (every curve's baseline)."""
        self.publish_weights()
        if not self.resumed:
            self.evaluate()
            self.next_eval = self.cfg.eval_interval

    def poll(self) -> None:
        """Send weights the fan-out budget held back, and evaluate when the environment-step schedule says so."""
        self.weights_server.poll()
        if self.env_steps >= self.next_eval:
            self.evaluate()
            self.next_eval = (self.env_steps // self.cfg.eval_interval + 1) * self.cfg.eval_interval

    def target_updates(self) -> int:
        return int(max(0, self.cfg.total_steps - self.cfg.learning_starts) * self.cfg.samples_per_insert)

    def done(self, starved: bool) -> bool:
        """The budget is spent: every step collected and trained on, or nothing more to be had (`starved`)."""
        return self.env_steps >= self.cfg.total_steps and (self.updates >= self.target_updates() or starved)

    def finish(self, finished: bool) -> None:
        """Last weights and evaluation if the run finished, a checkpoint either way, then close the records."""
        if finished:
            self.policy_version += 1
            self.publish_weights(final=True)
            if self.updates != self.last_eval_updates:  # not the policy the schedule just evaluated
                self.evaluate()
            log.info("finished: %d env steps, %d updates, last eval return %s", self.env_steps, self.updates,
                     self.last_eval_return)
        if self.first_update_at is not None:
            span = self.last_update_at - self.first_update_at
            log.info("training: %d updates in %.2f s from the first to the last (%.2f ms each), %.2f s of it in updates "
                     "(duty cycle %.3f)", self.updates_this_start, span, 1000 * span / self.updates_this_start,
                     self.update_time, self.update_time / max(span, 1e-9))
        if not self.checkpoint():
            log.error("the final checkpoint could not be written (%d checkpoint(s) failed): --resume would continue "
                      "from the last one that was", self.checkpoints_failed)
        self.progress.close()

    # -- records ---------------------------------------------------------------------
    def evaluate(self) -> None:
        """Evaluate the policy (deterministic unless --eval-stochastic) and write a progress row."""
        if self.cfg.eval_episodes == 0:
            return
        t0 = time.monotonic()
        mean, std, length, success = evaluate(self.weights(), self.spec, self.cfg.eval_episodes,
                                              seeds.evaluation(self.cfg.seed, self.evals),
                                              deterministic=not self.cfg.eval_stochastic)
        self.evals += 1
        self.last_eval_return = mean
        self.last_eval_updates = self.updates
        elapsed = time.monotonic() - self.started
        losses = self.update.stats()
        self.progress.row({
            "time": round(elapsed, 3),
            "env_steps": self.env_steps,
            "updates": self.updates,
            "policy_version": self.policy_version,
            "eval_return": mean,
            "eval_return_std": std,
            "eval_length": length,
            "alpha": self.update.alpha,
            "critic_loss": losses.get("critic_loss", float("nan")),
            "actor_loss": losses.get("actor_loss", float("nan")),
            "updates_per_s": self.updates / max(elapsed, 1e-9),
            **{k: losses.get(k, float("nan")) for k in DIVERGENCE_COLUMNS + GASIL_COLUMNS},
            **{k: self.buffer_meta.get(k) for k in EXPERT_COLUMNS},
            "checkpoints_failed": self.checkpoints_failed,
            "eval_success": "" if success is None else success,
            "q_target_clipped": losses.get("q_target_clipped", float("nan")),
        })
        log.info("eval at %d env steps, %d updates: return %.1f +- %.1f (length %.0f%s, %.1fs)",
                 self.env_steps, self.updates, mean, std, length,
                 "" if success is None else f", goal reached in {success:.0%}", time.monotonic() - t0)

    def stats(self) -> dict[str, Any]:
        """The learner's stats message (the batch stream adds its own counters)."""
        elapsed = time.monotonic() - self.started
        losses = self.update.stats()
        return {
            "time": time.time(),
            "updates": self.updates,
            "policy_version": self.policy_version,
            "env_steps": self.env_steps,
            "total_steps": self.cfg.total_steps,
            "last_eval_return": self.last_eval_return,
            "updates_per_s": self.updates / max(elapsed, 1e-9),
            "checkpoints_failed": self.checkpoints_failed,
            "duty_cycle": self.update_time / max(elapsed, 1e-9),
            "policy_lag_mean": float(np.mean(self.policy_lag)) if self.policy_lag else None,
            "expert_age_mean": float(np.mean(self.expert_age)) if self.expert_age else None,
            "device": str(self.update.device),
            "torch_threads": self.update.torch_threads,
            **self.weights_server.stats(),
        } | {k: P.finite_or_none(v) for k, v in losses.items()} | {"q_bound_exceeded": losses["q_bound_exceeded"]}

    def record_scalars(self, stats: dict[str, Any]) -> None:
        """The training statistics as TensorBoard scalars at the current env step."""
        if self.updates:
            keys = [*self.update.stat_names(), "updates_per_s"]
            self.progress.scalars({f"train/{k}": stats[k] for k in keys if stats.get(k) is not None}, self.env_steps)
