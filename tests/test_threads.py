"""The learner's torch threads: chosen by timing the update, logged, honoured; --torch-threads overrides."""

from __future__ import annotations

import logging

import pytest
import torch

from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.learner import threads
from silcr.learner.update import Update


@pytest.fixture(autouse=True)
def _keep_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_the_faster_count_is_kept_whichever_it_is():
    for faster in (1, 4):
        calls = []

        def timer(step, n, updates):
            calls.append(n)
            return 1.0 if n == faster else 2.0

        best, times = threads.choose_threads(lambda: None, 4, timer=timer)
        assert best == faster and times == {faster: 1.0, 5 - faster: 2.0}
        assert calls == [1, 4, 1, 4]  # alternated, so load from elsewhere hits both
    assert threads.choose_threads(lambda: None, 1, timer=lambda s, n, u: 1.0)[0] == 1  # one core: nothing to time


@pytest.mark.parametrize("faster", [1, 2])
def test_the_learner_logs_its_choice_and_uses_it(caplog, monkeypatch, faster):
    spec = EnvSpec.of("InvertedPendulum-v5")
    monkeypatch.setattr("silcr.learner.update.usable_cores", lambda: 2)
    timed = []
    real = threads.time_per_update

    def rigged(step, n, updates):  # make `faster` the faster, whatever this machine measures
        timed.append(n)
        return real(step, n, 2) * (1.0 if n == faster else 100.0)

    monkeypatch.setattr(threads, "time_per_update", rigged)
    with caplog.at_level(logging.INFO, logger="learner"):
        update = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], batch_size=16, device="cpu"), spec)
    assert sorted(set(timed)) == [1, 2]
    # honoured: the count in use is the choice, not the last one timed (2)
    assert update.torch_threads == faster and torch.get_num_threads() == faster
    assert any(r.getMessage().startswith(f"torch threads: {faster} (timed the update: 1 thread") for r in caplog.records)


def test_torch_threads_overrides_the_choice(caplog, monkeypatch):
    spec = EnvSpec.of("InvertedPendulum-v5")
    monkeypatch.setattr(threads, "time_per_update", lambda *a: pytest.fail("timed anyway"))
    with caplog.at_level(logging.INFO, logger="learner"):
        update = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], torch_threads=1, device="cpu"), spec)
    assert update.torch_threads == 1 and torch.get_num_threads() == 1
    assert not any("torch threads" in r.getMessage() for r in caplog.records)


def test_the_probe_changes_nothing_the_run_draws():
    """The probe trains a throwaway copy before the seed is set: the networks start the same either way."""
    spec = EnvSpec.of("InvertedPendulum-v5")
    chosen = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], device="cpu"), spec)
    pinned = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], torch_threads=1, device="cpu"), spec)
    for a, b in zip(chosen.sac.actor_arrays().values(), pinned.sac.actor_arrays().values()):
        assert (a == b).all()
