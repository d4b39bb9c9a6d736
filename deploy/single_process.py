"""`silcr train --single-process`: the buffer, the learner and the actors in one process, in a fixed order.

No Zenoh, no router, no other process: the same `ReplayState`, `Learner` and
`Actor` as a distributed run, joined by the in-process clients of
the channel modules of silcr.common (episode_channel, sample_channel, weights_channel). Each round:

1. every actor, in id order, steps each of its envs once with its current policy
   (new weights are taken every `--weights-poll-steps` steps); finished episodes
   go straight into D_O and D_E;
2. the learner takes exactly the updates the transitions received so far are due
   (`--samples-per-insert`, after `--learning-starts`), never more;
3. evaluations and checkpoints fall due on the same schedules as in a distributed run.

Nothing here depends on timing, so one seed gives the same progress.csv to the
last digit on one machine, except the wall-clock columns `time` and
`updates_per_s` (tests/test_single_process.py). What the distributed run adds -
actors that run ahead or fall behind, weights that arrive a little late - is
exactly what this mode leaves out: use it for debugging (a debugger works),
reproducible experiments and small machines; use the distributed launcher to
spread a run over cores and machines (docs/deployment.md, "Which launcher").

Checkpoints: the learner's on its update schedule, the buffer's every
`--buffer-checkpoint-interval` seconds in a background thread, both on the way
out; `--resume` restores both (the actors start new episodes, with new seeds)
and, after a hard kill left the two at different moments, takes the updates
the learner lost again (`ReplayState.take_learner_count`).
There is no stats topic: the progress bar, progress.csv and TensorBoard report.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any, Callable

from silcr.actor.service import Actor, policy_factory, random_initial_weights
from silcr.buffer_service import snapshot
from silcr.buffer_service.replay import checkpoint_path, open_replay
from silcr.common import run_layout, seeds
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.episode_channel import InProcessEpisodeWriter
from silcr.common.lifecycle import StopFlag, ignore_stop_signals, stop_on_signals
from silcr.common.sample_channel import InProcessBatchStream
from silcr.common.schedule import Every
from silcr.common.weights_channel import InProcessWeights
from silcr.deploy.console import RunEnd, TrainingDisplay
from silcr.learner.checkpoint import CheckpointError
from silcr.learner.learner import Learner

log = logging.getLogger("train")


class ResumeError(RuntimeError):
    """A checkpoint to resume from cannot be used (the message names it and why)."""


class SingleProcessRun:
    """One run's buffer, learner and actors in this process (what `silcr train --single-process` and the
    Python API's `actors=0` drive). `run()` steps them to `cfg.total_steps`; raise the budget and call it
    again to go on with the same tables and counters. `close()` writes the last checkpoints."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.spec = spec = EnvSpec.of(cfg.env)
        try:
            self.replay, snap = open_replay(cfg, spec)
        except snapshot.SnapshotError as e:
            raise ResumeError(str(e)) from None
        self.board = InProcessWeights()
        try:
            self.learner = Learner(cfg, spec, self.board)
        except CheckpointError as e:
            raise ResumeError(str(e)) from None
        self.learner.books.start()  # the first weights are on the board before any actor acts
        # A hard kill leaves the two checkpoints at different moments: the limiter takes the learner's count.
        self.replay.sampler.take_learner_count(self.learner.books.incarnation, self.learner.books.updates)
        actor_cfg = cfg
        if self.replay.transitions_received:  # resumed actors must not replay the episodes of the first start
            actor_cfg = Config(**cfg.to_dict() | {"seed": seeds.resumed(cfg.seed, self.replay.transitions_received)})
        self.actors = [Actor(actor_cfg, spec, i, InProcessEpisodeWriter(self.replay.intake),
                             self.board.client(policy_factory(spec),
                                               random_initial_weights(actor_cfg, spec, seeds.actor(actor_cfg.seed, i))()))
                       for i in range(cfg.actors)]
        self.stream = InProcessBatchStream(self.replay.sampler, self.learner.update.sample_request(), None)
        self.checkpoints = snapshot.PeriodicCheckpoints(checkpoint_path(cfg), cfg.buffer_checkpoint_interval)
        self.checkpoints.restore_parts(snap, self.replay)
        self._polled = [0] * len(self.actors)
        self.checkpoint_written = True  # the learner's last one (`run` sets it)
        self._reported = 0  # evaluations told to `run`'s callers

    def run(self, stop: StopFlag, display: TrainingDisplay | None = None,
            evaluated: Callable[[dict[str, Any]], bool] | None = None) -> bool:
        """Step the actors, the learner and the schedules until the budget is spent (True) or `stop` is set or
        `evaluated` (given each new progress row) returns False (False) or raises (raised again). The learner's
        last weights, evaluation and checkpoint follow either way (`Learner.settle`); its records stay open for
        another `run`."""
        cfg, replay, learner = self.cfg, self.replay, self.learner
        finished = False
        raised: BaseException | None = None  # the callback's: raised once the learner has settled
        show = Every(cfg.stats_interval)
        while not stop.is_set():
            if evaluated is not None:
                try:
                    if self._told(evaluated) is False:
                        break
                except Exception as e:
                    raised = e
                    break
            collecting = replay.transitions_received < cfg.total_steps
            if collecting:
                for i, actor in enumerate(self.actors):
                    actor.step()
                    if actor.steps - self._polled[i] >= cfg.weights_poll_steps:
                        self._polled[i] = actor.steps
                        actor.weights.update()
            for batch in self.stream.due():
                learner.step(batch)
            learner.books.see(self.stream.last_reply)
            learner.books.poll()
            if learner.books.done(starved=not collecting):
                finished = True
                break
            now = time.monotonic()
            self.checkpoints.maybe(replay, now)
            if show.due(now):
                stats = learner.books.stats()
                learner.books.record_scalars(stats)
                if display is not None:
                    display.show(replay.transitions_received, stats)
        if display is not None:
            display.show(replay.transitions_received, learner.books.stats())
        self.checkpoint_written = learner.books.settle(finished)
        if raised is not None:
            raise raised
        if finished and evaluated is not None:
            self._told(evaluated)  # the closing evaluation
        return finished

    def _told(self, evaluated: Callable[[dict[str, Any]], bool]) -> bool | None:
        """Give `evaluated` the newest progress row if it has not seen it (one evaluation at most falls
        between two calls, the first one before the loop); what it returned."""
        evaluations = self.learner.books.evaluations
        if evaluations.evals == self._reported or not evaluations.last_row:
            return None
        self._reported = evaluations.evals
        return evaluated(evaluations.last_row)

    def close(self) -> list[str]:
        """Close the learner's records and write the buffer's last checkpoint; the actors' envs close. The
        components whose final checkpoint could not be written (stale on disk)."""
        self.learner.books.evaluations.close()
        buffer_written = self.checkpoints.final(self.replay)
        for actor in self.actors:
            actor.close()
        return [name for name, ok in (("learner", self.checkpoint_written), ("buffer", buffer_written)) if not ok]


