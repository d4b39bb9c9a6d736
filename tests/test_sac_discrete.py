"""Discrete-action SAC (issue 19, item 1): the update's terms against a hand computation on a 2-state,
2-action case, and the whole update learning a two-state task where each state has its own best action."""

from __future__ import annotations

import math

import pytest
import torch

from silcr.learner import sac_discrete as D

ALPHA, GAMMA = 0.5, 0.9


def t(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float32)


def test_the_soft_target_is_the_exact_expectation_over_next_actions():
    next_probs = t([[0.25, 0.75], [0.6, 0.4]])
    q1_next, q2_next = t([[1.0, 2.0], [4.0, 0.0]]), t([[1.5, 1.0], [3.0, 9.0]])
    y = D.soft_target(t([1.0, 0.0]), t([0.0, 1.0]), next_probs, next_probs.log(), q1_next, q2_next, t(ALPHA), GAMMA)
    # row 0: min_j Q = [1.0, 1.0]; V = 0.25 (1 - 0.5 ln 0.25) + 0.75 (1 - 0.5 ln 0.75)
    v0 = 0.25 * (1.0 - ALPHA * math.log(0.25)) + 0.75 * (1.0 - ALPHA * math.log(0.75))
    # row 1 ends the episode: y = r, whatever comes after
    assert y.tolist() == pytest.approx([1.0 + GAMMA * v0, 0.0], abs=1e-6)
    assert v0 == pytest.approx(1.281168, abs=1e-6)  # 1 + alpha * H(0.25, 0.75), H = 0.562335 nats


def test_each_critic_is_scored_on_the_action_taken():
    q1, q2 = t([[0.5, 3.0], [1.0, 0.0]]), t([[1.0, 2.0], [0.5, 0.5]])
    y = t([2.0, 0.25])
    l1, l2 = D.critic_losses(q1, q2, torch.tensor([1, 0]), y)
    assert l1.item() == pytest.approx(((3.0 - 2.0) ** 2 + (1.0 - 0.25) ** 2) / 2)
    assert l2.item() == pytest.approx(((2.0 - 2.0) ** 2 + (0.5 - 0.25) ** 2) / 2)


def test_the_policy_and_temperature_losses_are_exact_over_actions():
    probs = t([[0.5, 0.5], [0.9, 0.1]])
    q1, q2 = t([[0.5, 3.0], [1.0, 0.0]]), t([[1.0, 2.0], [0.5, 0.5]])
    # min_j Q = [[0.5, 2.0], [0.5, 0.0]]
    row0 = 0.5 * (ALPHA * math.log(0.5) - 0.5) + 0.5 * (ALPHA * math.log(0.5) - 2.0)
    row1 = 0.9 * (ALPHA * math.log(0.9) - 0.5) + 0.1 * (ALPHA * math.log(0.1) - 0.0)
    assert D.actor_loss(probs, probs.log(), q1, q2, t(ALPHA)).item() == pytest.approx((row0 + row1) / 2, abs=1e-6)
    log_alpha = t(math.log(ALPHA)).requires_grad_(True)
    target = 0.89 * math.log(2)
    neg_h = [0.5 * math.log(0.5) * 2, 0.9 * math.log(0.9) + 0.1 * math.log(0.1)]
    loss = D.alpha_loss(log_alpha, probs, probs.log(), target)
    assert loss.item() == pytest.approx(-math.log(ALPHA) * sum(h + target for h in neg_h) / 2, abs=1e-6)
    loss.backward()
    # row 0 is uniform (entropy ln 2 > target), row 1 is sure (entropy 0.33 < target): on average
    # the entropy is below the target, so the gradient step raises alpha
    assert log_alpha.grad.item() < 0


def test_the_update_learns_a_different_best_action_in_each_state():
    torch.manual_seed(0)
    sac = D.DiscreteSac(2, 2, [32, 32], D.DiscreteSacHyper(lr=3e-3), torch.device("cpu"))
    obs = torch.eye(2).repeat(64, 1)  # states s0 = [1, 0] and s1 = [0, 1], 64 rows each
    g = torch.Generator().manual_seed(1)
    for _ in range(400):
        actions = torch.randint(0, 2, (128,), generator=g)
        rewards = (actions == obs.argmax(-1)).float()  # s0 pays for action 0, s1 for action 1
        out = sac.update(obs, actions, rewards, obs, torch.ones(128), torch.zeros(128))
    q1, q2 = sac.critic(torch.eye(2))
    assert q1[0, 0] > q1[0, 1] + 0.5 and q1[1, 1] > q1[1, 0] + 0.5 and q2[0, 0] > q2[0, 1] + 0.5
    assert sac.actor.act(torch.eye(2), deterministic=True).tolist() == [0, 1]
    probs, _ = sac.actor.probs_and_log_probs(torch.eye(2))
    assert probs[0, 0] > 0.6 and probs[1, 1] > 0.6
    assert out["entropy"].item() == pytest.approx(sac.target_entropy, abs=0.25)  # the temperature found its target


def test_an_absorbing_terminal_pays_the_label_and_the_policys_entropy_forever():
    from silcr.learner.sac import absorbing

    # row 0 ends (done): its target r becomes r + gamma (r + alpha H) / (1 - gamma); row 1 goes on unchanged
    entropy = t(0.6)
    y = absorbing(t([1.0, 5.0]), t([1.0, 1.0]), t([1.0, 0.0]), t(ALPHA), entropy, GAMMA)
    assert y.tolist() == pytest.approx([1.0 + GAMMA * (1.0 + ALPHA * 0.6) / (1 - GAMMA), 5.0], abs=1e-5)
    # = (r + gamma alpha H) / (1 - gamma): within the soft-Q bound, whose H is the largest entropy
    assert y[0].item() == pytest.approx((1.0 + GAMMA * ALPHA * 0.6) / (1 - GAMMA), abs=1e-5)
