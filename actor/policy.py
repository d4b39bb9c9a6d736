"""The actors' copy of the policy, in NumPy.

Actors never import torch: inference at batch size 1-16 on 800-400 layers is a
few matrix-vector products, NumPy does them as fast, and an actor process stays
small (no torch runtime, no thread pool fighting the learner for the 2 cores).
The layout mirrors `learner.sac.Actor`'s state_dict; a test checks both agree.
"""

from __future__ import annotations

import numpy as np

from silcr.common.protocol import ProtocolError, Weights

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


class NumpyPolicy:
    def __init__(self, weights: Weights, obs_dim: int, act_dim: int) -> None:
        p = weights.params
        self.version = weights.version
        layers = []
        i = 0
        while f"trunk.{i}.weight" in p:
            layers.append((p[f"trunk.{i}.weight"].T.copy(), p[f"trunk.{i}.bias"].copy()))
            i += 2  # Linear, ReLU, Linear, ReLU, ...
        try:
            self.mean = (p["mean.weight"].T.copy(), p["mean.bias"].copy())
            self.log_std = (p["log_std.weight"].T.copy(), p["log_std.bias"].copy())
        except KeyError as e:
            raise ProtocolError("bad_field", f"weights lack {e.args[0]!r}") from None
        if not layers:
            raise ProtocolError("bad_field", "weights have no hidden layers")
        if any(w.ndim != 2 or b.ndim != 1 for w, b in [*layers, self.mean, self.log_std]):
            raise ProtocolError("bad_shape", "weights need 2-D matrices and 1-D biases")
        if layers[0][0].shape[0] != obs_dim or self.mean[0].shape[1] != act_dim:
            raise ProtocolError(
                "bad_shape",
                f"weights are for obs {layers[0][0].shape[0]} / act {self.mean[0].shape[1]}, env has {obs_dim} / {act_dim}",
            )
        for (w, b), (w2, _) in zip(layers, layers[1:] + [self.mean]):
            if w.shape[1] != b.shape[0] or w.shape[1] != w2.shape[0]:
                raise ProtocolError("bad_shape", "weights' layer shapes do not chain")
        for name, (w, b) in (("mean", self.mean), ("log_std", self.log_std)):
            if w.shape != self.mean[0].shape or b.shape != (act_dim,):
                raise ProtocolError("bad_shape", f"the {name} head is {w.shape[0]} -> {w.shape[1]} with {b.shape[0]} biases, "
                                                 f"expected {self.mean[0].shape[0]} -> {act_dim}")
        self.layers = layers
        # Both heads in one matmul: one BLAS call fewer per step, and the heads' output
        # is a single array the sampling below works on in place.
        self.act_dim = act_dim
        self.head_w = np.ascontiguousarray(np.concatenate([self.mean[0], self.log_std[0]], axis=1))
        self.head_b = np.concatenate([self.mean[1], self.log_std[1]])

    def _heads(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # In place after each matmul: at batch 1-16 the temporaries of `relu(h @ w + b)`
        # cost as much as the small layers themselves.
        h = np.asarray(obs, dtype=np.float32)
        for w, b in self.layers:
            h = h @ w
            h += b
            np.maximum(h, 0.0, out=h)
        out = h @ self.head_w
        out += self.head_b
        mean, log_std = out[..., : self.act_dim], out[..., self.act_dim :]
        np.clip(log_std, LOG_STD_MIN, LOG_STD_MAX, out=log_std)
        return mean, log_std

    def sample(self, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Stochastic action tanh(mean + std * noise) in [-1, 1], as the learner's `Actor.sample`."""
        mean, log_std = self._heads(obs)
        u = np.exp(log_std)
        u *= rng.standard_normal(mean.shape, dtype=np.float32)
        u += mean
        return np.tanh(u, out=u)

    def deterministic(self, obs: np.ndarray) -> np.ndarray:
        return np.tanh(self._heads(obs)[0])


def initial_weights(obs_dim: int, act_dim: int, hidden: list[int], seed: int) -> Weights:
    """PyTorch's default Linear init (uniform +-1/sqrt(fan_in)), for an actor with no learner yet."""
    rng = np.random.default_rng(seed)
    params: dict[str, np.ndarray] = {}
    sizes = [obs_dim, *hidden]

    def linear(name: str, fan_in: int, fan_out: int) -> None:
        bound = 1.0 / np.sqrt(fan_in)
        params[f"{name}.weight"] = rng.uniform(-bound, bound, (fan_out, fan_in)).astype(np.float32)
        params[f"{name}.bias"] = rng.uniform(-bound, bound, fan_out).astype(np.float32)

    for i in range(len(hidden)):
        linear(f"trunk.{2 * i}", sizes[i], sizes[i + 1])
    linear("mean", hidden[-1], act_dim)
    linear("log_std", hidden[-1], act_dim)
    return Weights(-1, params, {"obs_dim": obs_dim, "act_dim": act_dim, "hidden": list(hidden)})
