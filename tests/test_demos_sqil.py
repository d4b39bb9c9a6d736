"""Demonstration files (`silcr demos`), the SQIL buffer, and their rejections."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.demos import DemosError, load_demos, save_demos
from silcr.common.envs import EnvSpec
from tests.conftest import make_episode
from tests.helpers import REPO

ENV = "InvertedPendulum-v5"  # obs 4, act 1


@pytest.fixture(scope="module")
def spec():
    return EnvSpec.of(ENV)


def _demos(n=3):
    return [make_episode(5 + i, ret=10.0 + i, seq=i, start=100 * i) for i in range(n)]


def test_demos_round_trip(tmp_path, spec):
    eps = _demos()
    save_demos(tmp_path / "d.npz", ENV, eps)
    back = load_demos(tmp_path / "d.npz", spec)
    assert [e.length for e in back] == [5, 6, 7]
    for a, b in zip(eps, back):
        np.testing.assert_array_equal(a.obs, b.obs)
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.rewards, b.rewards)
        assert (a.episode_return, a.terminated, a.truncated) == (b.episode_return, b.terminated, b.truncated)
    assert [p.name for p in tmp_path.iterdir()] == ["d.npz"]  # written atomically, no temporary left


def _rewrite(path, **changes):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    for k in [k for k, v in changes.items() if v is None]:
        del arrays[k]
    np.savez(path, **arrays)


@pytest.mark.parametrize("change, message", [
    ({"env": np.array("Hopper-v5")}, "demonstrations are for Hopper-v5, but this run's env is InvertedPendulum-v5"),
    ({"obs": np.zeros((21, 5), np.float32)}, "obs has shape (21, 5), expected (21, 4)"),
    ({"actions": np.zeros((17, 1), np.float32)}, "actions has shape (17, 1), expected (18, 1)"),
    ({"actions": np.full((18, 1), 2.0, np.float32)}, "episode 0: actions must be the policy's squashed outputs in [-1, 1]"),
    ({"rewards": np.full(18, np.nan, np.float32)}, "episode 0: episode contains NaN or infinite values"),
    ({"returns": np.array([1.0, 2.0, 3.0])}, "differs from the sum of rewards"),
    ({"episode_lengths": np.array([5, 0, 13])}, "episode_lengths must be a non-empty list of positive integers"),
    ({"version": np.array(7)}, "version 7 is not supported"),
    ({"rewards": None}, "not a silcr demonstrations file (missing rewards)"),
])
def test_demos_rejections_name_the_problem(tmp_path, spec, change, message):
    path = tmp_path / "d.npz"
    save_demos(path, ENV, _demos())
    _rewrite(path, **change)
    with pytest.raises(DemosError) as e:
        load_demos(path, spec)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_corrupt_demos_file_is_refused(tmp_path, spec):
    path = tmp_path / "d.npz"
    save_demos(path, ENV, _demos())
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(DemosError, match="unreadable or corrupt"):
        load_demos(path, spec)
    with pytest.raises(DemosError, match="no such demonstrations file"):
        load_demos(tmp_path / "missing.npz", spec)


def test_sqil_batches_are_half_online_at_0_and_half_demos_at_1(tmp_path, spec):
    demos = [make_episode(20, ret=50.0, seq=i, start=1000 + 100 * i) for i in range(2)]
    save_demos(tmp_path / "d.npz", ENV, demos)
    cfg = Config(run="sqil", env=ENV, algo="sqil", demos=str(tmp_path / "d.npz"), learning_starts=10)
    state = ReplayState(cfg, spec)
    assert len(state.heap) == 40 and state.heap.num_episodes == 2
    for i in range(5):  # online episodes, one of them better than the demos
        state.intake.ingest(make_episode(10, ret=500.0 if i == 3 else 1.0, seq=i, start=10 * i).encode())
    assert len(state.heap) == 40 and state.heap.max_return == 50.0  # D_E never changes
    reply = state.sampler.answer(P.SampleRequest(4, 64).encode())
    assert reply.status == "ok"
    obs, rew = reply.batch.obs[:, 0].reshape(4, 64), reply.batch.rewards.reshape(4, 64)
    assert (rew[:, :32] == 0).all() and (rew[:, 32:] == 1).all()
    assert (obs[:, :32] < 1000).all() and (obs[:, 32:] >= 1000).all()  # online rows first, then demonstration rows


def test_demos_command_records_a_checkpoint_and_sqil_accepts_it(tmp_path):
    import torch

    from silcr.learner.checkpoint import save_checkpoint
    from silcr.learner.sac import Sac, SacHyper

    torch.manual_seed(0)
    sac = Sac(4, 1, [16], SacHyper(), torch.device("cpu"))
    ckpt = tmp_path / "learner.pt"
    save_checkpoint(ckpt, {"sac": sac.state_dict(), "counters": {"policy_version": 3},
                           "config": Config(run="ck", env=ENV, hidden=[16]).to_dict()})
    out = tmp_path / "demos.npz"
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "demos", str(ckpt), "--episodes", "3", "-o", str(out)],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "wrote" in r.stdout and "3 episodes" in r.stdout
    eps = load_demos(out, EnvSpec.of(ENV))
    assert len(eps) == 3 and all(e.terminated or e.truncated for e in eps)

    # The buffer's option check loads the file: a wrong env is one line and exit code 2.
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "buffer", "--run", "x", "--env", "Hopper-v5", "--algo", "sqil",
                        "--demos", str(out)], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2 and "--demos" in r.stderr and "InvertedPendulum-v5" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "buffer", "--run", "x", "--env", ENV, "--algo", "sqil"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2 and "needs a demonstrations file" in r.stderr


def test_a_warm_started_expert_buffer_gives_way_only_to_better_own_episodes(tmp_path, spec):
    """--expert-init: demonstrations enter D_E first and are ranked and evicted like the agent's own episodes."""
    from silcr.buffer_service import snapshot
    from silcr.buffer_service.service import open_replay

    save_demos(tmp_path / "d.npz", ENV, [make_episode(20, ret=r, seq=i, start=1000 * (i + 1))
                                         for i, r in enumerate([50.0, 60.0, 70.0])])
    cfg = Config(run="warm", runs_dir=str(tmp_path), env=ENV, expert_capacity=40, learning_starts=10,
                 expert_init=str(tmp_path / "d.npz"))
    state, _ = open_replay(cfg, spec)
    assert sorted([e.episode_return for e in state.heap.episodes()]) == [60.0, 70.0]  # the best that fit M = 40, best first
    assert state.stats()["expert_init_transitions"] == 40
    for i in range(5):  # worse own episodes: the demonstrations stay
        state.intake.ingest(make_episode(20, ret=10.0 + i, seq=i).encode())
    assert sorted([e.episode_return for e in state.heap.episodes()]) == [60.0, 70.0] and state.stats()["expert_init_transitions"] == 40
    state.intake.ingest(make_episode(20, ret=65.0, seq=5).encode())  # better than one of them
    assert sorted([e.episode_return for e in state.heap.episodes()]) == [65.0, 70.0] and state.stats()["expert_init_transitions"] == 20
    # A checkpoint keeps them as demonstrations, and a resumed buffer does not add them again.
    snapshot.write(tmp_path / "warm" / "checkpoints" / "buffer.ckpt", snapshot.take(state))
    back, snap = open_replay(Config(**cfg.to_dict() | {"resume": True}), spec)
    assert snap is not None and sorted([e.episode_return for e in back.heap.episodes()]) == [65.0, 70.0]
    assert back.stats()["expert_init_transitions"] == 20
    state.intake.ingest(make_episode(20, ret=90.0, seq=6).encode())  # evicts the lowest: the agent's 65
    assert sorted([e.episode_return for e in state.heap.episodes()]) == [70.0, 90.0] and state.stats()["expert_init_transitions"] == 20
    state.intake.ingest(make_episode(20, ret=95.0, seq=7).encode())
    assert state.stats()["expert_init_transitions"] == 0  # all pushed out by better own episodes
