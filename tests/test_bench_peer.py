"""`silcr bench peer` (issue 21): silcr and Stable-Baselines3 are given the same work, and the quick bench
runs both and reports ratios. The measured table is docs/performance.md's, not a test's."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch
from torch import nn

from silcr.bench.peer import PeerConfig
from silcr.cli import build_parser
from silcr.common.config import resolve
from silcr.common.envs import EnvSpec
from silcr.learner.sac import Sac, SacHyper
from tests.helpers import REPO

sb3 = pytest.importorskip("stable_baselines3")  # the test extra installs it; `.[bench]` for users


def _linears(module: nn.Module) -> list[tuple[int, int]]:
    return [(m.in_features, m.out_features) for m in module.modules() if isinstance(m, nn.Linear)]


@pytest.mark.parametrize("hidden", [(256, 256), (800, 400)])
def test_both_libraries_build_the_same_networks_and_batches(tmp_path, hidden):
    import gymnasium as gym

    peer = PeerConfig(hidden=hidden)
    parser, _ = build_parser()
    argv = peer.silcr_args(tmp_path, "peer", single_process=True)
    cfg = resolve(parser.parse_args(argv), "train")
    spec = EnvSpec.of(cfg.env)
    mine = Sac(spec.obs_dim, spec.act_dim, cfg.hidden, SacHyper(cfg.gamma, cfg.tau, cfg.lr), torch.device("cpu"))
    theirs = sb3.SAC(env=gym.make(peer.env_id), **peer.sb3_kwargs())

    # the actor's trunk and heads, and each critic, layer by layer
    assert _linears(mine.actor.trunk) == _linears(theirs.actor.latent_pi)
    assert _linears(mine.actor.mean) == _linears(theirs.actor.mu)
    critic = [(w.shape[1], w.shape[2]) for w in mine.critic.weights]
    assert mine.critic.weights[0].shape[0] == theirs.critic.n_critics == 2
    assert critic == _linears(theirs.critic.qf0) == _linears(theirs.critic.qf1)
    # what each update is made of
    assert cfg.batch_size == theirs.batch_size == 128
    assert (cfg.lr, cfg.tau, cfg.gamma) == (theirs.learning_rate, theirs.tau, theirs.gamma)
    assert cfg.learning_starts == theirs.learning_starts and cfg.total_steps == peer.total_steps
    assert (theirs.train_freq.frequency, theirs.gradient_steps) == (1, 1) and cfg.samples_per_insert == 1.0
    assert (cfg.algo, cfg.reward, cfg.eval_episodes) == ("sac", "dense", 0)
    assert theirs.target_entropy == -spec.act_dim == mine.target_entropy


@pytest.mark.slow
def test_the_quick_peer_bench_runs_all_three_programs_on_the_same_work(tmp_path):
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "bench", "peer", "--quick", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=900, cwd=REPO)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "silcr against Stable-Baselines3" in r.stdout
    result = json.loads((tmp_path / "peer.json").read_text())["results"][0]
    runs = {x["program"]: x for x in result["runs"]}
    assert set(runs) == {"sb3", "distributed", "single-process"}
    # the same budget and, within a few (where each program stops its last step), the same updates
    assert all(x["env_steps"] >= 800 for x in runs.values()), runs
    assert max(x["updates"] for x in runs.values()) - min(x["updates"] for x in runs.values()) <= 6, runs
    for key in ("distributed_wall", "distributed_cpu", "single-process_wall", "single-process_cpu",
                "distributed_rate_vs_floor", "single-process_rate_vs_floor"):
        s = result["ratios"][key]
        assert 0 < s["min"] <= s["median"] <= s["max"], result["ratios"]
    # silcr's learners reported their training span in their logs, and the bench timed the update alone
    for program in ("distributed", "single-process"):
        run = runs[program]
        assert run["threads"] >= 1 and run["span_updates"] == run["updates"] and run["floor_ms"] > 0, run
        assert 0 < run["in_updates_s"] <= run["span_s"] and 0 < run["duty_cycle"] <= 1, run


def test_the_peer_runs_without_silcrs_thread_pool_defaults_but_with_the_users(monkeypatch):
    """SB3 must run as a user would: silcr's OMP_WAIT_POLICY=PASSIVE and one OpenBLAS thread are not its
    defaults (and the first is what makes a 2-thread torch slower here), while what the user set stays."""
    import os

    import silcr.common.process_env as process_env
    from silcr.bench.peer import _peer_env

    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE" or process_env.ENV_BEFORE_DEFAULTS["OMP_WAIT_POLICY"] is not None
    monkeypatch.setattr(process_env, "ENV_BEFORE_DEFAULTS", {"OMP_WAIT_POLICY": None, "OPENBLAS_NUM_THREADS": "3"})
    env = _peer_env()
    assert "OMP_WAIT_POLICY" not in env and env["OPENBLAS_NUM_THREADS"] == "3"
    assert env["PATH"] == os.environ["PATH"]
