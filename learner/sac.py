"""Soft actor-critic as SILCR uses it: networks and one gradient update, top to bottom.

Equation numbers refer to the paper (`shared/paper/silcr.tex`):
  (3) constant rewards: r = 0 for D_O samples, r = 1 for D_E samples. They arrive
      in the batch already (the buffer service sets them), so this module is the
      same for SILCR and plain SAC; only the rewards differ.
  (4) critic loss J_Q, one squared error per buffer half (the batch concatenates
      B_O and B_E, so a mean over the batch is the sum of the two expectations
      up to the constant 1/2 split);
  (5) soft target y = r + gamma * (min_j Q_target_j(s', a') - alpha log pi(a'|s')),
      a' ~ pi(.|s');
  (6) policy loss J_pi = E[alpha log pi(a|s) - Q(s, a)], a ~ pi(.|s).
Automatic temperature tuning (not in the paper, in the official code):
  J(alpha) = E[-log_alpha * (log pi(a|s) + target_entropy)].

Two options keep the critics bounded where constant labels let them run away (docs/algorithm.md,
"Critics that stay bounded"); `SacHyper` leaves both off, `silcr train`'s `auto` turns both on for the
algorithms whose labels lie in [0, 1] (silcr, sqil, ircr: `common.config.critics_of`), each one place below:
  --critic-norm layer    LayerNorm after each hidden layer of both critics (RLPD, Ball et al. 2023);
  --q-target-clip bound  (5)'s target clipped at the soft-Q bound the labels allow, `soft_q_bound`.

One option adds a term the paper does not have, for keeping what D_E holds (docs/algorithm.md, "Keeping what D_E
holds"); off by default, one place below:
  --bc-weight w  (6) plus w * mean|Q| * mean ||mu(s) - a||^2 over the batch's D_E rows (mu: the policy's mean
                 action): self-imitation (Oh et al. 2018) in TD3+BC's form (Fujimoto and Gu 2021), where mean|Q|
                 makes w free of the critics' scale (TD3+BC's alpha = 2.5 is w = 0.4).

Details follow the official code (docs/algorithm.md lists them), except the
tanh log-probability correction, computed by default in its exact stable form
(see `Actor.sample`; `tanh_log_prob="official"` gives the official one): mean-squared
critic loss without the 1/2, gradient-norm clip 40 per critic and for the actor,
the actor step against the just-updated critics, the alpha step using that
actor step's log-probabilities, soft target update after every update (Table I's
tau = 0.05; silcr's default is 0.005, because 0.05 made the critics diverge:
docs/algorithm.md, "Divergence"). Differs on purpose: the bootstrap is masked only on true termination
(`terminated`), unless `time_limit_terminal` asks for the official behaviour.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from silcr.common.config import CRITIC_NORMS, TANH_LOG_PROB_FORMS

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
LOG2 = float(np.log(2.0))


def mlp(sizes: list[int], inplace: bool = False, layer_norm: bool = False) -> nn.Sequential:
    """Linear + ReLU layers, with a LayerNorm between the two when `layer_norm` (RLPD's critics);
    `inplace` ReLU overwrites the previous layer's fresh output (one allocation fewer)."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if layer_norm:
            layers.append(nn.LayerNorm(sizes[i + 1]))
        layers.append(nn.ReLU(inplace=inplace))
    return nn.Sequential(*layers)


def soft_q_bound(reward_max: torch.Tensor | float, alpha: torch.Tensor, entropy_max: float, gamma: float) -> torch.Tensor:
    """The largest soft Q-value rewards of at most `reward_max` allow: Q <= r_max + gamma (Q_max + alpha H_max)
    gives Q_max = (r_max + gamma alpha H_max) / (1 - gamma), where H_max bounds the policy's entropy."""
    return (reward_max + gamma * alpha * entropy_max) / (1.0 - gamma)


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy; outputs actions in [-1, 1] (rescaled to the env by the caller)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int], inplace: bool = True,
                 tanh_log_prob: str = "exact") -> None:
        super().__init__()
        if tanh_log_prob not in TANH_LOG_PROB_FORMS:
            raise ValueError(f"tanh_log_prob must be one of {TANH_LOG_PROB_FORMS}, got {tanh_log_prob!r}")
        self.trunk = mlp([obs_dim, *hidden], inplace)
        self.mean = nn.Linear(hidden[-1], act_dim)
        self.log_std = nn.Linear(hidden[-1], act_dim)
        self.exact_log_prob = tanh_log_prob == "exact"

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.trunk(obs)
        return self.mean(h), self.log_std(h).clamp(LOG_STD_MIN, LOG_STD_MAX)

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """a ~ pi(.|s) by reparameterisation, and log pi(a|s) with the tanh change of variables."""
        mean, log_std = self(obs)
        std = log_std.exp()
        u = mean + std * torch.randn_like(mean)
        a = torch.tanh(u)
        log_prob = (-0.5 * ((u - mean) / std) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
        if self.exact_log_prob:
            # log(1 - tanh(u)^2) in its exact, stable form. The official log(1 - a^2 + 1e-6) has
            # zero gradient once tanh saturates in float32, so a saturated policy never comes
            # back and alpha grows without bound (seen on Reacher and Hopper; docs/algorithm.md).
            return a, log_prob - (2.0 * (LOG2 - u - F.softplus(-2.0 * u))).sum(-1)
        return a, log_prob - torch.log(1.0 - a.pow(2) + 1e-6).sum(-1)  # the official code's form

    def mean_action(self, obs: torch.Tensor) -> torch.Tensor:
        """The policy's mean action tanh(mu(s)), differentiable (the behaviour-cloning term's)."""
        return torch.tanh(self(obs)[0])

    @torch.no_grad()
    def act_deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        return self.mean_action(obs)


class TwinCritic(nn.Module):
    """Q_1 and Q_2 as one network with stacked weights: each layer is one batched matmul.

    Critic j's layer i is `weights[i][j]` (in x out) and `biases[i][j]`; both are
    initialised as PyTorch's `nn.Linear` is, independently per critic. Same maths
    as two separate MLPs, about 10% faster on a CPU (half the kernel calls).
    With `norm="layer"` each hidden layer is followed by a LayerNorm with its own gain
    and shift per critic (`norm_gains[i][j]`, `norm_shifts[i][j]`, initialised to 1 and 0
    as `nn.LayerNorm`'s), before the ReLU, as RLPD's critics have it.
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int], norm: str = "none") -> None:
        super().__init__()
        if norm not in CRITIC_NORMS:
            raise ValueError(f"critic norm must be one of {CRITIC_NORMS}, got {norm!r}")
        sizes = [obs_dim + act_dim, *hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes, sizes[1:]):
            bound = 1.0 / np.sqrt(fan_in)
            self.weights.append(nn.Parameter(torch.empty(2, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(2, 1, fan_out).uniform_(-bound, bound)))
        self.layer_norm = norm == "layer"
        self.norm_gains = nn.ParameterList()
        self.norm_shifts = nn.ParameterList()
        if self.layer_norm:
            for width in hidden:
                self.norm_gains.append(nn.Parameter(torch.ones(2, 1, width)))
                self.norm_shifts.append(nn.Parameter(torch.zeros(2, 1, width)))

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([obs, act], -1)
        h = x.unsqueeze(0).expand(2, *x.shape)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(b, h, w)
            if i < last:
                if self.layer_norm:  # normalised over each row's units, then each critic's own gain and shift
                    h = torch.addcmul(self.norm_shifts[i], F.layer_norm(h, h.shape[-1:]), self.norm_gains[i])
                h = torch.relu_(h)  # neither baddbmm's nor addcmul's backward needs its output
        q = h.squeeze(-1)
        return q[0], q[1]

    def clip_grad_norm_(self, max_norm: float) -> None:
        """Clip each critic's gradient norm separately, as the official code clips Q_1 and Q_2."""
        grads = [p.grad for p in self.parameters() if p.grad is not None]
        norms = torch.stack([g.reshape(2, -1).norm(dim=1) for g in grads]).norm(dim=0)  # (2,)
        scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
        for g in grads:
            g.mul_(scale.view(2, *([1] * (g.dim() - 1))))


@dataclass
class SacHyper:
    gamma: float = 0.99
    tau: float = 0.005  # Table I: 0.05 (docs/algorithm.md, "Divergence")
    lr: float = 3e-4
    grad_clip: float = 40.0
    init_alpha: float = 1.0
    target_entropy: float | None = None  # default: -act_dim
    time_limit_terminal: bool = False
    tanh_log_prob: str = "exact"  # or "official": log(1 - tanh(u)^2 + 1e-6)
    absorbing_terminal: bool = False  # a terminal row's label is paid forever after (`absorbing`)
    critic_norm: str = "none"  # or "layer": LayerNorm after each hidden layer of the critics
    #: --q-target-clip bound: the largest label the rows can carry (1 for SILCR's, SQIL's and IRCR's
    #: labels), and the TD target is clipped at the soft-Q bound it allows; None: no clip
    target_reward_max: float | None = None
    bc_weight: float = 0.0  # --bc-weight: the behaviour-cloning term on D_E rows in (6); 0: off


#: An update counts as past the soft-Q bound when its largest Q exceeds the bound by
#: more than this fraction of the bound's size (at least 1): fitted critics overshoot
#: a little, diverging ones by orders of magnitude (docs/algorithm.md).
Q_BOUND_SLACK = 0.5


class QBoundWatch:
    """Counts the updates whose largest Q passes the soft-Q bound (divergence), kept on the device.

    A policy's entropy is at most `entropy_max` (d log 2 for actions in [-1, 1]^d, log |A|
    for |A| discrete actions), so a soft Q-value is at most
      (r_max + gamma * alpha * entropy_max) / (1 - gamma).
    Critics carry the entropy bonus of earlier, larger temperatures for about
    1 / (tau (1 - gamma)) updates (the target network moves at rate tau, the horizon
    is 1 / (1 - gamma) backups), so the alpha in the bound is the current one or, if
    larger, a running value that decays to it at that rate: a falling alpha does not
    make healthy critics look divergent. Nothing here waits for the device.
    """

    def __init__(self, entropy_max: float, hp: Any, device: torch.device) -> None:
        """`hp`: the update's hyperparameters (gamma, tau, init_alpha), continuous or discrete."""
        self.entropy_max, self.gamma, self.tau = entropy_max, hp.gamma, hp.tau
        self.reward_max = torch.tensor(float("-inf"), device=device)
        self.alpha_for_bound = torch.tensor(hp.init_alpha, device=device)
        self.exceeded = torch.zeros((), dtype=torch.int64, device=device)

    def see(self, q_max: torch.Tensor, rewards: torch.Tensor, alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Update the bound's inputs and the count of updates past it; return (q_max, q_bound)."""
        torch.maximum(self.reward_max, rewards.max(), out=self.reward_max)
        decayed = torch.lerp(self.alpha_for_bound, alpha, self.tau * (1.0 - self.gamma))
        torch.maximum(decayed, alpha, out=self.alpha_for_bound)
        if self.gamma >= 1.0:  # no discount: no finite bound
            return q_max, torch.tensor(float("inf"), device=q_max.device)
        q_bound = soft_q_bound(self.reward_max, self.alpha_for_bound, self.entropy_max, self.gamma)
        slack = Q_BOUND_SLACK * torch.clamp(q_bound.abs(), min=1.0)
        self.exceeded += (q_max > q_bound + slack).long()
        return q_max, q_bound

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"reward_max": self.reward_max.detach().cpu(), "alpha_for_bound": self.alpha_for_bound.detach().cpu(),
                "exceeded": self.exceeded.detach().cpu()}

    def load_state_dict(self, watch: dict[str, torch.Tensor] | None) -> None:
        if watch is None:  # absent from checkpoints written before it existed
            return
        with torch.no_grad():
            self.reward_max.copy_(watch["reward_max"])
            self.alpha_for_bound.copy_(watch["alpha_for_bound"])
            self.exceeded.copy_(watch["exceeded"])


def absorbing(y: torch.Tensor, rewards: torch.Tensor, done: torch.Tensor, alpha: torch.Tensor, entropy: torch.Tensor,
              gamma: float) -> torch.Tensor:
    """(5) with an absorbing state after termination (after Kostrikov et al. 2019, DAC, and SQIL): the
    episode ends in a state that keeps paying the row's label r and the entropy bonus the policy
    earns now, alpha * `entropy` (its mean entropy over the batch's next states), every step. A
    terminal row's target is r + gamma (r + alpha entropy) / (1 - gamma) instead of r.

    Why (docs/algorithm.md, "Discrete actions"): with constant labels, a plain terminal row stops
    the stream of 1s that D_E rows earn and the entropy bonus too, so on a task whose episodes end
    at success (MiniGrid's goal) ending looks worse than wandering on, and the agent learns to
    avoid the goal. With the policy's own entropy, ending and going on earn the same entropy
    bonus and only the labels tell them apart. Three other choices were measured and failed: the
    label alone (the temperature rose until wandering won again), and the largest or the target
    entropy (a policy below it gained by ending in proportion to the temperature, which then kept
    growing).
    """
    return y + (gamma / (1.0 - gamma)) * done * (rewards + alpha * entropy)


def clip_target(y: torch.Tensor, reward_max: float, alpha: torch.Tensor, entropy_max: float,
                gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(5)'s target clipped at `soft_q_bound` for the current alpha (--q-target-clip bound), and the share clipped.

    With labels in [0, r_max] no soft Q of the current policy and temperature can exceed the bound,
    so a target above it is the target critics' own overestimate fed back into the critics, which
    is how a run away from the data compounds. The bound uses the alpha the target itself uses
    (a larger one would leave the clip loose). One sampled a' can make -log pi(a'|s') exceed the
    entropy bound, so a few sound targets are cut too: a small downward bias, and never a target
    above what the rewards allow.
    """
    bound = soft_q_bound(reward_max, alpha, entropy_max, gamma)
    return torch.minimum(y, bound), (y > bound).float().mean()


def _adam(params: list[torch.Tensor], lr: float) -> torch.optim.Adam:
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, ValueError):  # a device or dtype without a fused kernel
        return torch.optim.Adam(params, lr=lr)


def as_floats(stats: dict[str, torch.Tensor]) -> dict[str, float]:
    """`Sac.update`'s statistics as Python floats (one device synchronisation)."""
    if not stats:
        return {}
    values = torch.stack(list(stats.values())).tolist()
    return dict(zip(stats, values))


class SacState:
    """What both SAC updates (this one and `sac_discrete.DiscreteSac`) hold under the same names, and so
    save, restore and send to actors the same way: `actor`, `critic`, `critic_target`, `log_alpha`,
    their three optimisers, the divergence `watch` and the networks' `arch()`."""

    actor: nn.Module
    critic: nn.Module
    critic_target: nn.Module
    log_alpha: torch.Tensor
    critic_opt: torch.optim.Optimizer
    actor_opt: torch.optim.Optimizer
    alpha_opt: torch.optim.Optimizer
    watch: QBoundWatch

    def arch(self) -> dict:
        raise NotImplementedError

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    @property
    def q_bound_exceeded(self) -> torch.Tensor:
        return self.watch.exceeded

    # -- weights for actors -------------------------------------------------------
    def actor_arrays(self) -> dict[str, np.ndarray]:
        return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in self.actor.state_dict().items()}

    # -- checkpoints ---------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "log_alpha": self.log_alpha.detach().cpu(),
            "critic_opt": self.critic_opt.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "arch": self.arch(),
            "critic_norm": self.hp.critic_norm,
            "q_bound_watch": self.watch.state_dict(),
        }

    def load_state_dict(self, sd: dict) -> None:
        saved_norm = sd.get("critic_norm", "none")  # absent from checkpoints written before the option
        if saved_norm != self.hp.critic_norm:
            raise ValueError(f"the checkpoint's critics have --critic-norm {saved_norm}, this run's "
                             f"--critic-norm {self.hp.critic_norm}")
        for name in ("actor", "critic", "critic_target"):
            getattr(self, name).load_state_dict(sd[name])
        with torch.no_grad():
            self.log_alpha.copy_(sd["log_alpha"])
        for name in ("critic_opt", "actor_opt", "alpha_opt"):
            getattr(self, name).load_state_dict(sd[name])
        self.watch.load_state_dict(sd.get("q_bound_watch"))