def run_single_process(cfg: Config) -> RunEnd:
    """The run to its end, in this process; how it ended (the launcher reports it: `console.report_end`)."""
    with stop_on_signals(StopFlag()) as stop:  # the API and tests call this in their own process
        return _run_single_process(cfg, stop)


def _run_single_process(cfg: Config, stop: StopFlag) -> RunEnd:
    run_dir = cfg.run_dir  # held by the launcher (`launch.run_directory`)
    # The log goes to a file, as each component's does in a distributed run; the terminal shows the display.
    logging.basicConfig(level=logging.INFO, filename=run_layout.single_process_log(run_dir), force=True,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    print(f"silcr train: run {cfg.run} in {run_dir} ({cfg.algo} on {cfg.env}, {cfg.actors} actor(s), "
          f"{cfg.total_steps} env steps, single process)", flush=True)
    try:
        run = SingleProcessRun(cfg)
    except ResumeError as e:
        print(f"silcr train: error: cannot resume: {e}", file=sys.stderr)
        return RunEnd(2, [])
    with TrainingDisplay(cfg.total_steps) as display:
        # Ctrl-C once `run` returns would leave half-written checkpoints behind the atomic renames: it
        # settles the learner before returning, and the rest finishes with Ctrl-C ignored.
        finished = run.run(stop, display)
    ignore_stop_signals()
    stale = run.close()
    if finished:
        return RunEnd(0, stale)
    print(f"silcr train: stopped ({stop.reason}) at {run.learner.books.updates} updates; checkpoints in "
          f"{run_layout.checkpoints(run_dir)}", file=sys.stderr)
    return RunEnd(130, stale)
