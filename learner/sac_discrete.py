"""Soft actor-critic for discrete actions, top to bottom, beside the continuous `sac.py`.

The paper's equations (`shared/paper/silcr.tex`) are the same; with |A| actions the
policy is categorical and each critic has one output per action, so every expectation
over actions that continuous SAC estimates with one sampled action is computed
exactly here (Christodoulou 2019, "Soft Actor-Critic for Discrete Action Settings"):
  (3) constant rewards, set by the buffer: this module is the same for SILCR and SAC;
  (4) critic loss J_Q: squared error of Q_j(s, a) for the action taken, per critic;
  (5) soft target y = r + gamma * sum_a' pi(a'|s') [min_j Q_target_j(s', a') - alpha log pi(a'|s')]:
      the soft state value as an exact expectation over a' instead of one sample;
  (6) policy loss J_pi = E_s[ sum_a pi(a|s) (alpha log pi(a|s) - min_j Q_j(s, a)) ]:
      exact, so no reparameterisation is needed;
  temperature J(alpha) = E_s[ -log_alpha * (sum_a pi(a|s) log pi(a|s) + target_entropy) ],
      the continuous form with the entropy computed exactly.
The target entropy is `target_entropy_scale * log |A|`, a fraction of the uniform
policy's entropy. silcr's default fraction is 0.89, as in CleanRL's `sac_atari.py`;
Christodoulou used 0.98, which keeps the policy near uniform for long (a sparse-reward
agent that must commit to a path never does).

The two options that keep critics bounded act as in `sac.py`: `--critic-norm layer` puts a
LayerNorm after each hidden layer of both critics, and `--q-target-clip bound` clips (5)'s target
at the soft-Q bound, with log |A| as the entropy's largest value.

Everything else matches `sac.py`: mean-squared critic loss, the gradient-norm clip per
critic and for the actor, the actor step against the just-updated critics, the alpha
step with that step's probabilities, Polyak averaging after every update, and the
bootstrap masked only on true termination unless `time_limit_terminal`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from silcr.common.config import CRITIC_NORMS

from .sac import QBoundWatch, SacState, _adam, absorbing, clip_target, mlp

#: silcr's default target entropy, as a fraction of log |A| (CleanRL's sac_atari.py; Christodoulou: 0.98;
#: `--target-entropy-scale`)
TARGET_ENTROPY_SCALE = 0.89


@dataclass
class DiscreteSacHyper:
    gamma: float = 0.99
    tau: float = 0.005
    lr: float = 3e-4
    grad_clip: float = 40.0
    init_alpha: float = 1.0
    target_entropy_scale: float = TARGET_ENTROPY_SCALE
    time_limit_terminal: bool = False
    absorbing_terminal: bool = False  # a terminal row's label is paid forever after (`sac.absorbing`)
    critic_norm: str = "none"  # or "layer": LayerNorm after each hidden layer of the critics
    target_reward_max: float | None = None  # --q-target-clip bound: the labels' largest value (`sac.clip_target`)


class CategoricalActor(nn.Module):
    """pi(.|s) over |A| actions, as logits."""

    def __init__(self, obs_dim: int, n_actions: int, hidden: list[int]) -> None:
        super().__init__()
        self.trunk = mlp([obs_dim, *hidden])
        self.logits = nn.Linear(hidden[-1], n_actions)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.logits(self.trunk(obs))

    def probs_and_log_probs(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pi(.|s) and log pi(.|s), each (batch, |A|); log_softmax keeps log pi finite where pi underflows."""
        log_pi = F.log_softmax(self(obs), dim=-1)
        return log_pi.exp(), log_pi

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        """An action index per row: sampled from pi, or the most likely one."""
        logits = self(obs)
        if deterministic:
            return logits.argmax(-1)
        return torch.distributions.Categorical(logits=logits).sample()