class Sac(SacState):
    """Networks, optimizers and the update. `update(batch)` is one gradient step on everything."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int], hp: SacHyper, device: torch.device) -> None:
        self.hp = hp
        self.device = device
        self.obs_dim, self.act_dim, self.hidden = obs_dim, act_dim, list(hidden)
        self.actor = Actor(obs_dim, act_dim, hidden, tanh_log_prob=hp.tanh_log_prob).to(device)
        self.critic = TwinCritic(obs_dim, act_dim, hidden, hp.critic_norm).to(device)
        self.critic_target = TwinCritic(obs_dim, act_dim, hidden, hp.critic_norm).to(device)
        self.critic_target.load_state_dict(self.critic.state_dict())
        for p in self.critic_target.parameters():
            p.requires_grad_(False)
        self.log_alpha = torch.tensor(float(np.log(hp.init_alpha)), device=device, requires_grad=True)
        self.target_entropy = float(-act_dim if hp.target_entropy is None else hp.target_entropy)
        # One Adam over both critics equals the official two (Adam is per-parameter);
        # clipping stays per critic. Fused Adam does each step in one kernel per
        # parameter group: the same maths, a quarter of a CPU update's time saved.
        self.critic_params = list(self.critic.parameters())
        self.target_params = list(self.critic_target.parameters())
        self.critic_opt = _adam(self.critic_params, hp.lr)
        self.actor_opt = _adam(list(self.actor.parameters()), hp.lr)
        self.alpha_opt = _adam([self.log_alpha], hp.lr)
        # Divergence watch (`q_bound`): actions in [-1, 1]^d have at most d log 2 of entropy.
        self.watch = QBoundWatch(act_dim * LOG2, hp, device)

    def update(self, obs, actions, rewards, next_obs, terminated, truncated,
               expert_from: int | None = None) -> dict[str, torch.Tensor]:
        """One SAC step on a batch of tensors already on `self.device` (rewards per eq. 3); rows from
        `expert_from` on are D_E's (None: the batch has none).

        Returns the step's statistics as 0-dim tensors on the device: reading them
        (`as_floats`) waits for the device, so callers do it only when they report.
        """
        hp = self.hp
        alpha = self.log_alpha.exp().detach()
        done = terminated if not hp.time_limit_terminal else torch.maximum(terminated, truncated)

        # (5) soft target from the target critics at a' ~ pi(.|s')
        with torch.no_grad():
            next_a, next_logp = self.actor.sample(next_obs)
            q_next = torch.min(*self.critic_target(next_obs, next_a))
            y = rewards + hp.gamma * (1.0 - done) * (q_next - alpha * next_logp)
            if hp.absorbing_terminal:
                y = absorbing(y, rewards, done, alpha, -next_logp.mean(), hp.gamma)
            if hp.target_reward_max is not None:  # --q-target-clip bound: no target above what the labels allow
                y, clipped = clip_target(y, hp.target_reward_max, alpha, self.watch.entropy_max, hp.gamma)

        # (4) critic loss over the concatenated D_O and D_E halves
        q1, q2 = self.critic(obs, actions)
        q1_loss = F.mse_loss(q1, y)
        q2_loss = F.mse_loss(q2, y)
        self.critic_opt.zero_grad(set_to_none=True)
        (q1_loss + q2_loss).backward()
        if hp.grad_clip > 0:
            self.critic.clip_grad_norm_(hp.grad_clip)
        self.critic_opt.step()

        # (6) policy loss against the just-updated critics; the critics' own parameter
        # gradients are not needed here, so autograd is told not to compute them.
        for p in self.critic_params:
            p.requires_grad_(False)
        a, logp = self.actor.sample(obs)
        q_pi = torch.min(*self.critic(obs, a))
        actor_loss = (alpha * logp - q_pi).mean()
        if hp.bc_weight > 0 and expert_from is not None:  # --bc-weight: imitate D_E's actions, scaled by mean |Q|
            bc_loss = F.mse_loss(self.actor.mean_action(obs[expert_from:]), actions[expert_from:])
            actor_loss = actor_loss + hp.bc_weight * q_pi.detach().abs().mean() * bc_loss
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        for p in self.critic_params:
            p.requires_grad_(True)
        if hp.grad_clip > 0:
            nn.utils.clip_grad_norm_(self.actor.parameters(), hp.grad_clip)
        self.actor_opt.step()

        # temperature, with the log-probabilities of the actor step above
        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        self.alpha_opt.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_opt.step()

        # Polyak averaging of the target critics: target += tau * (online - target)
        with torch.no_grad():
            torch._foreach_lerp_(self.target_params, self.critic_params, hp.tau)
            q_max, q_bound = self.watch.see(torch.maximum(q1, q2).max(), rewards, alpha)

        stats = {
            "critic_loss": (q1_loss + q2_loss).detach() / 2,
            "actor_loss": actor_loss.detach(),
            "alpha": alpha,
            "alpha_loss": alpha_loss.detach(),
            "q_mean": q1.detach().mean(),
            "q_max": q_max,
            "target_q_mean": y.mean(),
            "log_pi_mean": logp.detach().mean(),
            "entropy": -logp.detach().mean(),
            "q_bound": q_bound,
        }
        if hp.target_reward_max is not None:
            stats["q_target_clipped"] = clipped
        if hp.bc_weight > 0 and expert_from is not None:
            stats["bc_loss"] = bc_loss.detach()
        return stats

    def arch(self) -> dict:
        return {"obs_dim": self.obs_dim, "act_dim": self.act_dim, "hidden": self.hidden}
