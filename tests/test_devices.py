"""The learner on each device: the SAC, discrete-SAC and GASIL updates with each critic option and the soft-Q
bound's clip on the CPU and, where torch sees one, on CUDA; and a model trained on CUDA read back and trained on
a CPU (and the reverse), through the Python API. The CUDA cases are skipped where there is no GPU, as on CI; on a
GPU box run `pytest tests/test_devices.py`. The rest of the suite uses the GPU there too, since `--device auto`
(the command line's default) picks CUDA when present."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from silcr import SILCR
from silcr.learner import sac_discrete as D
from silcr.learner.gasil import Gasil, GasilHyper
from silcr.learner.sac import LOG2, Sac, SacHyper, as_floats
from tests.test_api import ENV, SMALL, _observations
from tests.test_critic_options import GAMMA, _batch, _runaway_target
from tests.test_gasil import _two_sets

NEEDS_GPU = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
DEVICES = ["cpu", pytest.param("cuda", marks=NEEDS_GPU)]

CRITIC_OPTIONS = [{}, {"critic_norm": "layer"}, {"target_reward_max": 1.0},
                  {"critic_norm": "layer", "target_reward_max": 1.0}]


def _on(device: torch.device, tensors) -> tuple[torch.Tensor, ...]:
    return tuple(t.to(device) for t in tensors)


def _all_on(device: torch.device, *modules) -> bool:
    return all(p.device.type == device.type for m in modules for p in m.parameters())  # cuda:0 is not torch.device('cuda')


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("options", CRITIC_OPTIONS, ids=lambda o: "+".join(o) or "default")
def test_sac_trains_on_the_device_with_each_critic_option(options, device):
    dev = torch.device(device)
    torch.manual_seed(0)
    sac = Sac(3, 2, [64, 64], SacHyper(gamma=GAMMA, **options), dev)
    before = [p.detach().clone() for p in sac.critic.parameters()]
    batch = _on(dev, _batch(n=64))
    for _ in range(200):
        stats = sac.update(*batch)
    assert all(t.device.type == dev.type for t in stats.values())  # nothing falls back to the host
    stats = as_floats(stats)
    assert all(math.isfinite(v) for v in stats.values()), stats
    assert _all_on(dev, sac.actor, sac.critic, sac.critic_target) and sac.log_alpha.device.type == dev.type
    assert any(not torch.equal(b, p) for b, p in zip(before, sac.critic.parameters()))
    assert stats["q_mean"] > 0  # half the labels are 1: Q rises from its start near 0


@pytest.mark.parametrize("device", DEVICES)
def test_the_clip_holds_the_bound_on_the_device(device):
    dev = torch.device(device)
    torch.manual_seed(0)
    sac = Sac(3, 2, [8], SacHyper(gamma=GAMMA, init_alpha=0.2, target_reward_max=1.0), dev)
    _runaway_target(sac.critic_target, 1e6)
    stats = as_floats(sac.update(*_on(dev, _batch())))
    assert stats["target_q_mean"] == pytest.approx((1.0 + GAMMA * 0.2 * 2 * LOG2) / (1 - GAMMA), rel=1e-5)
    assert stats["q_target_clipped"] == 1.0
    assert float(sac.q_bound_exceeded) == 0  # the watch counts on the device and reads back as a number


@pytest.mark.parametrize("device", DEVICES)
def test_discrete_sac_trains_on_the_device(device):
    dev = torch.device(device)
    torch.manual_seed(0)
    sac = D.DiscreteSac(3, 4, [32, 32], D.DiscreteSacHyper(gamma=GAMMA, critic_norm="layer", target_reward_max=1.0),
                        dev)
    obs, _, rewards, nxt, term, trunc = _on(dev, _batch(n=64))
    actions = torch.randint(0, 4, (64,), device=dev)
    for _ in range(100):
        stats = sac.update(obs, actions, rewards, nxt, term, trunc)
    stats = as_floats(stats)
    assert all(math.isfinite(v) for v in stats.values()), stats
    assert _all_on(dev, sac.actor, sac.critic, sac.critic_target)


@pytest.mark.parametrize("device", DEVICES)
def test_the_gasil_discriminator_trains_and_pays_on_the_device(device):
    dev = torch.device(device)
    torch.manual_seed(0)
    gasil = Gasil(4, 1, GasilHyper(), dev)
    gen = torch.Generator().manual_seed(1)
    for _ in range(300):
        stats = gasil.update(*_on(dev, _two_sets(64, gen)))
    assert stats["disc_acc_expert"] > 0.95 and stats["disc_acc_policy"] > 0.95
    expert_obs, expert_act, recent_obs, recent_act = _on(dev, _two_sets(256, gen))
    r_expert, r_policy = gasil.reward(expert_obs, expert_act), gasil.reward(recent_obs, recent_act)
    assert r_expert.device.type == dev.type and r_expert.min() > r_policy.max()


@NEEDS_GPU
@pytest.mark.parametrize("trained_on, resumed_on", [("cuda", "cpu"), ("cpu", "cuda")])
def test_a_model_moves_between_gpu_and_cpu_with_its_training_state(tmp_path, trained_on, resumed_on):
    """A run trained on one device, saved with its critics, optimisers and buffers, goes on learning on the
    other; its policy gives the same actions on both (the actors always run it on a CPU)."""
    model = SILCR(ENV, runs_dir=tmp_path / "a", seed=5, device=trained_on, **SMALL)
    model.learn(1000)
    obs = _observations()
    actions = model.predict(obs, deterministic=True)[0]
    model.save(tmp_path / "m.silcr", include_training_state=True)
    model.close()
    moved = SILCR.load(tmp_path / "m.silcr", include_training_state=True, runs_dir=tmp_path / "b", device=resumed_on)
    assert np.array_equal(moved.predict(obs, deterministic=True)[0], actions)
    moved.learn(500)
    assert moved.num_timesteps >= 1500
    assert np.all(np.isfinite(moved.predict(obs, deterministic=True)[0]))
    moved.close()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize("role", ["train", "learner"])
def test_device_cuda_without_a_gpu_is_refused_by_every_way_of_training(role, tmp_path):
    """`silcr train --device cuda` and `silcr learner --device cuda` exit 2 with one line and write nothing; the
    Python API raises ValueError naming `device`: one check (deploy/preflight.py) for every launcher (issue 62)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "silcr.cli", role, "--env", "InvertedPendulum-v5", "--device", "cuda",
                        "--runs-dir", str(tmp_path / "runs"), "--run", "c"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].endswith("--device: CUDA is not available on this machine"), r.stderr
    assert not (tmp_path / "runs").exists()
    from silcr import SILCR

    with pytest.raises(ValueError, match="^device: CUDA is not available"):
        SILCR("InvertedPendulum-v5", device="cuda", runs_dir=tmp_path / "api")
    assert not (tmp_path / "api").exists()
