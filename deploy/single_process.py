"""`silcr train --single-process`: the buffer, the learner and the actors in one process, in a fixed order.

No Zenoh, no router, no other process: the same `ReplayState`, `Learner` and
`Actor` as a distributed run, joined by the in-process clients of
silcr.common.clients. Each round:

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
import signal
import sys
import time

from silcr.actor.service import Actor, policy_factory, random_initial_weights
from silcr.buffer_service import snapshot
from silcr.buffer_service.replay import checkpoint_path, open_replay
from silcr.common import seeds
from silcr.common.clients import InProcessBatchStream, InProcessEpisodeWriter, InProcessWeights
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.lifecycle import StopFlag
from silcr.common.schedule import Every
from silcr.deploy.console import TrainingDisplay, done_message
from silcr.learner.checkpoint import CheckpointError
from silcr.learner.learner import Learner

log = logging.getLogger("train")


def run_single_process(cfg: Config) -> int:
    run_dir = cfg.run_dir
    (run_dir / "logs").mkdir(parents=True, exist_ok=True)
    cfg.save(run_dir / "config.toml")
    # The log goes to a file, as each component's does in a distributed run; the terminal shows the display.
    logging.basicConfig(level=logging.INFO, filename=run_dir / "logs" / "single-process.log", force=True,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    print(f"silcr train: run {cfg.run} in {run_dir} ({cfg.algo} on {cfg.env}, {cfg.actors} actor(s), "
          f"{cfg.total_steps} env steps, single process)", flush=True)
    stop = StopFlag().install_signal_handlers()
    spec = EnvSpec.of(cfg.env)
    try:
        replay, snap = open_replay(cfg, spec)
    except snapshot.SnapshotError as e:
        print(f"silcr train: error: cannot resume: {e}", file=sys.stderr)
        return 2
    board = InProcessWeights()
    try:
        learner = Learner(cfg, spec, board)
    except CheckpointError as e:
        print(f"silcr train: error: cannot resume: {e}", file=sys.stderr)
        return 2
    learner.start()  # the first weights are on the board before any actor acts
    # A hard kill leaves the two checkpoints at different moments: the limiter takes the learner's count.
    replay.take_learner_count(learner.books.incarnation, learner.books.updates)
    actor_cfg = cfg
    if replay.transitions_received:  # resumed actors must not replay the episodes of the first start
        actor_cfg = Config(**cfg.to_dict() | {"seed": seeds.resumed(cfg.seed, replay.transitions_received)})
    actors = [Actor(actor_cfg, spec, i, InProcessEpisodeWriter(replay),
                    board.client(policy_factory(spec),
                                 random_initial_weights(actor_cfg, spec, seeds.actor(actor_cfg.seed, i))()))
              for i in range(cfg.actors)]
    stream = InProcessBatchStream(replay, learner.sample_request(), stop)
    checkpoints = snapshot.PeriodicCheckpoints(checkpoint_path(cfg), cfg.buffer_checkpoint_interval)
    checkpoints.restore_parts(snap, replay)
    polled = [0] * len(actors)
    finished = False
    show = Every(cfg.stats_interval)
    with TrainingDisplay(cfg.total_steps) as display:
        while not stop.is_set():
            collecting = replay.transitions_received < cfg.total_steps
            if collecting:
                for i, actor in enumerate(actors):
                    actor.step()
                    if actor.steps - polled[i] >= cfg.weights_poll_steps:
                        polled[i] = actor.steps
                        actor.weights.update()
            for batch in stream.due():
                learner.step(batch)
            learner.see(stream.last_meta)
            learner.poll()
            if learner.done(starved=not collecting):
                finished = True
                break
            now = time.monotonic()
            checkpoints.maybe(replay, now)
            if show.due(now):
                stats = learner.stats()
                learner.record_scalars(stats)
                display.show(replay.transitions_received, stats)
        display.show(replay.transitions_received, learner.stats())
    # Ctrl-C from here on would leave half-written checkpoints behind the atomic renames: finish first.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    learner.finish(finished)
    checkpoints.final(replay)
    for actor in actors:
        actor.close()
    if finished:
        print(done_message(run_dir))
        return 0
    print(f"silcr train: stopped ({stop.reason}) at {learner.books.updates} updates; checkpoints in {run_dir / 'checkpoints'}",
          file=sys.stderr)
    return 130
