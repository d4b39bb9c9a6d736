"""GASIL's discriminator and reward, top to bottom (Guo et al. 2018, "Generative Adversarial
Self-Imitation Learning"; docs/algorithm.md, "GASIL").

GASIL keeps D_E, the top episodes by return (the same table as SILCR's), and trains a
discriminator D(s, a) = sigmoid(f(s, a)) to tell D_E's transitions (label 1) from the
current policy's (label 0). The policy learns from the shaped reward

    r = r_env + alpha_gasil * r_D(s, a)

with r_D computed from the current discriminator for every batch (never stored), so
a reward always says what the discriminator thinks now (DAC does the same).

silcr's GASIL runs on SAC, off-policy, so three things differ from the paper's PPO:
  * negatives come from the newest transitions of D_O (the buffer serves them), not
    from the whole FIFO, which is mostly older policies' data;
  * a gradient penalty keeps the discriminator smooth (DAC, Kostrikov et al. 2019:
    lambda (||grad f(x_hat)|| - 1)^2 at random interpolates x_hat of the two classes);
  * r_D's form is a choice (`REWARD_FORMS`), because Hopper, Walker2d and Humanoid end
    early: a reward that is always positive pays for staying alive, one that is always
    negative pays for falling. `logit` (the default) is f itself, log D - log(1 - D):
    zero where the discriminator cannot tell the two apart, positive where a transition
    looks like D_E's, negative where it looks like the policy's. `positive` is
    -log(1 - D) (GASIL's -log D_pi; ASIL's code), `negative` is log D (GAIL's).

Observations are normalised with running statistics of the discriminator's own
training rows (both classes); actions are already in [-1, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from silcr.common.config import GASIL_REWARD_FORMS

#: normalised observations are clipped to this many standard deviations (outliers early in a run)
OBS_CLIP = 10.0


@dataclass
class GasilHyper:
    alpha: float = 0.1  # GASIL paper
    reward_form: str = "logit"
    hidden: tuple[int, ...] = (100, 100)  # ASIL's discriminator; DAC's is the same size
    lr: float = 3e-4  # Acme's AIL agents use 1e-5 to 3e-4
    grad_penalty: float = 10.0  # DAC
    warmup: int = 0  # discriminator updates before r_D enters the reward


class RunningNorm(nn.Module):
    """Mean and variance of everything seen so far (Chan et al.'s parallel update), as buffers of the module."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(dim, dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.double()
        n = x.shape[0]
        batch_mean = x.mean(0)
        delta = batch_mean - self.mean
        total = self.count + n
        self.mean += delta * n / total
        self.m2 += ((x - batch_mean) ** 2).sum(0) + delta**2 * self.count * n / total
        self.count.fill_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        std = (self.m2 / self.count.clamp(min=1.0)).sqrt().clamp(min=1e-6)
        return ((x - self.mean.to(x.dtype)) / std.to(x.dtype)).clamp(-OBS_CLIP, OBS_CLIP)


class Discriminator(nn.Module):
    """f(s, a): the logit of D(s, a), the probability that (s, a) comes from D_E. Tanh MLP on normalised states."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.norm = RunningNorm(obs_dim)
        sizes = [obs_dim + act_dim, *hidden]
        layers: list[nn.Module] = []
        for fan_in, fan_out in zip(sizes, sizes[1:]):
            layers += [nn.Linear(fan_in, fan_out), nn.Tanh()]
        self.body = nn.Sequential(*layers, nn.Linear(sizes[-1], 1))

    def inputs(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.norm(obs), actions], -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x).squeeze(-1)


def reward_from_logit(logit: torch.Tensor, form: str) -> torch.Tensor:
    """r_D from f = logit D, in the numerically stable forms."""
    if form == "logit":
        return logit  # log D - log(1 - D)
    if form == "positive":
        return F.softplus(logit)  # -log(1 - D) >= 0
    if form == "negative":
        return -F.softplus(-logit)  # log D <= 0
    raise ValueError(f"reward form must be one of {GASIL_REWARD_FORMS}, got {form!r}")


class Gasil:
    """The discriminator, its optimiser and normaliser; `update` trains it, `shape` makes the reward."""

    def __init__(self, obs_dim: int, act_dim: int, hp: GasilHyper, device: torch.device) -> None:
        if hp.reward_form not in GASIL_REWARD_FORMS:
            raise ValueError(f"reward form must be one of {GASIL_REWARD_FORMS}, got {hp.reward_form!r}")
        self.hp = hp
        self.disc = Discriminator(obs_dim, act_dim, tuple(hp.hidden)).to(device)
        self.opt = torch.optim.Adam(self.disc.parameters(), lr=hp.lr)
        self.updates = 0

    def update(self, expert_obs: torch.Tensor, expert_actions: torch.Tensor, recent_obs: torch.Tensor,
               recent_actions: torch.Tensor) -> dict[str, torch.Tensor]:
        """One step on D_E rows (label 1) against recent policy rows (label 0); statistics as 0-dim tensors."""
        self.disc.norm.update(torch.cat([expert_obs, recent_obs]))
        x_e = self.disc.inputs(expert_obs, expert_actions)
        x_p = self.disc.inputs(recent_obs, recent_actions)
        f_e, f_p = self.disc(x_e), self.disc(x_p)
        # GAIL's classification loss with D_E as the positive class
        bce = (F.binary_cross_entropy_with_logits(f_e, torch.ones_like(f_e))
               + F.binary_cross_entropy_with_logits(f_p, torch.zeros_like(f_p))) / 2
        # DAC's gradient penalty at random interpolates of the (normalised) inputs
        eps = torch.rand(x_e.shape[0], 1, device=x_e.device)
        x_hat = (eps * x_e.detach() + (1 - eps) * x_p.detach()).requires_grad_(True)
        grad, = torch.autograd.grad(self.disc(x_hat).sum(), x_hat, create_graph=True)
        penalty = ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        loss = bce + self.hp.grad_penalty * penalty
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.updates += 1
        return {
            "disc_loss": bce.detach(),
            "disc_grad_penalty": penalty.detach(),
            "disc_acc_expert": (f_e.detach() > 0).float().mean(),
            "disc_acc_policy": (f_p.detach() < 0).float().mean(),
        }

    @torch.no_grad()
    def reward(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """r_D(s, a) from the discriminator as it is now."""
        return reward_from_logit(self.disc(self.disc.inputs(obs, actions)), self.hp.reward_form)

    def shape(self, rewards: torch.Tensor, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(r_env + alpha_gasil * r_D, mean r_D) after the warm-up; (r_env, mean r_D) before it."""
        r_d = self.reward(obs, actions)
        if self.updates < self.hp.warmup:
            return rewards, r_d.mean()
        return rewards + self.hp.alpha * r_d, r_d.mean()

    def state_dict(self) -> dict:
        return {"disc": self.disc.state_dict(), "opt": self.opt.state_dict(), "updates": self.updates}

    def load_state_dict(self, sd: dict) -> None:
        self.disc.load_state_dict(sd["disc"])
        self.opt.load_state_dict(sd["opt"])
        self.updates = int(sd["updates"])
