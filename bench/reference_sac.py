"""The reference the learner benchmark compares against: a SAC update written the obvious way.

Same networks, batch, optimiser and maths as `learner.sac.Sac.update`, in the
style of the official code and CleanRL: separate critic modules and optimizers,
the actor loss backpropagated through the critics with their parameter
gradients computed and thrown away, default Adam.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from silcr.learner.sac import Actor, mlp


class Critic(nn.Module):
    """One Q network, as the official code writes it."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int]) -> None:
        super().__init__()
        self.net = nn.Sequential(mlp([obs_dim + act_dim, *hidden]), nn.Linear(hidden[-1], 1))

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, act], -1)).squeeze(-1)


class PlainSac:
    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int], device: torch.device, tau: float = 0.05) -> None:
        self.actor = Actor(obs_dim, act_dim, hidden, inplace=False).to(device)
        self.q1, self.q2 = Critic(obs_dim, act_dim, hidden).to(device), Critic(obs_dim, act_dim, hidden).to(device)
        self.q1_t, self.q2_t = Critic(obs_dim, act_dim, hidden).to(device), Critic(obs_dim, act_dim, hidden).to(device)
        self.q1_t.load_state_dict(self.q1.state_dict())
        self.q2_t.load_state_dict(self.q2.state_dict())
        self.q1_opt = torch.optim.Adam(self.q1.parameters(), lr=3e-4)
        self.q2_opt = torch.optim.Adam(self.q2.parameters(), lr=3e-4)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=3e-4)
        self.log_alpha = torch.zeros((), device=device, requires_grad=True)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=3e-4)
        self.target_entropy = -float(act_dim)
        self.tau, self.gamma = tau, 0.99

    def update(self, obs, act, rew, next_obs, term, trunc) -> None:
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            na, nlogp = self.actor.sample(next_obs)
            y = rew + self.gamma * (1 - term) * (torch.min(self.q1_t(next_obs, na), self.q2_t(next_obs, na)) - alpha * nlogp)
        for q, opt in ((self.q1, self.q1_opt), (self.q2, self.q2_opt)):
            loss = F.mse_loss(q(obs, act), y)
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(q.parameters(), 40)
            opt.step()
        a, logp = self.actor.sample(obs)
        actor_loss = (alpha * logp - torch.min(self.q1(obs, a), self.q2(obs, a))).mean()
        self.actor_opt.zero_grad()
        actor_loss.backward()
        nn.utils.clip_grad_norm_(self.actor.parameters(), 40)
        self.actor_opt.step()
        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        self.alpha_opt.zero_grad()
        alpha_loss.backward()
        self.alpha_opt.step()
        with torch.no_grad():
            for net, tgt in ((self.q1, self.q1_t), (self.q2, self.q2_t)):
                for p, tp in zip(net.parameters(), tgt.parameters()):
                    tp.mul_(1 - self.tau).add_(p, alpha=self.tau)


def update_flops(obs_dim: int, act_dim: int, hidden: list[int], batch: int) -> float:
    """Matmul FLOPs of one SAC update (forward 2*B*in*out per layer; backward twice that).

    Counts what the update must do: target actor and 2 target critics forward on s';
    2 critics forward and backward; actor forward and backward plus 2 critics forward
    and backward to their inputs only (no critic parameter gradients are needed).
    No network needs the gradient with respect to its first layer's input except the
    critics in the actor step (that is d Q / d a), so those products are not counted.
    A test checks this against the matmuls autograd really runs.
    """
    def fwd(sizes: list[int]) -> float:
        return sum(2.0 * batch * a * b for a, b in zip(sizes, sizes[1:]))

    actor = fwd([obs_dim, *hidden]) + 2 * fwd([hidden[-1], act_dim])
    critic = fwd([obs_dim + act_dim, *hidden, 1])
    target = actor + 2 * critic
    actor_in = fwd([obs_dim, hidden[0]])
    critic_in = fwd([obs_dim + act_dim, hidden[0]])
    critic_step = 2 * (critic + 2 * critic - critic_in)
    actor_step = (actor + 2 * actor - actor_in) + 2 * (critic + critic)
    return target + critic_step + actor_step


def matmul_gflops(device: torch.device, seconds: float = 1.0) -> float:
    """Measured fp32 matmul throughput at the paper's layer shape (256x800 @ 800x400)."""
    a = torch.randn(256, 800, device=device)
    b = torch.randn(800, 400, device=device)
    flops = 2.0 * 256 * 800 * 400
    for _ in range(20):
        a @ b
    n, t0 = 0, _now(device)
    while _now(device) - t0 < seconds:
        for _ in range(50):
            a @ b
        n += 50
    return flops * n / (_now(device) - t0) / 1e9


def _now(device: torch.device) -> float:
    import time

    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter()


def random_batch(obs_dim: int, act_dim: int, batch: int, device: torch.device, seed: int = 0):
    g = np.random.default_rng(seed)
    t = lambda x: torch.as_tensor(x, dtype=torch.float32, device=device)  # noqa: E731
    return (
        t(g.normal(size=(batch, obs_dim))), t(g.uniform(-1, 1, (batch, act_dim))), t(g.integers(0, 2, batch)),
        t(g.normal(size=(batch, obs_dim))), t(g.random(batch) < 0.01), t(np.zeros(batch)),
    )


_MATMULS = ("mm", "addmm", "bmm", "baddbmm")


def record_matmuls(step: Callable[[], None]) -> list[tuple[Any, list[tuple[tuple[int, ...], tuple[int, ...]]]]]:
    """Every matrix multiply one call of `step` runs (backward included), with its operands' shapes and strides."""
    from torch.utils._python_dispatch import TorchDispatchMode

    calls: list[tuple[Any, list[tuple[tuple[int, ...], tuple[int, ...]]]]] = []

    class Recorder(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.overloadpacket.__name__ in _MATMULS:
                calls.append((func, [(tuple(a.shape), tuple(a.stride())) for a in args if isinstance(a, torch.Tensor)]))
            return func(*args, **(kwargs or {}))

    with Recorder():
        step()
    return calls


def matmul_only_rate(calls, device: torch.device, seconds: float = 1.0) -> float:
    """Replays of the recorded matmuls per second: an update's rate if everything else took no time.

    This is the ceiling at the update's own shapes (batch 128 and thin layers run
    below the peak shape's throughput), with the operands' memory layouts kept.
    """
    ops = []
    for func, operands in calls:
        tensors = []
        for shape, stride in operands:
            # one storage that covers the view, so broadcast (stride-0) operands stay broadcast
            size = 1 + sum((n - 1) * st for n, st in zip(shape, stride))
            tensors.append(torch.randn(size, device=device).as_strided(shape, stride))
        ops.append((func, tensors))

    def replay() -> None:
        for func, tensors in ops:
            func(*tensors)

    for _ in range(3):
        replay()
    n, t0 = 0, _now(device)
    while _now(device) - t0 < seconds:
        replay()
        n += 1
    return n / (_now(device) - t0)
