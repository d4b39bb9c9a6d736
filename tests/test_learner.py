"""`Learner` driven directly, without Zenoh: counters, the weights schedule, checkpoints, evaluations, the end."""

from __future__ import annotations

import csv

import numpy as np

from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.weights_channel import InProcessWeights
from silcr.learner.checkpoint import load_checkpoint
from silcr.learner.learner import Learner
from tests.conftest import make_episode

ENV = "InvertedPendulum-v5"


class Recorder(InProcessWeights):
    def __init__(self) -> None:
        super().__init__()
        self.versions: list[int] = []

    def publish(self, weights: P.Weights, final: bool = False) -> None:
        super().publish(weights, final)
        self.versions.append(weights.version)


def _learner(tmp_path, **over) -> tuple[Learner, Recorder, Config]:
    cfg = Config(run="lt", runs_dir=str(tmp_path), env=ENV, hidden=[16], batch_size=8, learning_starts=10,
                 weights_interval=3, checkpoint_interval=5, eval_interval=40, eval_episodes=1, total_steps=100, **over)
    server = Recorder()
    return Learner(cfg, EnvSpec.of(ENV), server), server, cfg


def _batch(replay: ReplayState, batches: int) -> P.BatchReply:
    return replay.sampler.sample(P.SampleRequest(batches, 8))


def test_step_keeps_the_schedules(tmp_path):
    lrn, server, cfg = _learner(tmp_path)
    replay = ReplayState(cfg, EnvSpec.of(ENV))
    for i in range(6):
        replay.intake.store(make_episode(10, ret=float(i), seq=i))
    lrn.books.start()
    assert server.versions == [0] and lrn.books.evaluations.evals == 1  # the untrained policy's weights and evaluation
    for n in (2, 2, 2, 1):
        lrn.step(_batch(replay, n))
        lrn.books.poll()
    assert lrn.books.updates == 7 and lrn.books.env_steps == 60
    assert server.versions == [0, 1, 2]  # a new version every 3 updates (after 3 and 6)
    assert load_checkpoint(lrn.books.checkpoints.path)["counters"]["updates"] == 6  # every 5 updates, at the step crossing it
    assert lrn.books.evaluations.evals == 2  # 60 env steps passed the evaluation at 40
    assert lrn.books.ages.policy_lag and lrn.books.ages.expert_age  # both halves of a SILCR batch measured apart
    assert not lrn.books.done(starved=False)
    lrn.books.see(P.BatchReply("not_ready", {"env_steps": 100}))
    assert not lrn.books.done(starved=False) and lrn.books.done(starved=True)  # 7 of the 90 updates due: done only if starved
    lrn.books.finish(finished=True)
    rows = list(csv.DictReader(open(tmp_path / "lt" / "progress.csv")))
    # evaluations: the untrained policy, the first poll past 40 env steps (after 2 updates), the final one
    assert [int(r["updates"]) for r in rows] == [0, 2, 7]
    assert server.versions[-1] == 3 and load_checkpoint(lrn.books.checkpoints.path)["counters"]["updates"] == 7


def test_policy_lag_counts_only_online_rows(tmp_path):
    lrn, _, cfg = _learner(tmp_path)
    replay = ReplayState(cfg, EnvSpec.of(ENV))
    for i in range(4):
        replay.intake.store(make_episode(10, ret=float(i), seq=i, version=0))
    lrn.books.policy_version = 10
    batch = _batch(replay, 1)
    versions = batch.batch.policy_version
    online = batch.meta["online_rows"]
    versions[:online] = 8  # D_O rows: 2 versions behind
    versions[online:] = 1  # D_E rows: old expert episodes, 9 versions behind
    lrn.step(batch)
    assert lrn.books.ages.policy_lag[-1] == 2.0 and lrn.books.ages.expert_age[-1] == 9.0
    assert np.isfinite(lrn.books.stats()["policy_lag_mean"])
