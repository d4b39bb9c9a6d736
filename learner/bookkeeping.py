"""The learner's bookkeeping: counters, schedules, and the parts that keep the run's records.

`Bookkeeping` keeps what a run counts (updates, env steps, policy versions), decides when
weights are published, evaluations run and checkpoints are written, and joins the parts that
each keep one record and save and restore their own state:

  evaluations.Evaluations   the evaluation schedule and the progress.csv/TensorBoard rows
  checkpoint.LearnerCheckpoints   the learner checkpoint, its loading on --resume, failed writes
  row_ages.RowAges          how old the rows trained on are (policy lag, D_E's age)
  update_clock.UpdateClock  the time spent in updates (rate, duty cycle, this start's span)

It also checks that the buffer service runs this learner's algorithm (every reply names it).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from silcr.common import protocol as P
from silcr.common import run_end
from silcr.common.algorithms import algorithm
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.weights_channel import WeightsServer

from .checkpoint import LearnerCheckpoints
from .evaluations import Evaluations
from .row_ages import RowAges
from .update import Update
from .update_clock import UpdateClock

log = logging.getLogger("learner")


class Bookkeeping:
    """Everything a run keeps around the update."""

    COUNTERS = ("updates", "policy_version", "env_steps")

    def __init__(self, cfg: Config, spec: EnvSpec, update: Update, weights: WeightsServer,
                 checkpoints: LearnerCheckpoints) -> None:
        """Counters at zero; `Learner` restores them from the checkpoint (`restore`)."""
        self.cfg, self.spec = cfg, spec
        self.algo = algorithm(cfg.algo)
        self.update = update
        self.weights_server = weights
        self.incarnation = P.new_incarnation()
        self.updates = self.policy_version = self.env_steps = 0  # COUNTERS
        self.checkpoints = checkpoints
        self.resumed = checkpoints.resumed
        self.evaluations = Evaluations(cfg, spec, cfg.run_dir, self.resumed)
        self.clock = UpdateClock()  # before `restore`: it keeps the run's time before this start
        self.ages = RowAges()
        self.next_checkpoint = (self.updates // cfg.checkpoint_interval + 1) * cfg.checkpoint_interval
        self.buffer_meta: dict[str, Any] = {}  # the latest reply's description of the buffer (D_E's returns)

    # -- counters and checkpoints ------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """The checkpoint's counters: this object's and its parts', in one map."""
        return ({name: getattr(self, name) for name in self.COUNTERS} | {"wall_time": self.clock.wall_time()}
                | self.evaluations.state() | self.checkpoints.state())

    def restore(self, counters: dict[str, Any]) -> None:
        for name in self.COUNTERS:
            setattr(self, name, counters[name])
        self.clock.wall_before = float(counters.get("wall_time", 0.0))  # absent before silcr 0.6
        self.evaluations.restore(counters)
        self.checkpoints.restore(counters)
        self.next_checkpoint = (self.updates // self.cfg.checkpoint_interval + 1) * self.cfg.checkpoint_interval

    def checkpoint(self) -> bool:
        """Write the learner checkpoint; a failure (a full disk, a directory made unwritable) is counted in
        `checkpoints_failed` and training goes on: the previous checkpoint stays whole (`write_atomic`), and
        dying here would only restart the learner from that older checkpoint, losing more updates."""
        t0 = time.monotonic()
        try:
            self.checkpoints.write(self.update.state() | {"counters": self.state(), "config": self.cfg.to_dict()})
        except (OSError, RuntimeError) as e:  # torch.save reports a failed write as RuntimeError
            if self.checkpoints.failed == 1:
                log.warning("checkpoint at %d updates failed (%s); training goes on, and failures are counted in "
                            "checkpoints_failed (stats, progress.csv)", self.updates, e)
            return False
        log.info("checkpoint at %d updates written in %.2fs", self.updates, time.monotonic() - t0)
        return True

    # -- what the buffer says -------------------------------------------------------------
    def see(self, reply: P.BatchReply | None) -> None:
        """Take in a reply's description of the buffer (any reply: a not-ready one too; None: none came yet)."""
        if reply is None:
            return
        reply.header.check_algo(self.algo)
        meta = reply.meta
        self.env_steps = max(self.env_steps, int(meta.get("env_steps", 0)))
        if "expert_transitions" in meta:
            self.buffer_meta = meta

    def note_rows(self, reply: P.BatchReply) -> None:
        """How old the rows of a reply are: the policy lag of its D_O rows, the age of its D_E rows."""
        self.ages.note(reply, self.policy_version)

    # -- schedules -------------------------------------------------------------------
    def counted(self, n: int, seconds: float) -> None:
        """`n` updates were made in `seconds`: publish weights and checkpoint when due."""
        self.updates += n
        self.clock.counted(n, seconds)
        if self.updates // self.cfg.weights_interval != (self.updates - n) // self.cfg.weights_interval:
            self.policy_version += 1
            self.publish_weights()
        if self.updates >= self.next_checkpoint:
            self.checkpoint()
            self.next_checkpoint = (self.updates // self.cfg.checkpoint_interval + 1) * self.cfg.checkpoint_interval

    def weights(self, wire_dtype: str = "float32") -> P.Weights:
        """The actor's weights now; `wire_dtype`: how they travel (the learner evaluates its own float32 ones)."""
        return self.update.weights(self.policy_version, self.incarnation, time.time(), wire_dtype)

    def publish_weights(self, final: bool = False) -> None:
        self.weights_server.publish(self.weights(self.cfg.weights_dtype), final=final)

    def start(self) -> None:
        """Publish the first weights and, on a fresh start, evaluate the untrained policy (every curve's baseline)."""
        run_end.unmark(self.cfg.run_dir)  # a finished run that goes on (a larger budget) is not finished any more
        self.publish_weights()
        if not self.resumed:
            self.evaluate()
            self.evaluations.next_eval = self.cfg.eval_interval

    def poll(self) -> None:
        """Send weights the fan-out budget held back, and evaluate when the environment-step schedule says so."""
        self.weights_server.poll()
        if self.evaluations.due(self.env_steps):
            self.evaluate()
            self.evaluations.scheduled(self.env_steps)

    def done(self, starved: bool) -> bool:
        """The budget is spent: every step collected and trained on, or nothing more to be had (`starved`)."""
        return self.env_steps >= self.cfg.total_steps and (self.updates >= run_end.target_updates(self.cfg) or starved)

    def finish(self, finished: bool) -> bool:
        """`settle`, then close the records; whether the final checkpoint was written."""
        try:
            return self.settle(finished)
        finally:
            self.evaluations.close()

    def settle(self, finished: bool) -> bool:
        """Last weights and evaluation if the budget is spent, a checkpoint either way; the records stay open,
        so a larger budget can go on from here (the Python API's second `learn`). Whether the checkpoint was
        written."""
        if finished:
            self.policy_version += 1
            self.publish_weights(final=True)
            if self.evaluations.final_due(self.updates):
                self.evaluate(final=True)
            log.info("finished: %d env steps, %d updates, last eval return %s", self.env_steps, self.updates,
                     self.evaluations.last_eval_return)
        self.clock.log_span()
        if not self.checkpoint():
            log.error("the final checkpoint could not be written (%d checkpoint(s) failed): --resume would continue "
                      "from the last one that was", self.checkpoints.failed)
            return False
        if finished:  # the finished-run rule: from now on a start with this budget changes nothing (run_end.py)
            run_end.mark(self.cfg.run_dir, run_end.Finished(self.cfg.run, self.env_steps, self.updates,
                                                            self.cfg.total_steps))
        return True

    # -- records ---------------------------------------------------------------------
    def evaluate(self, final: bool = False) -> None:
        """Evaluate the policy (deterministic unless --eval-stochastic) and write a progress row."""
        self.evaluations.run(self.weights(), {
            "time": round(self.clock.elapsed(), 3),
            "wall_time": round(self.clock.wall_time(), 3),
            "env_steps": self.env_steps,
            "updates": self.updates,
            "policy_version": self.policy_version,
            "alpha": self.update.alpha,
            "updates_per_s": self.clock.rates(self.updates)["updates_per_s"],
            "checkpoints_failed": self.checkpoints.failed,
        }, self.update.stats(), self.updates, self.buffer_meta, final)

    def stats(self) -> dict[str, Any]:
        """The learner's stats message (the batch stream adds its own counters)."""
        losses = self.update.stats()
        return {
            "time": time.time(),
            "updates": self.updates,
            "policy_version": self.policy_version,
            "env_steps": self.env_steps,
            "total_steps": self.cfg.total_steps,
            "last_eval_return": self.evaluations.last_eval_return,
            **self.clock.rates(self.updates),
            "checkpoints_failed": self.checkpoints.failed,
            **self.evaluations.progress.stats(),
            **self.ages.stats(),
            "device": str(self.update.device),
            "torch_threads": self.update.torch_threads,
            **self.weights_server.stats(),
        } | {k: P.finite_or_none(v) for k, v in losses.items()} | {"q_bound_exceeded": losses["q_bound_exceeded"]}

    def record_scalars(self, stats: dict[str, Any]) -> None:
        """The training statistics as TensorBoard scalars at the current env step."""
        if self.updates:
            keys = [*self.update.stat_names(), "updates_per_s"]
            self.evaluations.scalars({f"train/{k}": stats[k] for k in keys if stats.get(k) is not None}, self.env_steps)
        self.evaluations.rollout_scalars(self.buffer_meta, self.env_steps)
