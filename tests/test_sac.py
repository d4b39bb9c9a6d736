"""SAC update math on tiny cases, checked against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from silcr.actor.policy import NumpyPolicy, initial_weights
from silcr.common.protocol import Weights
from silcr.learner.sac import Actor, Sac, SacHyper, TwinCritic, as_floats


def _sac(**hp) -> Sac:
    torch.manual_seed(0)
    return Sac(3, 2, [8], SacHyper(**hp), torch.device("cpu"))


def _batch(n=4, terminated=None, truncated=None, rewards=None):
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(n, 3, generator=g)
    act = torch.rand(n, 2, generator=g) * 2 - 1
    nxt = torch.randn(n, 3, generator=g)
    term = torch.zeros(n) if terminated is None else torch.tensor(terminated, dtype=torch.float32)
    trunc = torch.zeros(n) if truncated is None else torch.tensor(truncated, dtype=torch.float32)
    r = torch.zeros(n) if rewards is None else torch.tensor(rewards, dtype=torch.float32)
    return obs, act, r, nxt, term, trunc


def _constant_critic(sac: Sac, value: float) -> None:
    """Make both target critics output `value` everywhere."""
    with torch.no_grad():
        for p in sac.critic_target.parameters():
            p.zero_()
        sac.critic_target.biases[-1].fill_(value)


def _fixed_policy(sac: Sac, logp: float) -> None:
    def sample(obs):
        a = torch.zeros(obs.shape[0], 2)
        return a + 0 * sac.actor(obs)[0], torch.full((obs.shape[0],), logp) + 0 * sac.actor(obs)[0].sum(-1)

    sac.actor.sample = sample  # type: ignore[method-assign]


def _expected_critic_loss(sac, obs, act, y):
    with torch.no_grad():
        q1, q2 = sac.critic(obs, act)
        return float((((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean()) / 2)


@pytest.mark.parametrize("time_limit_terminal", [False, True])
def test_soft_target_and_terminal_masking(time_limit_terminal):
    """Eq. 5: y = r + gamma (1 - done) (min Q' - alpha log pi); truncation bootstraps unless asked not to."""
    sac = _sac(gamma=0.9, init_alpha=0.5, time_limit_terminal=time_limit_terminal)
    _constant_critic(sac, 10.0)
    _fixed_policy(sac, logp=-2.0)
    obs, act, r, nxt, term, trunc = _batch(rewards=[1.0, 0.0, 1.0, 0.0], terminated=[0, 1, 0, 0], truncated=[0, 0, 1, 0])
    bootstrap = 0.9 * (10.0 - 0.5 * -2.0)  # 9.9
    done = np.array([0, 1, 1 if time_limit_terminal else 0, 0])
    y = torch.tensor(np.array([1.0, 0.0, 1.0, 0.0]) + (1 - done) * bootstrap, dtype=torch.float32)
    expected = _expected_critic_loss(sac, obs, act, y)
    out = as_floats(sac.update(obs, act, r, nxt, term, trunc))
    assert out["critic_loss"] == pytest.approx(expected, rel=1e-5)
    assert out["alpha"] == pytest.approx(0.5)


def test_target_critics_follow_with_tau():
    sac = _sac(tau=0.25)
    before_tgt = [p.clone() for p in sac.critic_target.parameters()]
    sac.update(*_batch())
    for old, tgt, online in zip(before_tgt, sac.critic_target.parameters(), sac.critic.parameters()):
        torch.testing.assert_close(tgt, 0.75 * old + 0.25 * online)


def test_alpha_moves_towards_target_entropy():
    sac = _sac(init_alpha=1.0)
    _fixed_policy(sac, logp=5.0)  # entropy -5, far below the target -|A| = -2: alpha must grow
    sac.update(*_batch())
    assert sac.alpha > 1.0
    sac2 = _sac(init_alpha=1.0)
    _fixed_policy(sac2, logp=-5.0)  # entropy 5 > -2: alpha must shrink
    sac2.update(*_batch())
    assert sac2.alpha < 1.0


def test_constant_reward_one_drives_q_up_and_zero_keeps_it_low():
    """SILCR's signal: with r=1 on one set of states and r=0 elsewhere, Q separates them."""
    sac = _sac(gamma=0.5)
    g = torch.Generator().manual_seed(2)
    expert_obs = torch.randn(64, 3, generator=g) + 3.0
    online_obs = torch.randn(64, 3, generator=g) - 3.0
    obs = torch.cat([online_obs, expert_obs])
    act = torch.zeros(128, 2)
    r = torch.cat([torch.zeros(64), torch.ones(64)])
    zeros = torch.zeros(128)
    for _ in range(300):
        sac.update(obs, act, r, obs, zeros, zeros)
    with torch.no_grad():
        q_exp = sac.critic(expert_obs, torch.zeros(64, 2))[0].mean()
        q_on = sac.critic(online_obs, torch.zeros(64, 2))[0].mean()
    assert q_exp > q_on + 0.5


def test_gradient_clipping_bounds_the_step():
    sac = _sac(grad_clip=1e-3, lr=1.0)
    before = [p.clone() for p in sac.critic.parameters()]
    sac.update(*_batch(rewards=[1e6] * 4))
    # Adam's first step moves each parameter by about lr whatever the gradient size; clipping
    # must not produce NaN or blow up.
    for b, p in zip(before, sac.critic.parameters()):
        assert torch.isfinite(p).all() and (p - b).abs().max() <= 1.0 + 1e-4


def test_log_prob_matches_tanh_change_of_variables():
    torch.manual_seed(0)
    actor = Actor(3, 1, [16])
    obs = torch.randn(5000, 3)
    a, logp = actor.sample(obs)
    mean, log_std = actor(obs)
    u = torch.atanh(a.clamp(-0.999999, 0.999999))
    normal = torch.distributions.Normal(mean, log_std.exp())
    ref = normal.log_prob(u).sum(-1) - torch.log(1 - a.pow(2) + 1e-6).sum(-1)
    mask = a.abs().squeeze(-1) < 0.99
    torch.testing.assert_close(logp[mask], ref[mask], rtol=1e-3, atol=1e-3)


def test_numpy_policy_matches_torch_actor():
    torch.manual_seed(0)
    sac = Sac(5, 3, [16, 8], SacHyper(), torch.device("cpu"))
    w = Weights(3, sac.actor_arrays(), sac.arch())
    pol = NumpyPolicy(w, 5, 3)
    obs = np.random.default_rng(0).normal(size=(7, 5)).astype(np.float32)
    expected = sac.actor.act_deterministic(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(pol.deterministic(obs), expected, atol=1e-5)
    s = pol.sample(obs, np.random.default_rng(0))
    assert s.shape == (7, 3) and (np.abs(s) <= 1).all()
    # the stochastic action is tanh(mean + std * noise) with the rng's next normals
    noise = np.random.default_rng(0).standard_normal((7, 3), dtype=np.float32)
    with torch.no_grad():
        mean, log_std = sac.actor(torch.from_numpy(obs))
    np.testing.assert_allclose(s, np.tanh(mean.numpy() + np.exp(log_std.numpy()) * noise), atol=1e-5)
    # one observation without a batch axis, as `learner.evaluate.rollout` passes it
    np.testing.assert_allclose(pol.deterministic(obs[0]), expected[0], atol=1e-5)


def test_initial_weights_shape_matches_learner_layout():
    sac = Sac(5, 3, [16, 8], SacHyper(), torch.device("cpu"))
    w = initial_weights(5, 3, [16, 8], seed=0)
    assert {k: v.shape for k, v in w.params.items()} == {k: v.shape for k, v in sac.actor_arrays().items()}
    NumpyPolicy(w, 5, 3)  # loads


def test_twin_critic_is_two_independent_mlps():
    torch.manual_seed(0)
    twin = TwinCritic(3, 2, [8, 4])
    obs, act = torch.randn(5, 3), torch.randn(5, 2)
    q = twin(obs, act)
    x = torch.cat([obs, act], -1)
    for j in (0, 1):
        h = x
        for i, (w, b) in enumerate(zip(twin.weights, twin.biases)):
            h = h @ w[j] + b[j]
            if i < 2:
                h = torch.relu(h)
        torch.testing.assert_close(q[j], h.squeeze(-1))
    assert not torch.allclose(q[0], q[1])  # independently initialised


def test_twin_critic_clips_each_critic_separately():
    torch.manual_seed(0)
    twin = TwinCritic(3, 2, [8])
    obs, act = torch.randn(5, 3), torch.randn(5, 2)
    q1, q2 = twin(obs, act)
    (1000 * q1.sum() + 1e-3 * q2.sum()).backward()
    small_before = [p.grad[1].clone() for p in twin.parameters()]
    twin.clip_grad_norm_(1.0)
    norm = lambda j: torch.sqrt(sum((p.grad[j] ** 2).sum() for p in twin.parameters()))  # noqa: E731
    assert norm(0) == pytest.approx(1.0, rel=1e-4)
    for before, p in zip(small_before, twin.parameters()):
        torch.testing.assert_close(p.grad[1], before)  # the small one is left alone


def test_a_restored_state_continues_exactly_as_the_original(tmp_path):
    """Checkpoint round trip: networks, target critics, optimizer moments and alpha all come back."""
    from silcr.learner.checkpoint import load_checkpoint, save_checkpoint

    a = _sac()
    for _ in range(3):
        a.update(*_batch(8, rewards=[1.0] * 8))
    save_checkpoint(tmp_path / "c.pt", {"sac": a.state_dict(), "counters": {}})
    torch.manual_seed(123)
    b = Sac(3, 2, [8], SacHyper(), torch.device("cpu"))
    b.load_state_dict(load_checkpoint(tmp_path / "c.pt")["sac"])
    assert b.alpha == a.alpha
    torch.manual_seed(7)
    la = a.update(*_batch(8, rewards=[1.0] * 8))
    torch.manual_seed(7)
    lb = b.update(*_batch(8, rewards=[1.0] * 8))
    assert as_floats(la) == as_floats(lb)
    for pa, pb in zip([*a.actor.parameters(), *a.critic.parameters(), *a.critic_target.parameters()],
                      [*b.actor.parameters(), *b.critic.parameters(), *b.critic_target.parameters()]):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0)