class TwinQ(nn.Module):
    """Q_1(s, .) and Q_2(s, .): one output per action (`norm="layer"`: a LayerNorm after each hidden layer)."""

    def __init__(self, obs_dim: int, n_actions: int, hidden: list[int], norm: str = "none") -> None:
        super().__init__()
        if norm not in CRITIC_NORMS:
            raise ValueError(f"critic norm must be one of {CRITIC_NORMS}, got {norm!r}")
        ln = norm == "layer"
        self.q1 = nn.Sequential(mlp([obs_dim, *hidden], layer_norm=ln), nn.Linear(hidden[-1], n_actions))
        self.q2 = nn.Sequential(mlp([obs_dim, *hidden], layer_norm=ln), nn.Linear(hidden[-1], n_actions))

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.q1(obs), self.q2(obs)


def soft_target(rewards: torch.Tensor, done: torch.Tensor, next_probs: torch.Tensor, next_log_probs: torch.Tensor,
                next_q1_target: torch.Tensor, next_q2_target: torch.Tensor, alpha: torch.Tensor,
                gamma: float) -> torch.Tensor:
    """(5), exact over a': y = r + gamma (1 - done) sum_a' pi(a'|s') [min_j Q_target_j(s', a') - alpha log pi(a'|s')]."""
    v_next = (next_probs * (torch.min(next_q1_target, next_q2_target) - alpha * next_log_probs)).sum(-1)
    return rewards + gamma * (1.0 - done) * v_next


