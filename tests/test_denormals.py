"""Denormal floats are flushed to zero while the learner's CPU update runs, and only then (learner/denormals.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.learner import denormals
from silcr.learner.update import Update
from tests.helpers import two_batch_reply

DENORMAL = 1e-39  # below float32's smallest normal number, 1.2e-38


def survives() -> bool:
    """Whether a float32 denormal survives arithmetic on this thread now."""
    return float(torch.tensor([DENORMAL]) * 1.0) != 0.0


@pytest.fixture(autouse=True)
def _mode_off_after():
    yield
    torch.set_flush_denormal(False)


def test_denormals_are_flushed_inside_the_block_and_kept_outside():
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush denormals (not x86 with SSE3)")
    assert survives()
    with denormals.flushed(torch.device("cpu")):
        assert not survives()
    assert survives()  # MuJoCo, stepped by the same thread in --single-process, sees the default mode
    with denormals.flushed(torch.device("cpu"), enabled=False):
        assert survives()
    with pytest.raises(RuntimeError), denormals.flushed(torch.device("cpu")):
        raise RuntimeError("an update that fails")
    assert survives()  # restored on the way out of a failure too


def test_torchs_other_threads_flush_inside_the_block_too():
    """The mode belongs to each thread: torch's OpenMP workers get it copied (a 2-thread update ran 13.0 ms, not 8.9, without)."""
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush denormals")
    if denormals.team_env() is None:
        pytest.skip("torch's OpenMP runtime cannot be reached here (not Linux, or not libgomp/libiomp5/libomp)")
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        many = torch.full((2_000_000,), DENORMAL)  # big enough that torch splits the multiply over both threads
        assert int(((many * 1.0) != 0).sum()) == many.numel()  # the pool exists, in the default mode
        with denormals.flushed(torch.device("cpu")):
            assert int(((many * 1.0) != 0).sum()) == 0  # the worker's half too (1M survived without the copy)
        assert int(((many * 1.0) != 0).sum()) == many.numel()  # and every thread is back to the default
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("keep", [False, True])
def test_the_learners_update_runs_with_denormals_flushed_unless_kept(monkeypatch, keep):
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush denormals")
    spec = EnvSpec.of("InvertedPendulum-v5")
    update = Update(Config(run="t", env=spec.env_id, hidden=[8, 8], batch_size=4, torch_threads=1,
                           keep_denormals=keep), spec)
    seen = []
    real = update.sac.update
    monkeypatch.setattr(update.sac, "update", lambda *a: (seen.append(survives()), real(*a))[1])
    assert update.train(two_batch_reply(spec.obs_dim, spec.act_dim), 0) == 2
    assert seen == [keep, keep]
    assert survives()  # and the mode is back to the default after the reply
    assert np.isfinite(update.stats()["critic_loss"])