def taken(q: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Q(s, a) for each row's action index (`actions`: one index per row, shaped (n,) or (n, 1))."""
    return q.gather(-1, actions.long().reshape(-1, 1)).squeeze(-1)


def critic_losses(q1: torch.Tensor, q2: torch.Tensor, actions: torch.Tensor,
                  y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(4): each critic's Q(s, a) for the action taken, against y."""
    return F.mse_loss(taken(q1, actions), y), F.mse_loss(taken(q2, actions), y)


def actor_loss(probs: torch.Tensor, log_probs: torch.Tensor, q1: torch.Tensor, q2: torch.Tensor,
               alpha: torch.Tensor) -> torch.Tensor:
    """(6), exact over a: E_s[ sum_a pi(a|s) (alpha log pi(a|s) - min_j Q_j(s, a)) ]."""
    return (probs * (alpha * log_probs - torch.min(q1, q2))).sum(-1).mean()


def alpha_loss(log_alpha: torch.Tensor, probs: torch.Tensor, log_probs: torch.Tensor,
               target_entropy: float) -> torch.Tensor:
    """Temperature: -log_alpha * (sum_a pi log pi + target entropy), with pi held fixed."""
    neg_entropy = (probs * log_probs).sum(-1).detach()
    return -(log_alpha * (neg_entropy + target_entropy)).mean()


class DiscreteSac(SacState):
    """Networks, optimizers and the update for |A| discrete actions; `update(batch)` is one step on everything."""

    def __init__(self, obs_dim: int, n_actions: int, hidden: list[int], hp: DiscreteSacHyper,
                 device: torch.device) -> None:
        if n_actions < 2:
            raise ValueError(f"discrete SAC needs at least 2 actions, got {n_actions}")
        self.hp, self.device = hp, device
        self.obs_dim, self.n_actions, self.hidden = obs_dim, n_actions, list(hidden)
        self.actor = CategoricalActor(obs_dim, n_actions, hidden).to(device)
        self.critic = TwinQ(obs_dim, n_actions, hidden, hp.critic_norm).to(device)
        self.critic_target = TwinQ(obs_dim, n_actions, hidden, hp.critic_norm).to(device)
        self.critic_target.load_state_dict(self.critic.state_dict())
        for p in self.critic_target.parameters():
            p.requires_grad_(False)
        self.log_alpha = torch.tensor(float(np.log(hp.init_alpha)), device=device, requires_grad=True)
        self.target_entropy = hp.target_entropy_scale * float(np.log(n_actions))
        self.critic_params = list(self.critic.parameters())
        self.target_params = list(self.critic_target.parameters())
        self.critic_opt = _adam(self.critic_params, hp.lr)
        self.actor_opt = _adam(list(self.actor.parameters()), hp.lr)
        self.alpha_opt = _adam([self.log_alpha], hp.lr)
        # Divergence watch (`q_bound`), as in sac.py: a categorical policy's entropy is at most log |A|.
        self.watch = QBoundWatch(float(np.log(n_actions)), hp, device)

    def arch(self) -> dict:
        return {"obs_dim": self.obs_dim, "n_actions": self.n_actions, "hidden": self.hidden, "action_kind": "discrete"}

    def update(self, obs, actions, rewards, next_obs, terminated, truncated,
               expert_from: int | None = None) -> dict[str, torch.Tensor]:
        """One step on a batch of tensors on `self.device`; `actions` are action indices ((n,) or (n, 1))."""
        hp = self.hp
        alpha = self.log_alpha.exp().detach()
        done = terminated if not hp.time_limit_terminal else torch.maximum(terminated, truncated)

        # (5) the soft target, exact over a'
        with torch.no_grad():
            next_probs, next_log_probs = self.actor.probs_and_log_probs(next_obs)
            y = soft_target(rewards, done, next_probs, next_log_probs, *self.critic_target(next_obs), alpha, hp.gamma)
            if hp.absorbing_terminal:
                entropy = -(next_probs * next_log_probs).sum(-1).mean()
                y = absorbing(y, rewards, done, alpha, entropy, hp.gamma)
            if hp.target_reward_max is not None:  # --q-target-clip bound: no target above what the labels allow
                y, clipped = clip_target(y, hp.target_reward_max, alpha, self.watch.entropy_max, hp.gamma)

        # (4) critic loss for the actions taken
        q1, q2 = self.critic(obs)
        q1_loss, q2_loss = critic_losses(q1, q2, actions, y)
        self.critic_opt.zero_grad(set_to_none=True)
        (q1_loss + q2_loss).backward()
        if hp.grad_clip > 0:
            nn.utils.clip_grad_norm_(self.critic.q1.parameters(), hp.grad_clip)
            nn.utils.clip_grad_norm_(self.critic.q2.parameters(), hp.grad_clip)
        self.critic_opt.step()

        # (6) policy loss, exact over a, against the just-updated critics (held fixed)
        probs, log_probs = self.actor.probs_and_log_probs(obs)
        with torch.no_grad():
            q1_pi, q2_pi = self.critic(obs)
        pi_loss = actor_loss(probs, log_probs, q1_pi, q2_pi, alpha)
        self.actor_opt.zero_grad(set_to_none=True)
        pi_loss.backward()
        if hp.grad_clip > 0:
            nn.utils.clip_grad_norm_(self.actor.parameters(), hp.grad_clip)
        self.actor_opt.step()

        # temperature, with the probabilities of the actor step above
        a_loss = alpha_loss(self.log_alpha, probs, log_probs, self.target_entropy)
        self.alpha_opt.zero_grad(set_to_none=True)
        a_loss.backward()
        self.alpha_opt.step()

        # Polyak averaging of the target critics
        with torch.no_grad():
            torch._foreach_lerp_(self.target_params, self.critic_params, hp.tau)
            q1_a = taken(q1.detach(), actions)
            q_max, q_bound = self.watch.see(torch.maximum(q1_a, taken(q2.detach(), actions)).max(), rewards, alpha)

        entropy = -(probs * log_probs).sum(-1).detach().mean()
        stats = {
            "critic_loss": (q1_loss + q2_loss).detach() / 2,
            "actor_loss": pi_loss.detach(),
            "alpha": alpha,
            "alpha_loss": a_loss.detach(),
            "q_mean": q1_a.mean(),
            "q_max": q_max,
            "target_q_mean": y.mean(),
            "log_pi_mean": -entropy,  # E_a[log pi(a|s)], exact
            "entropy": entropy,
            "q_bound": q_bound,
        }
        if hp.target_reward_max is not None:
            stats["q_target_clipped"] = clipped
        return stats
